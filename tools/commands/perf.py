"""Time the firmware tick on recorded inputs, count its allocations, size its state.

The inputs are the frames a firmware received during a bench run (a log from
``coiltrack bench --log PATH``, or a run of ``--scenario`` recorded in
memory). They are replayed into a fresh firmware on a virtual clock
(``tools.bench.framelog``): the same tick sees the same bytes, so the timing is of
the firmware alone. Reported, after a warm-up:

* the tick time (median, p99, max) overall, over the ticks that processed an
  IMU sample (the "fused tick") and per stage (receive, actuate, measure,
  track, supervise, transmit; ``loop.PHASES``); Python's garbage
  collector is frozen after start-up (``gc.freeze``), as a board has none;
* the tick's CPU time (``time.thread_time_ns``: the time the replaying
  thread ran, so a preemption by another process on a shared machine does
  not count; keys ``tick_cpu_us_*``, ``cpu_deadline_misses``) beside the
  wall-clock figures, which include it;
* the interpreter's garbage collections inside the measured ticks and the longest one's CPU
  time (``gc_collections_in_ticks``, ``gc_us_max``), which the tick times include; with
  ``--worst N`` the N ticks of the most CPU time, each with its stage times, field evaluations,
  collections and the tracker's sensor and pose-solver unit before it;
* what the machine did around each tick (``machine``; ``tools.bench.tick_noise``): page faults,
  context switches inside and just before the tick and core changes, read with
  ``getrusage(RUSAGE_THREAD)`` outside the timed window, and the CPU figures of the ticks none of
  these touched (``machine.undisturbed``), so a maximum reached only by disturbed ticks is told
  from the firmware's own; the worst ticks carry their row and work class. The recorder keeps
  its per-tick figures in arrays made before the replay: records kept as new Python objects
  grow the interpreter's heap, and the firmware's short-lived objects then land on pages touched
  for the first time inside its timed ticks (a page fault each, counted as firmware time);
* with ``--repeat N`` the log replayed N times and compared tick by tick (``repeat``): each tick's
  least CPU time over the replays (the firmware's work; the machine's noise does not repeat at
  the same virtual time) and whether the costliest ticks stay or move;
* numpy array allocations per tick (``tools.bench.alloc.NumpyAllocationCounter``,
  a second replay);
* the firmware state in bytes: the data of every numpy array and byte buffer
  the firmware owns, as a board's RAM budget would count it (Python object
  headers excluded);
* one step of the fusion filter (strapdown + covariance prediction) and one
  magnetic update against the same steps written with filterpy
  (``KalmanFilter.predict`` / ``update`` with the filter's own ``A``, ``Q``,
  ``H``, ``R``).
"""
from __future__ import annotations

import sys
import time

import numpy as np

from .. import args as A
from .. import scenarios
from ..bench.alloc import NumpyAllocationCounter, available
from ..bench.framelog import replay, load
from ..bench.tick_noise import FIELDS as MACHINE_FIELDS, MachineProbe, recurrence, summarise as machine_summary
from ..bench.work_classes import TickWork, summarise

HELP = "time the firmware tick on recorded inputs (per phase, allocations, state bytes, filterpy comparison)"


def add_arguments(p) -> None:
    p.add_argument("--log", type=A.input_file, metavar="PATH",
                   help="frame log from `coiltrack bench --log` (default: record a run)")
    p.add_argument("--scenario", type=scenarios.known, default="roetenberg-fusion",
                   help="scenario to record when no --log is given (default roetenberg-fusion)")
    p.add_argument("--seed", type=A.seed, default=1, help="0..2^32-1 (default 1)")
    p.add_argument("--duration", type=A.bench_seconds, default=30.0,
                   help=f"seconds to record, (0, {A.MAX_BENCH_S:g}] (default 30)")
    p.add_argument("--warmup", type=A.real(0.0, A.MAX_BENCH_S), default=5.0,
                   help="seconds excluded from the statistics (default 5)")
    p.add_argument("--json", type=A.output_path, metavar="PATH", help="write the figures as JSON")
    p.add_argument("--core", choices=("compiled", "python"), default=None,
                   help="the firmware's numeric core ([core] impl; default the configuration's: compiled "
                        "where the extension is built)")
    p.add_argument("--worst", type=A.integer(0, 1000), default=0, metavar="N",
                   help="also list the N ticks of the most CPU time: stage times, field evaluations, the "
                        "tracker's sensor and garbage collections in each (default 0: none)")
    p.add_argument("--repeat", type=A.integer(1, 20), default=1, metavar="N",
                   help="replay the log N times in this process (1-20, default 1) and compare the replays tick by "
                        "tick: each tick's minimum CPU time over them (the firmware's work) and whether the costliest "
                        "ticks stay at the same time (the firmware's) or move (the machine's); the other figures are "
                        "the first replay's")
    p.add_argument("--solver", choices=("lm", "raab", "both"),
                   help="also replay with this pose solver ([pose] pose_solver) and report its cost per update: "
                        "field evaluations and time of each burst's solve; 'both': Raab's beside the LM's")


# ---------------------------------------------------------------------------
def state_bytes(fw) -> tuple[int, dict]:
    """Bytes of array data and byte buffers reachable from the firmware
    (objects of ``firmware_py`` and ``protocol``; shared buffers counted once),
    total and per top-level attribute."""
    seen: set[int] = set()

    def walk(obj, depth: int) -> int:
        if depth > 12:
            return 0
        oid = id(obj)
        if oid in seen:
            return 0
        seen.add(oid)
        if isinstance(obj, np.ndarray):
            base = obj
            while base.base is not None and isinstance(base.base, np.ndarray):
                base = base.base
            if id(base) in seen and base is not obj:
                return 0
            seen.add(id(base))
            return int(base.nbytes)
        if isinstance(obj, (bytearray, bytes)):
            return len(obj)
        if isinstance(obj, dict):
            return sum(walk(v, depth + 1) for v in obj.values())
        if isinstance(obj, (list, tuple, set)):
            return sum(walk(v, depth + 1) for v in obj)
        mod = getattr(type(obj), "__module__", "") or ""
        if not mod.startswith(("coiltrack.firmware", "coiltrack.protocol")):
            return 0
        total = 0
        d = getattr(obj, "__dict__", None)
        if d:
            total += sum(walk(v, depth + 1) for v in d.values())
        for cls in type(obj).__mro__:
            for name in getattr(cls, "__slots__", ()):
                if hasattr(obj, name):
                    total += walk(getattr(obj, name), depth + 1)
        return total

    seen.add(id(fw.port))
    parts = {}
    for name, v in vars(fw).items():
        if name in ("port", "cfg", "prof"):
            continue
        b = walk(v, 1)
        if b:
            parts[name] = b
    return sum(parts.values()), dict(sorted(parts.items(), key=lambda kv: -kv[1]))


def instances(fw, cls) -> list:
    """Every object of type ``cls`` reachable from the firmware's attributes."""
    seen: set[int] = set()
    found = []

    def walk(obj, depth: int) -> None:
        if depth > 12 or id(obj) in seen:
            return
        seen.add(id(obj))
        if isinstance(obj, cls):
            found.append(obj)
            return
        if isinstance(obj, dict):
            for v in obj.values():
                walk(v, depth + 1)
        elif isinstance(obj, (list, tuple)):
            for v in obj:
                walk(v, depth + 1)
        elif (getattr(type(obj), "__module__", "") or "").startswith("coiltrack.firmware"):
            for v in getattr(obj, "__dict__", {}).values():
                walk(v, depth + 1)

    walk(fw, 0)
    return found


def _stats(a_ns) -> dict:
    a = np.asarray(a_ns, dtype=float) / 1e3
    if a.size == 0:
        return {"median": None, "p99": None, "p999": None, "max": None, "n": 0}
    return {"median": round(float(np.median(a)), 2), "p99": round(float(np.percentile(a, 99)), 2),
            "p999": round(float(np.percentile(a, 99.9)), 2), "max": round(float(a.max()), 2), "n": int(a.size)}


def _with_core(cfg, core):
    """``cfg`` with ``[core] impl = core`` (``--core``), or ``cfg`` itself when ``core`` is None."""
    if core is None:
        return cfg
    import dataclasses

    return cfg.with_(core={"impl": core})


def _record(scenario: str, seed: int, duration: float, core=None):
    # imported where used: the world's physics (magpylib) loads only when a run starts
    from ..bench.runner import record_log

    sc = scenarios.get(scenario)
    return record_log(sc, seed, duration, _with_core(sc.firmware_config(), core))


def _filter_steps(fw) -> dict:
    """Median time of one fusion step and one magnetic update, ours and filterpy's."""
    out = {}
    ins = getattr(fw.tracker, "inertial", {})
    fus = next((i.fusion for i in ins.values() if i.fusion.initialized), None)
    if fus is None:
        return out
    k = fus.imu.last_pushed_slot()
    t1 = int(fus.imu.tv[k])
    t0 = t1 - int(1e6 / fw.cfg.imu.imu_rate_hz)
    saved = (fus.p.copy(), fus.v.copy(), fus.Th.copy(), fus.ba.copy(), fus.bg.copy(), fus.P.copy())
    n = 2000
    ts = np.zeros(n, dtype=np.int64)
    for i in range(n):
        a = time.perf_counter_ns()
        fus._step(k, t0, t1)
        ts[i] = time.perf_counter_ns() - a
    out["fused_step_us"] = round(float(np.median(ts)) / 1e3, 2)
    A, Q = fus.pred.A.copy(), fus.pred.Q.copy()
    upd = fus.upd
    P0 = saved[5]
    tu = np.zeros(200, dtype=np.int64)
    for i in range(200):
        np.copyto(fus.P, P0)
        upd.y[:] = 0.0
        a = time.perf_counter_ns()
        upd.update(fus.P)
        tu[i] = time.perf_counter_ns() - a
    out["fused_update_us"] = round(float(np.median(tu)) / 1e3, 2)
    np.copyto(fus.p, saved[0])
    np.copyto(fus.v, saved[1])
    np.copyto(fus.Th, saved[2])
    np.copyto(fus.ba, saved[3])
    np.copyto(fus.bg, saved[4])
    np.copyto(fus.P, saved[5])
    out["filter_states"] = fus.n
    out["update_dim"] = fus.m
    try:
        from filterpy.kalman import KalmanFilter
    except ImportError:          # an optional package: the comparison is marked absent
        out.update(filterpy_step_us=None, filterpy_update_us=None, filterpy="absent (pip install filterpy)")
        return out
    kf = KalmanFilter(dim_x=fus.n, dim_z=fus.m)
    kf.F = A
    kf.Q = Q
    kf.P = P0.copy()
    kf.H = upd.H.copy()
    kf.R = upd.R.copy()
    tp = np.zeros(n, dtype=np.int64)
    for i in range(n):
        a = time.perf_counter_ns()
        kf.predict()
        tp[i] = time.perf_counter_ns() - a
    out["filterpy_step_us"] = round(float(np.median(tp)) / 1e3, 2)
    z = np.zeros(fus.m)
    tq = np.zeros(200, dtype=np.int64)
    for i in range(200):
        kf.P = P0.copy()
        a = time.perf_counter_ns()
        kf.update(z)
        tq[i] = time.perf_counter_ns() - a
    out["filterpy_update_us"] = round(float(np.median(tq)) / 1e3, 2)
    return out


def field_eval_ns(fw, n: int = 3000) -> float:
    """Median time of one field evaluation (``SignalModel.measure`` of the tracker's coils at a
    point 0.3 m out, divided by the coils), ns: the budget's unit in this machine's time now."""
    from coiltrack.firmware.model.signal import SignalModel

    models = instances(fw, SignalModel)
    if not models:
        return float("nan")
    m = models[0]
    R = memoryview(np.eye(3))
    cur = [1.0] * m.n
    h = memoryview(np.zeros(3 * m.n))
    H = memoryview(np.zeros(18 * m.n))
    ts = np.zeros(n, dtype=np.int64)
    clk = time.perf_counter_ns
    e0 = m.evals
    for i in range(n):
        a = clk()
        m.measure(0.3, 0.1, 0.05, R, cur, h, H)
        ts[i] = clk() - a
    m.evals = e0                     # not the firmware's work
    return float(np.median(ts)) / m.n


def signing_cost(n: int = 2000) -> dict:
    """Median time to encode one COIL_PULSE_CMD frame unsigned and signed (HMAC-SHA256, as the
    firmware does with ``signing_key``), in us, over ``n`` frames each."""
    from coiltrack.protocol import MSG, FrameEncoder, SignedFrameEncoder, Signer

    cmd = MSG["COIL_PULSE_CMD"]
    fields = [f.name for f in cmd.DEF.fields]
    msg = cmd(**{f: 1 for f in fields}) if fields else cmd()
    plain, signed = FrameEncoder(1), SignedFrameEncoder(1, Signer(bytes(range(32)), 1))
    out = {}
    for name, enc in (("command_encode_us_median", lambda k: plain.encode(msg)),
                      ("command_sign_us_median", lambda k: signed.encode(msg, 1_000_000 + k))):
        ts = np.zeros(n, dtype=np.int64)
        for k in range(n):
            a = time.perf_counter_ns()
            enc(k)
            ts[k] = time.perf_counter_ns() - a
        out[name] = round(float(np.median(ts)) / 1e3, 2)
    out["command_sign_overhead_us"] = round(out["command_sign_us_median"] - out["command_encode_us_median"], 2)
    return out


def _tracker_at(fw) -> str:
    """Which piece of the tracker's work a tick is at: the index of the sensor being solved
    (``sensor k/n``) and the pose solver's next unit, where the tracker has them."""
    tr = fw.tracker
    parts = []
    k = getattr(tr, "_next", None)
    chans = getattr(tr, "channels", ())
    if isinstance(k, int) and k >= 0 and chans:
        parts.append(f"sensor {k}/{len(chans)} (node {chans[k].node})")
    unit = getattr(getattr(tr, "solver", None), "next_unit", None)
    if unit is not None:
        parts.append(getattr(unit, "__name__", str(unit)).lstrip("_"))
    return ", ".join(parts) or "-"


class _TickRecorder:
    """Times every tick of a replay (wall and CPU, each stage, the tick's work class, what the
    machine did around it: :class:`~coiltrack.tools.bench.tick_noise.MachineProbe`) after
    ``warm`` us, and the interpreter's garbage collections inside them; with ``worst`` each
    tick's tracker position for ``worst_ticks``.

    Every per-tick figure goes into arrays allocated here for ``capacity`` ticks (the replay's
    tick count), not into growing lists of new Python objects: a harness whose own records
    grow the interpreter's heap tick after tick makes the firmware's short-lived objects
    land on pages never touched before, and the page faults that follow count in the
    firmware's tick time."""

    def __init__(self, warm: int, worst: int, core, capacity: int = 0):
        from coiltrack.firmware.loop import PHASES

        self.warm, self.worst, self.core = warm, worst, core
        self.prof = np.zeros(len(PHASES), dtype=np.int64)
        self.work = {"evals": 0, "replay": 0}
        self.n = 0                                     # measured ticks so far
        self.blocks0 = None                            # the interpreter's live blocks before the first measured tick
        self._grow(max(int(capacity), 1))
        self._codes = {"kind": {}, "at": {}}           # work class / tracker position -> its index in the arrays
        self.probe = MachineProbe()                    # page faults, context switches and the core around each tick
        self.gcs = 0
        self.gc_ns = []                                # CPU time of each collection the measured ticks ran
        self._gc_t0 = 0
        self.in_tick = False
        self.fw = None
        self.eval_ns_before = 0.0

    def _grow(self, size: int) -> None:
        """Arrays for ``size`` measured ticks (the first ``self.n`` rows kept), each written through."""
        from coiltrack.firmware.loop import PHASES

        def arr(shape, dtype, old=None):
            a = np.zeros(shape, dtype=dtype)
            a.reshape(-1)[:] = 0                       # touched now, not during a timed tick
            if old is not None:
                a[:self.n] = old[:self.n]
            return a

        g = getattr(self, "_cpu", None) is not None
        self._cpu = arr(size, np.int64, self._cpu if g else None)
        self._wall = arr(size, np.int64, self._wall if g else None)
        self._t = arr(size, np.int64, self._t if g else None)
        self._phase = arr((size, len(PHASES)), np.int64, self._phase if g else None)
        self._mach = arr((size, len(MACHINE_FIELDS)), np.int64, self._mach if g else None)
        # per tick: IMU sample received, work class, field evaluations, collections, tracker position
        self._small = arr((size, 5), np.int32, self._small if g else None)

    def on_gc(self, phase, info) -> None:
        if phase == "start":
            self.gcs += 1
            self._gc_t0 = time.thread_time_ns()
        elif self.in_tick:
            self.gc_ns.append(time.thread_time_ns() - self._gc_t0)

    # the measured ticks' figures, as the report reads them
    @property
    def cpu_ns(self):
        return self._cpu[:self.n]

    @property
    def tick_ns(self):
        return self._wall[:self.n]

    @property
    def t_us(self):
        return self._t[:self.n]

    @property
    def imu_ticks(self):
        return self._wall[:self.n][self._small[:self.n, 0] > 0]

    @property
    def phase_ns(self):
        return self._phase[:self.n].T

    @property
    def machine(self):
        return self._mach[:self.n]

    @property
    def kinds(self) -> list:
        names = {v: k for k, v in self._codes["kind"].items()}
        return [names[int(c)] for c in self._small[:self.n, 1]]

    @property
    def per_tick(self) -> list:
        """--worst: (CPU, t, wall, stages, evaluations, collections, tracker position, machine row, work
        class) per tick."""
        at = {v: k for k, v in self._codes["at"].items()}
        sm = self._small
        kinds = {v: k for k, v in self._codes["kind"].items()}
        return [(int(self._cpu[i]), int(self._t[i]), int(self._wall[i]), tuple(int(x) for x in self._phase[i]),
                 int(sm[i, 2]), int(sm[i, 3]), at.get(int(sm[i, 4]), "-"), tuple(int(x) for x in self._mach[i]),
                 kinds[int(sm[i, 1])]) for i in range(self.n)]

    def _code(self, table: str, name) -> int:
        codes = self._codes[table]
        c = codes.get(name)
        if c is None:
            c = codes[name] = len(codes)
        return c

    def factory(self, cfg, port):
        """The replay's firmware, its ``tick`` timed."""
        from coiltrack.firmware.estimate.magnetic_inertial import FusionFilter
        from coiltrack.firmware.loop import Firmware
        from coiltrack.firmware.model.signal import SignalModel

        fw = Firmware(_with_core(cfg, self.core), port)
        self.fw = fw
        self._models = tuple(instances(fw, SignalModel))     # every field evaluation goes through one of these
        self._filters = tuple(instances(fw, FusionFilter))
        self._tw = TickWork(fw, instances)
        self._real_tick = fw.tick_timed
        self.eval_ns_before = field_eval_ns(fw)
        fw.tick = self.tick
        return fw

    def tick(self, t) -> None:
        fw, rx, models = self.fw, self.fw.receiver, self._models
        n0 = rx.imu_received
        e0 = sum(m.evals for m in models)
        self._tw.begin()
        at = _tracker_at(fw) if self.worst else None
        g0 = self.gcs
        self.in_tick = t >= self.warm
        if self.blocks0 is None and self.in_tick:
            self.blocks0 = sys.getallocatedblocks()
        self.probe.before()
        c = time.thread_time_ns()
        a = time.perf_counter_ns()
        self._real_tick(t, self.prof)
        dt = time.perf_counter_ns() - a
        dc = time.thread_time_ns() - c
        mach = self.probe.after()
        self.in_tick = False
        kind = self._tw.end()
        if t < self.warm:
            return
        i = self.n
        if i == self._cpu.size:
            self._grow(2 * i)
        self.n = i + 1
        self._cpu[i], self._wall[i], self._t[i] = dc, dt, t
        self._phase[i] = self.prof
        self._mach[i] = mach
        ev = sum(m.evals for m in models) - e0
        sm = self._small[i]
        sm[0], sm[1], sm[2], sm[3] = rx.imu_received > n0, self._code("kind", kind), ev, self.gcs - g0
        if self.worst:
            sm[4] = self._code("at", at)
        self.work["evals"] = max(self.work["evals"], ev)
        self.work["replay"] = max(self.work["replay"], max((f.last_step_units for f in self._filters), default=0))


def _timed_replay(header: dict, reads, warm: int, worst: int, core) -> _TickRecorder:
    """One replay of the log through a timed firmware, the collector frozen."""
    import gc

    r = _TickRecorder(warm, worst, core, int(header["duration_s"] * 1e6) // int(header["tick_us"]) + 1)
    # a board has no garbage collector: start-up objects are moved out of the
    # collector's generations, so its pauses do not show as firmware time
    gc.collect()
    gc.freeze()
    gc.callbacks.append(r.on_gc)
    try:
        replay(r.factory, header, reads)
    finally:
        gc.callbacks.remove(r.on_gc)
        gc.unfreeze()
    return r


def measure(header: dict, reads, warmup_s: float = 5.0, worst: int = 0, core=None, repeat: int = 1) -> dict:
    """Replay a recorded run through a timed firmware; the report of ``coiltrack perf``. With
    ``repeat`` > 1 the log is replayed that many times and the replays compared tick by tick
    (``repeat``: :func:`coiltrack.tools.bench.tick_noise.recurrence`); the other figures are
    the first replay's."""
    warm = int(warmup_s * 1e6)
    r = _timed_replay(header, reads, warm, worst, core)
    blocks = sys.getallocatedblocks()
    fw = r.fw
    rep = {"scenario": header.get("scenario"), "seed": header.get("seed"), "duration_s": header["duration_s"],
           "warmup_s": warmup_s, "ticks": len(r.tick_ns), "tick_us": int(header["tick_us"]), "core": fw.core}
    _timing_keys(rep, r)
    # Python objects the measured ticks left alive (the recorder keeps none): a heap that grows tick
    # after tick is memory a board does not have, and its new pages fault inside the ticks
    rep["python_blocks_kept"] = blocks - r.blocks0 if r.blocks0 is not None else None
    total, parts = state_bytes(fw)
    rep["state_bytes"] = total
    rep["state_bytes_by_part"] = parts
    rep.update(signing_cost())
    # the tick's times in the budget's unit: how many field evaluations' time the worst ticks
    # take on this machine now (its speed measured before and after the replay)
    sc = _stats(r.cpu_ns)
    ev = 0.5 * (r.eval_ns_before + field_eval_ns(fw)) / 1e3
    rep["field_eval_us"] = round(ev, 3)
    rep["tick_p999_in_field_evals"] = round(sc["p999"] / ev, 1) if sc["p999"] is not None else None
    rep["tick_max_in_field_evals"] = round(sc["max"] / ev, 1) if sc["max"] is not None else None
    rep["status"] = {k: v for k, v in fw.status().items() if k in ("cycles", "poses", "fused_poses", "fusion_updates")}
    rep.update(_alloc_keys(header, reads, warm, core))
    rep.update(_filter_steps(fw))
    if repeat > 1:
        runs = [r.cpu_ns] + [_timed_replay(header, reads, warm, 0, core).cpu_ns for _ in range(repeat - 1)]
        rep["repeat"] = recurrence(runs, r.t_us, max(worst, 5))
    return rep


def _timing_keys(rep: dict, r: _TickRecorder) -> None:
    """The tick, CPU, work, fused-tick, stage, work-class and collection figures into ``rep``."""
    from coiltrack.firmware.loop import PHASES

    st = _stats(r.tick_ns)
    rep.update({"tick_us_median": st["median"], "tick_us_p99": st["p99"], "tick_us_p999": st["p999"],
                "tick_us_max": st["max"]})
    sc = _stats(r.cpu_ns)
    rep.update({"tick_cpu_us_median": sc["median"], "tick_cpu_us_p99": sc["p99"], "tick_cpu_us_p999": sc["p999"],
                "tick_cpu_us_max": sc["max"],
                "cpu_deadline_misses": int(sum(1 for d in r.cpu_ns if d >= rep["tick_us"] * 1000))})
    # the largest work done in one tick, in machine-independent units, against the configured budget
    cfg = r.fw.cfg
    rep.update({"max_field_evals_per_tick": r.work["evals"], "track_budget_evals": cfg.budget.track_budget_evals,
                "max_replay_steps_per_tick": r.work["replay"], "replay_budget_steps": cfg.budget.replay_budget_steps})
    si = _stats(r.imu_ticks)
    rep.update({"fused_tick_us_median": si["median"], "fused_tick_us_p99": si["p99"], "fused_ticks": si["n"]})
    ph = np.array(r.phase_ns)
    rep["phases_us"] = {}
    for i, name in enumerate(PHASES):
        rep["phases_us"][name] = _stats(ph[i])
        active = ph[i][ph[i] > 2000]          # ticks where the phase did work (> 2 us)
        rep["phases_us"][name]["active_median"] = round(float(np.median(active)) / 1e3, 2) if active.size else None
        rep["phases_us"][name]["active_ticks"] = int(active.size)
    rep["deadline_misses"] = int(sum(1 for d in r.tick_ns if d >= rep["tick_us"] * 1000))
    wc = summarise(r.cpu_ns, r.kinds)
    rep["work_classes"] = wc["classes"]
    rep["p999_work_classes"] = wc["p999_classes"]
    # the interpreter's garbage collections that ran inside measured ticks (a board has none):
    # they count in the tick times above; here they are told apart from the firmware's work
    rep["gc_collections_in_ticks"] = len(r.gc_ns)
    rep["gc_us_max"] = round(max(r.gc_ns) / 1e3, 2) if r.gc_ns else 0.0
    # the machine's share: page faults, context switches and core changes around each tick
    rep["machine"] = machine_summary(r.cpu_ns, r.machine, rep["tick_us"] * 1000)
    if r.worst:
        rows = sorted(r.per_tick, key=lambda x: -x[0])
        rep["worst_ticks"] = [{"t_us": x[1], "cpu_us": round(x[0] / 1e3, 2), "wall_us": round(x[2] / 1e3, 2),
                               "phases_us": {name: round(x[3][i] / 1e3, 2) for i, name in enumerate(PHASES)},
                               "field_evals": x[4], "gc_collections": x[5], "tracker_at": x[6],
                               "machine": dict(zip(MACHINE_FIELDS, x[7])), "work_class": x[8]}
                              for x in rows[:r.worst]]


def _alloc_keys(header: dict, reads, warm: int, core) -> dict:
    """Allocations: a second replay with the counting allocator around every tick."""
    from coiltrack.firmware.loop import Firmware

    if not available():            # pragma: no cover
        return {"allocs_per_tick": None}
    counter = NumpyAllocationCounter()
    counts = []

    def factory2(cfg, port):
        fw2 = Firmware(_with_core(cfg, core), port)
        real_tick = fw2.tick

        def counted(t):
            before = counter.count
            with counter:
                real_tick(t)
            if t >= warm:
                counts.append(counter.count - before)
        fw2.tick = counted
        return fw2

    replay(factory2, header, reads)
    c = np.asarray(counts)
    return {"allocs_per_tick": round(float(c.mean()), 6) if c.size else None,
            "allocs_max_tick": int(c.max()) if c.size else None,
            "ticks_with_allocs": int((c > 0).sum())}


def format_table(rep: dict) -> str:
    lines = [f"  ticks measured        {rep['ticks']} (after {rep['warmup_s']} s warm-up, {rep['tick_us']} us tick)",
             f"  tick                  median {rep['tick_us_median']} us, p99 {rep['tick_us_p99']} us, "
             f"p99.9 {rep['tick_us_p999']} us, max {rep['tick_us_max']} us",
             f"  tick CPU time         median {rep['tick_cpu_us_median']} us, p99 {rep['tick_cpu_us_p99']} us, "
             f"p99.9 {rep['tick_cpu_us_p999']} us, max {rep['tick_cpu_us_max']} us, "
             f"{rep['cpu_deadline_misses']} ticks >= {rep['tick_us']} us (preemption excluded)",
             f"  work in one tick      at most {rep['max_field_evals_per_tick']} field evaluations (budget "
             f"{rep['track_budget_evals']}), {rep['max_replay_steps_per_tick']} replay steps (budget "
             f"{rep['replay_budget_steps']})",
             f"  fused tick (IMU)      median {rep['fused_tick_us_median']} us, p99 {rep['fused_tick_us_p99']} us "
             f"({rep['fused_ticks']} ticks)",
             f"  in the budget's unit  one field evaluation {rep.get('field_eval_us')} us now: the CPU p99.9 is "
             f"{rep.get('tick_p999_in_field_evals')} evaluations' time, the max {rep.get('tick_max_in_field_evals')}"]
    for name, s in rep["phases_us"].items():
        lines.append(f"  {name:<21} median {s['median']} us, p99 {s['p99']} us, max {s['max']} us; "
                     f"when active: median {s['active_median']} us over {s['active_ticks']} ticks")
    lines.append(f"  deadline misses       {rep['deadline_misses']}")
    if rep.get("work_classes"):
        lines.append("  work classes          what a tick did (tools.bench.work_classes), CPU time; costliest maximum first:")
        for name, w in list(rep["work_classes"].items())[:8]:
            lines.append(f"    {name:<32} {w['ticks']:6d} ticks  median {w['cpu_us_median']:7.1f}  "
                         f"p99 {w['cpu_us_p99']:7.1f}  max {w['cpu_us_max']:7.1f} us")
        top = ", ".join(f"{k} {v}" for k, v in rep["p999_work_classes"].items())
        lines.append(f"    at or above the p99.9: {top}")
    lines.append(f"  garbage collections   {rep['gc_collections_in_ticks']} inside measured ticks "
                 f"(the longest {rep['gc_us_max']} us CPU time; counted in the tick times)")
    if rep.get("machine"):
        lines.extend(_machine_lines(rep["machine"]))
    if rep.get("python_blocks_kept") is not None:
        lines.append(f"  Python objects kept   {rep['python_blocks_kept']} interpreter blocks more after the measured "
                     f"ticks than before them")
    lines.append(f"  allocations           {rep.get('allocs_per_tick')} numpy arrays per tick "
                 f"(max {rep.get('allocs_max_tick')} in a tick, {rep.get('ticks_with_allocs')} ticks with any)")
    lines.append(f"  firmware state        {rep['state_bytes']} bytes "
                 f"({', '.join(f'{k} {v}' for k, v in list(rep['state_bytes_by_part'].items())[:6])}, ...)")
    if rep.get("worst_ticks"):
        lines.append(f"  the {len(rep['worst_ticks'])} ticks of the most CPU time (t, CPU, wall, costliest stage, "
                     "field evaluations, garbage collections, the machine: page faults, context switches in / "
                     "before the tick, core changed; work class; tracker before the tick):")
        for w in rep["worst_ticks"]:
            top = max(w["phases_us"].items(), key=lambda kv: kv[1])
            lines.append(f"    t {w['t_us'] / 1e6:9.3f} s  cpu {w['cpu_us']:8.1f} us  wall {w['wall_us']:8.1f} us  "
                         f"{top[0]} {top[1]:.1f} us  evals {w['field_evals']}  gc {w['gc_collections']}  "
                         f"{_machine_cell(w.get('machine'))}  {w.get('work_class', '-')}  {w['tracker_at']}")
    if rep.get("repeat"):
        lines.extend(_repeat_lines(rep["repeat"]))
    if "fused_step_us" in rep:
        ref = rep.get("filterpy")
        lines.append(f"  fusion step           {rep['fused_step_us']} us (strapdown + {rep['filter_states']}-state "
                     f"covariance); filterpy predict {ref or str(rep['filterpy_step_us']) + ' us'}")
        lines.append(f"  magnetic update       {rep['fused_update_us']} us ({rep['update_dim']}-dim, Joseph); "
                     f"filterpy update {ref or str(rep['filterpy_update_us']) + ' us'}")
    return "\n".join(lines)


def _machine_cell(m) -> str:
    """A worst tick's machine columns: ``pf N sw I/B mig`` (faults, switches in / before, core)."""
    if not m:
        return "-"
    return (f"pf {m['minflt'] + m['majflt']}" + (f" ({m['majflt']} major)" if m["majflt"] else "")
            + f"  sw {m['nivcsw'] + m['nvcsw']}/{m['switches_before']}" + ("  moved" if m["migrated"] else ""))


def _machine_lines(m: dict) -> list[str]:
    u, pf = m["undisturbed"], m["page_faults"]
    lines = [f"  the machine           undisturbed ticks (no page fault, context switch or core change in or "
             f"just before): {u['ticks']}, CPU median {u['median']} us, p99.9 {u['p999']} us, max {u['max']} us"
             + (f"; ticks >= the tick: {u['deadline_misses']} undisturbed, {m['disturbed']['deadline_misses']} "
                f"disturbed" if "disturbed" in m else ""),
             f"    page faults           {pf['faults']} ({pf['major']} major) in {pf['ticks']} ticks, "
             f"their CPU max {pf['max']} us (first touch of memory: the process's own)"]
    for key, what in (("preempted", "switched inside"), ("switched_before", "switched just before"),
                      ("migrated", "moved to another core")):
        d = m[key]
        lines.append(f"    {what:<22}{d['ticks']} ticks, their CPU median {d['median']} us, max {d['max']} us")
    w = m.get("worst_disturbed")
    if w:
        lines.append(f"    at or above the p99.9: {w['disturbed']} of {w['ticks']} ticks disturbed "
                     f"({w['page_faults']} with page faults, {w['preempted']} switched inside)")
    return lines


def _repeat_lines(r: dict) -> list[str]:
    mn = r["min_us"]
    lines = [f"  {r['runs']} replays        each tick's least CPU time over them (the firmware's work): "
             f"median {mn['median']} us, p99 {mn['p99']} us, p99.9 {mn['p999']} us, max {mn['max']} us",
             f"    costliest tick at   {', '.join(f'{t / 1e6:.3f}' for t in r['max_at'])} s; of each replay's "
             f"{len(r['worst'])} costliest ticks, the first replay's: {', '.join(str(k) for k in r['worst_kept'])}",
             "    costliest work (t, least CPU, CPU in each replay):"]
    for w in r["worst"]:
        lines.append(f"    t {w['t_us'] / 1e6:9.3f} s  least {w['min_us']:8.1f} us  "
                     + " ".join(f"{c:7.1f}" for c in w["cpu_us"]))
    return lines


def run(args) -> int:
    if args.log:
        log = load("perf", args.log)
        if log is None:
            return 2
        header, reads = log
        if header["duration_s"] <= args.warmup:
            cut = " (what is left of it before the damage)" if header.get("truncated") else ""
            print(f"coiltrack perf: --log {args.log}: {header['duration_s']:.3f} s of reads{cut}, not more than "
                  f"the --warmup {args.warmup:g} s: no tick to measure (give a shorter --warmup)", file=sys.stderr)
            return 2
    else:
        if args.duration <= args.warmup:
            print("coiltrack perf: --duration must exceed --warmup", file=sys.stderr)
            return 2
        header, reads = _record(args.scenario, args.seed, args.duration, args.core)
    rep = measure(header, reads, args.warmup, args.worst, args.core, args.repeat)
    print(f"coiltrack perf: {rep['scenario']} seed {rep['seed']}, {rep['duration_s']} s replayed on a virtual clock")
    print(format_table(rep))
    if args.solver:
        from ..analyses.perf_solvers import format_solver_costs, solver_costs

        rep["pose_solvers"] = solver_costs(header, reads, ("lm", "raab") if args.solver == "both" else (args.solver,),
                                           args.warmup)
        print(format_solver_costs(rep["pose_solvers"]))
    if args.json:
        from ..outputs.jsonout import write

        write(args.json, rep)
        print(f"figures written to {args.json}")
    return 0
