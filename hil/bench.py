"""Assemble a bench (world, nodes with their clocks, faults, recorder,
emulator) and compute its ground-truth checks.

``assemble`` is what ``tools.bench.runner.BenchSetup`` uses for both runners
(in-process simulated clock, two-process wall clock). The checks compare
what the firmware reported (``PULSE_WINDOW``, ``POSE``, ``FAULT_EVENT``
frames) with what really happened (true pulse edges, true sample times),
always on *true* time:

* :func:`window_truth`: for each pulse window the firmware used, the true
  times of its first and last used samples against the flat part of the
  true pulse (after the L/R rise and the eddy transients have settled,
  :meth:`hil.world.World.flat_start_us`, and before the true end edge);
* :func:`pose_latencies`: from the sample that completed a cycle (the first
  sample stamped after the last pulse's end + fall + trailing baseline) to
  the arrival of the pose frame;
* :func:`fault_summary`: what was injected and what the firmware reported.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from coiltrack.protocol import schema
from coiltrack.protocol.schema import NODE_COIL_DRIVER, NODE_SENSOR_BASE, POSE_VALID

from .clock import NodeClock
from .emulator import Emulator
from .faults import BenchFaults, FaultyLink, LinkFaults
from .nodes import CoilDriverNode, ImuSpec, MagSpec, Recorder, SensorNode
from .world import HardIron, MetalObject

#: relative settle tolerance that defines the flat part of a pulse (current and eddy field)
FLAT_TOL = 1e-3


@dataclass
class Bench:
    world: object
    link: object
    driver: CoilDriverNode
    sensors: list
    recorder: Recorder
    emulator: Emulator
    faults: BenchFaults

    @property
    def sensor(self) -> SensorNode:
        return self.sensors[0]


class NodeKinds:
    """The nodes a bench is built of: the pulsed-DC coil driver and sensor nodes
    (:mod:`hil.nodes`). Another excitation brings its own (``hil.ac_nodes.ACNodeKinds``), so
    :func:`assemble` builds the bench once, with the right nodes."""

    def driver(self, node_id: int, world, *, limits, seed: int, clock, faults) -> CoilDriverNode:
        return CoilDriverNode(node_id, world, limits=limits, seed=seed, clock=clock, faults=faults)

    def sensor(self, node_id: int, world, *, mag, imu, seed: int, clock, faults, driver) -> SensorNode:
        """A sensor node (``driver``: the bench's coil driver, for nodes that see its drive)."""
        return SensorNode(node_id, world, mag=mag, imu=imu, seed=seed, clock=clock, faults=faults)


def random_clock(rng: np.random.Generator, drift_ppm_max: float) -> NodeClock:
    """Offset 0.1..5 s, drift uniform in +-drift_ppm_max."""
    return NodeClock(offset_us=int(rng.integers(100_000, 5_000_000)),
                     drift_ppm=float(rng.uniform(-drift_ppm_max, drift_ppm_max)))


def assemble(world, link, *, mag: MagSpec, imu: ImuSpec | None = None, faults: BenchFaults | LinkFaults | None = None,
             seed_driver: int = 0, seed_sensor: int = 0, seed_faults: int = 0, seed_clocks: int | None = None,
             clock_drift_ppm: float = 50.0, sensor_ids=(NODE_SENSOR_BASE,), driver_limits=None,
             verifier=None, sensor_worlds=None, kinds: NodeKinds | None = None) -> Bench:
    """Build the nodes of one run and apply the fault switches.

    Node clocks get seeded offsets and drifts (``clock_drift_ppm`` bound;
    ``faults.drift_ppm`` overrides per node); timed faults become clock steps,
    objects in the world (a magnet on the sensor for ``sat``, a carried steel
    part for ``metal``), node off-windows, and switches the driver reads at
    each pulse (open circuit, short, sag). ``verifier``: checks the signatures
    of what the firmware sends (a :class:`coiltrack.protocol.SignatureVerifier`
    that requires signed commands: an unsigned, forged or replayed command is
    dropped and counted, never executed). ``sensor_worlds``: per sensor id, the
    :meth:`hil.world.World.view` that sensor moves in (default: all in ``world``). ``kinds``:
    the node classes (default :class:`NodeKinds`, pulsed DC; ``hil.ac_nodes.ACNodeKinds``).
    A sensor's clock and noise are drawn by its node id (``id - 16``-th draw), so a
    sensor run alone (``sensor_ids=(id,)``) sees what it sees among others.
    """
    if faults is None:
        faults = BenchFaults()
    elif isinstance(faults, LinkFaults):
        faults = BenchFaults(link=faults)
    rng = np.random.default_rng(seed_faults if seed_clocks is None else seed_clocks)
    clocks = {"driver": random_clock(rng, clock_drift_ppm)}
    slot = [sid - NODE_SENSOR_BASE if 0 <= sid - NODE_SENSOR_BASE < 256 else i for i, sid in enumerate(sensor_ids)]
    drawn = [random_clock(rng, clock_drift_ppm) for _ in range(max(slot) + 1)]
    sensor_clocks = [drawn[j] for j in slot]
    clocks["sensor"] = sensor_clocks[0]
    for name, ppm in faults.drift_ppm.items():
        clocks[name].drift_ppm = float(ppm)
    for f in faults.of("clock_step"):
        clocks[f.target].add_step(f.t_on_us, int(f.value))
    for f in faults.of("sat"):
        # a magnet on the sensor board: 300 uT along the sensor's x axis, beyond the 164 uT range
        world.add(HardIron([300e-6, 0.0, 0.0], f.t_on_us, f.t_off_us))
    for f in faults.of("metal"):
        d = faults.metal_distance_m
        world.add(MetalObject(radius=faults.metal_radius_m, carried_offset=[0.0, d, 0.0],
                              t_on_us=f.t_on_us, t_off_us=f.t_off_us))
    lk = FaultyLink(link, faults.link, seed=seed_faults) if faults.link.active() else link
    kinds = kinds or NodeKinds()
    driver = kinds.driver(NODE_COIL_DRIVER, world, limits=driver_limits, seed=seed_driver,
                          clock=clocks["driver"], faults=faults)
    sensors = []
    worlds = sensor_worlds or {}
    for i, sid in enumerate(sensor_ids):
        sensors.append(kinds.sensor(sid, worlds.get(sid, world), mag=MagSpec(**vars(mag)), imu=imu,
                                    seed=seed_sensor + 1009 * slot[i], clock=sensor_clocks[i], faults=faults,
                                    driver=driver))
    for f in faults.of("node_off"):
        (driver if f.target == "driver" else sensors[0]).add_off_window(f.t_on_us, f.t_off_us)
    recorder = Recorder(world)
    for sid, w in worlds.items():
        recorder.trajectories[sid] = w.trajectory
    emulator = Emulator(world, lk, driver, sensors, recorder, verifier=verifier)
    return Bench(world, lk, driver, sensors, recorder, emulator, faults)


# ---------------------------------------------------------------------------
# Ground truth checks
# ---------------------------------------------------------------------------


def _executed_index(driver) -> dict:
    idx: dict = {}
    for e in driver.executed:
        idx.setdefault((e["coil"], e["pulse_id"]), []).append(e)
    return idx


def _match(idx: dict, coil: int, pid: int, rx_us: int):
    """The latest executed pulse with this (coil, pulse id) that started before ``rx_us``."""
    best = None
    for e in idx.get((coil, pid), ()):
        if e["start_us"] <= rx_us and (best is None or e["start_us"] > best["start_us"]):
            best = e
    return best


def window_truth(bench, tol: float = FLAT_TOL) -> list[dict]:
    """One record per PULSE_WINDOW that used samples: true first/last sample time against the
    true flat part of its pulse. ``violation`` is True when a used sample lies before the flat
    part starts or after the true end edge; ``matched`` is False when no pulse ran for the
    window (refused command, driver off)."""
    world, rec = bench.world, bench.recorder
    sensors = {s.node_id: s for s in bench.sensors}
    idx = _executed_index(bench.driver)
    flat_cache: dict[int, int] = {}
    out = []
    for rx, w in rec.windows:
        if w.n_used == 0:
            continue
        s = sensors.get(w.node)
        e = _match(idx, w.coil, w.pulse_id, rx)
        r = {"node": w.node, "coil": w.coil, "pulse_id": w.pulse_id, "rx_us": rx, "n_used": w.n_used,
             "flags": w.flags, "matched": e is not None}
        if s is None or e is None:
            out.append(r)
            continue
        first = s.true_time_of(w.first_us)
        last = s.true_time_of(w.last_us)
        key = id(e)
        if key not in flat_cache:
            flat_cache[key] = world.flat_start_us(e["coil"], e["start_us"], e["end_us"], tol)
        flat0 = flat_cache[key]
        r.update({"true_start_us": e["start_us"], "true_end_us": e["end_us"], "flat_start_us": flat0,
                  "first_true_us": first, "last_true_us": last})
        if first is None or last is None:
            r["violation"] = True
            r["unknown_sample"] = True
        else:
            r["margin_start_us"] = first - flat0
            r["margin_end_us"] = e["end_us"] - last
            r["violation"] = first < flat0 or last > e["end_us"]
        out.append(r)
    return out


def pose_latencies(bench, fall_us: int, baseline_us: int) -> np.ndarray:
    """Latency (us, true time) from the sample that completed each cycle to the pose frame.

    From the true instant of the completing sample (when the sensor sampled, not when the
    emulator sent it), the first one stamped after the last pulse's end (as the driver reported
    it) + ``fall_us`` + ``baseline_us``: before it the firmware cannot close the cycle. To the
    pose's ``rx_us``: the start of the emulator step that read the ``POSE`` frame (on the wall
    clock, when its loop woke for the bytes). Poses without windows, whose pulses the driver did
    not report, or whose cycle closed on a time-out (the completing sample after the pose) are
    skipped. docs/bench-realtime.md, *The latency, defined*."""
    return np.asarray([rx - t for t, rx in pose_latency_times(bench, fall_us, baseline_us)], dtype=np.int64)


def pose_latency_times(bench, fall_us: int, baseline_us: int) -> list:
    """:func:`pose_latencies`' pairs: (true time of the completing sample, the pose's arrival), us."""
    sensors = {s.node_id: s for s in bench.sensors}
    idx = _executed_index(bench.driver)
    out = []
    for rp in bench.recorder.poses:
        m = rp["msg"]
        s = sensors.get(m.node)
        if s is None or not rp["windows"]:
            continue
        ends = []
        for w in rp["windows"]:
            e = _match(idx, w.coil, w.pulse_id, rp["rx_us"])
            if e is not None and "reported_end_us" in e:
                ends.append(e["reported_end_us"])
        if not ends:
            continue
        thr = max(ends) + fall_us + baseline_us
        st = s.stamps
        i = bisect.bisect_right(st, thr)
        while i < len(st) and st[i] <= thr:
            i += 1
        if i >= len(st):
            continue
        t_sample = s.true_times[i]
        if t_sample > rp["rx_us"]:
            continue
        out.append((int(t_sample), int(rp["rx_us"])))
    return out


def _names(prefix: str) -> dict[int, str]:
    return {getattr(schema, k): k[len(prefix):].lower() for k in dir(schema)
            if k.startswith(prefix) and isinstance(getattr(schema, k), int)}


def fault_summary(bench, fw_status: dict | None = None) -> dict:
    """``injected``: the switches and what the bench did; ``reported``: the firmware's
    FAULT_EVENT codes and POSE status bits, counted."""
    evt_names = _names("EVT_")
    pose_bits = _names("POSE_")
    drv = bench.driver
    inj: dict = {"switches": bench.faults.describe()}
    if hasattr(bench.link, "counts"):
        inj["link"] = {k: v for k, v in bench.link.counts.items() if v}
    coil_faults = {}
    for e in drv.executed:
        for bit, name in ((schema.COIL_FAULT_OPEN_CIRCUIT, "open_circuit"), (schema.COIL_FAULT_OVER_CURRENT,
                          "over_current"), (schema.COIL_FAULT_CURRENT_SAG, "current_sag"),
                          (schema.COIL_FAULT_SUPPLY_LOW, "supply_low")):
            if e.get("faults", 0) & bit:
                coil_faults[name] = coil_faults.get(name, 0) + 1
    if coil_faults:
        inj["coil_pulses_faulty"] = coil_faults
    if drv.refused:
        inj["commands_refused"] = drv.refused
    if drv.duplicates:
        inj["commands_duplicated"] = drv.duplicates
    s = bench.sensor
    if s.saturations:
        inj["samples_saturated"] = s.saturations
    # IMU samples clipped at the parts' full scale (the sensors' and the source module's)
    imu_nodes = [*getattr(bench, "sensors", ()), *([bench.source_imu] if getattr(bench, "source_imu", None) else [])]
    imu_sat = sum(getattr(n, "imu_saturated", 0) for n in imu_nodes)
    if imu_sat:
        inj["imu_samples_saturated"] = imu_sat
    steps = bench.faults.of("clock_step")
    if steps:
        inj["clock_steps"] = len(steps)
    reboots = {("driver" if n is drv else f"sensor{n.node_id}"): n.reboots for n in (drv, *bench.sensors) if n.reboots}
    if reboots:
        inj["reboots"] = reboots
    flips_in = sum(1 for f in s.flip_log if not f["commanded"])
    inj["flips"] = {"commanded": len(s.flip_log) - flips_in, "autonomous": flips_in}
    events: dict[str, int] = {}
    for _, ev in bench.recorder.events:
        name = evt_names.get(ev.code, f"code_{ev.code}")
        events[name] = events.get(name, 0) + 1
    bits: dict[str, int] = {}
    for rp in bench.recorder.poses:
        st = rp["msg"].status
        for b, name in pose_bits.items():
            if st & b:
                bits[name] = bits.get(name, 0) + 1
    rep = {"events": events, "pose_status": bits}
    if fw_status:
        rep["firmware"] = {k: v for k, v in fw_status.items() if k.startswith(("sup_", "sync_", "imu_saturated")) and v}
    return {"injected": inj, "reported": rep}


def bench_metrics(bench, fall_us: int, baseline_us: int) -> dict:
    """The ground-truth figures of a run for the report."""
    wt = window_truth(bench)
    checked = [r for r in wt if "violation" in r]
    viol = [r for r in checked if r["violation"]]
    margins = [min(r["margin_start_us"], r["margin_end_us"]) for r in checked if "margin_start_us" in r]
    valid_ids = set()
    for rp in bench.recorder.poses:
        if rp["msg"].status & POSE_VALID:
            valid_ids.update(id(w) for w in rp["windows"])
    viol_valid = 0
    for (rx, w), r in zip([x for x in bench.recorder.windows if x[1].n_used], wt):
        if r.get("violation") and id(w) in valid_ids:
            viol_valid += 1
    lat = pose_latencies(bench, fall_us, baseline_us)
    leads = bench.driver.cmd_leads_us
    out = {
        "pulse_window_violations": len(viol),
        "pulse_window_violations_in_valid_poses": viol_valid,
        "pulse_windows_checked": len(checked),
        "pulse_windows_unmatched": sum(1 for r in wt if not r["matched"]),
        "pulse_window_min_margin_us": int(min(margins)) if margins else None,
        "command_lead_min_ms": round(min(leads) / 1000.0, 3) if leads else None,
        "latency_ms_p50": round(float(np.percentile(lat, 50)) / 1000.0, 3) if lat.size else None,
        "latency_ms_p99": round(float(np.percentile(lat, 99)) / 1000.0, 3) if lat.size else None,
        "latency_ms_max": round(float(lat.max()) / 1000.0, 3) if lat.size else None,
        "flips_in_pulse_windows": flips_inside_windows(bench),
    }
    return out


def flips_inside_windows(bench) -> int:
    """Set/reset flips that happened (true time) inside a true pulse (start edge to end + settle)."""
    n = 0
    ex = sorted(bench.driver.executed, key=lambda e: e["start_us"])
    starts = [e["start_us"] for e in ex]
    for s in bench.sensors:
        for f in s.flip_log:
            i = bisect.bisect_right(starts, f["true_us"]) - 1
            if i >= 0 and f["true_us"] <= ex[i]["end_us"] + 5 * ex[i].get("tau_us", 0):
                n += 1
    return n
