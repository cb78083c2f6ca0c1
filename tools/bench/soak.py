"""The soak: a long bench run under a seeded random schedule of every fault switch.

:func:`random_schedule` draws the schedule (the ``--faults`` text of
``hil.faults``): the link faults on for the whole run at small rates, and the
timed faults one after the other, each kind in turn in a shuffled order, with
random lengths and quiet gaps between them so that every fault has its own
recovery. :func:`soak_run` runs one seed on the simulated clock
(firmware and emulator in one process, as ``bench``) and returns the bench
report with what the soak adds: whether it crashed, the firmware's memory
sampled over the run (:func:`footprint`), and the verdicts of
:func:`verdict`.
"""
from __future__ import annotations

import math
import traceback

import numpy as np

from ..stopping import Stopped, mark
from ..outputs import report as report_mod
from .links import inproc_pair

#: link fault rates for the whole run (per frame)
LINK_RATES = {"drop": 0.01, "corrupt": 0.01, "duplicate": 0.005, "truncate": 0.002, "garbage": 0.002,
              "delay": 0.005}
#: timed fault kinds and their (shortest, longest) length, s; None: a switch without an end
TIMED_KINDS = {
    "node_off=sensor": (1.0, 6.0), "node_off=driver": (1.0, 6.0), "sat": (1.0, 6.0),
    "open_circuit": (2.0, 10.0), "short": (1.0, 5.0), "overheat": (2.0, 8.0), "sag": (5.0, 30.0),
    "metal": (5.0, 60.0), "clock_step": None,
}
#: quiet time before the first fault and between faults (shortest, longest), s
WARMUP_S = 20.0
GAP_S = (25.0, 60.0)
#: memory samples over the run, and the part of the run counted as warm-up for them
MEMORY_SAMPLES = 24
MEMORY_WARMUP_FRACTION = 0.25
#: verdict limits
MAX_OVERCONFIDENT_FRACTION = 0.01
MAX_RECOVERY_S = 3.0


def random_schedule(seed: int, duration_s: float, n_coils: int = 3, gap_s: tuple[float, float] = GAP_S,
                    warmup_s: float = WARMUP_S, length_scale: float = 1.0) -> str:
    """A ``--faults`` text: every link fault at ``LINK_RATES``, then every timed
    kind of ``TIMED_KINDS`` in a shuffled order, repeated until the run ends
    (each fault a random length times ``length_scale``, ``gap_s`` apart, the
    first after ``warmup_s``; none closer than 10 s to the end)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x50AC]))
    parts = [f"{k}={v:g}" for k, v in LINK_RATES.items()]
    t = warmup_s
    kinds = list(TIMED_KINDS)
    while True:
        order = [kinds[i] for i in rng.permutation(len(kinds))]
        for kind in order:
            span = TIMED_KINDS[kind]
            length = 0.0 if span is None else float(rng.uniform(*span)) * length_scale
            if t + length + 10.0 > duration_s:
                return ",".join(parts)
            t0, t1 = round(t, 1), round(t + length, 1)
            if kind == "clock_step":
                step = int(rng.choice((-1, 1))) * int(rng.integers(2, 20))
                parts.append(f"clock_step=sensor:{step}ms@{t0:g}s")
            elif kind in ("open_circuit", "short", "overheat"):
                parts.append(f"{kind}={int(rng.integers(0, n_coils))}@{t0:g}s-{t1:g}s")
            elif kind == "sag":
                parts.append(f"sag={float(rng.uniform(0.5, 0.8)):.2f}@{t0:g}s-{t1:g}s")
            elif kind.startswith("node_off"):
                parts.append(f"{kind}@{t0:g}s-{t1:g}s")
            else:
                parts.append(f"{kind}={t0:g}s-{t1:g}s")
            t = t1 + float(rng.uniform(*gap_s))


def footprint(fw) -> dict:
    """The firmware's memory: ``state_bytes`` (array data and byte buffers reachable
    from its objects, ``tools.commands.perf.state_bytes``) and ``items`` (elements of
    every list, dict, set and tuple reachable from them): a buffer or a queue
    that grows shows in one of the two."""
    # imported where used here and below: the world's physics (magpylib) loads only when a run starts
    from ..commands.perf import state_bytes

    total, _ = state_bytes(fw)
    seen: set[int] = set()
    items = 0
    stack = [fw]
    while stack:
        obj = stack.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, dict):
            items += len(obj)
            stack.extend(obj.values())
        elif isinstance(obj, (list, tuple, set, frozenset)):
            items += len(obj)
            stack.extend(obj)
        elif (getattr(type(obj), "__module__", "") or "").startswith(("coiltrack.firmware", "coiltrack.protocol")):
            d = getattr(obj, "__dict__", None)
            if d is not None:
                stack.extend(d.values())
            for s in getattr(type(obj), "__slots__", ()):
                if hasattr(obj, s):
                    stack.append(getattr(obj, s))
    return {"state_bytes": int(total), "items": int(items)}


def soak_run(scenario, seed: int, duration_s: float, schedule: str | None = None) -> dict:
    """One soak run (see the module docstring); never raises for a firmware crash:
    the report says ``crashed`` with the traceback's last line."""
    from coiltrack.firmware.loop import Firmware

    from .runner import BenchSetup, parse_faults

    cfg = scenario.firmware_config()
    n_coils = len(cfg.source.coils)
    schedule = random_schedule(seed, duration_s, n_coils) if schedule is None else schedule
    faults = parse_faults(schedule, scenario)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(scenario, seed, duration_s, emu_end, faults, cfg=cfg)
    fw = Firmware(cfg, fw_end)
    end_us = int(duration_s * 1e6)
    tick = cfg.timing.tick_us
    every = max(tick, (end_us // MEMORY_SAMPLES) // tick * tick)
    memory = []
    crash = None
    stopped = None
    where = "bench"
    t = 0
    try:
        while t <= end_us:
            where = "bench"
            bench.emulator.step(t)
            where = "firmware"
            fw.tick(t)
            if t % every == 0:
                memory.append({"t_s": t * 1e-6, **footprint(fw)})
            t += tick
        where = "bench"
        bench.emulator.step(t)
    except Exception as exc:  # a crash is what the soak reports, not what stops it
        crash = f"{type(exc).__name__}: {exc} at t={t * 1e-6:.3f} s ({traceback.format_exc().splitlines()[-3].strip()})"
    except Stopped as exc:    # SIGINT, SIGTERM: the report of the time run, handed to the caller
        stopped = exc
    fw_end.close()
    emu_end.close()
    done_s = duration_s if crash is None and stopped is None else max(t, tick) * 1e-6
    rep = report_mod.build(bench, fw.status(), done_s, transport="inproc", cfg=cfg)
    rep["schedule"] = schedule
    rep["crashed"] = crash is not None and where == "firmware"       # the firmware's tick raised
    rep["bench_failed"] = crash is not None and where == "bench"      # the emulated world or nodes raised
    if crash:
        rep["crash"] = f"{where}: {crash}"
    rep["memory"] = memory
    rep.update(memory_growth(memory))
    rep["verdict"] = verdict(rep)
    if stopped is not None:
        raise mark(rep, stopped)
    return rep


def memory_growth(memory: list[dict]) -> dict:
    """Net growth of ``state_bytes`` and ``items`` from the end of the warm-up
    (``MEMORY_WARMUP_FRACTION`` of the samples) to the last sample."""
    if len(memory) < 2:
        return {"state_bytes_growth": None, "items_growth": None}
    w = memory[min(len(memory) - 1, int(math.ceil(len(memory) * MEMORY_WARMUP_FRACTION)))]
    last = memory[-1]
    return {"state_bytes_growth": last["state_bytes"] - w["state_bytes"],
            "items_growth": last["items"] - w["items"],
            "state_bytes_constant": len({m["state_bytes"] for m in memory}) == 1}


def verdict(rep: dict) -> dict:
    """The soak's pass conditions, each True or False: no crash (and the bench
    itself ran to the end), every fault
    reported, every fault window recovered from within ``MAX_RECOVERY_S``, at
    most ``MAX_OVERCONFIDENT_FRACTION`` overconfident poses, no memory growth."""
    rec = rep.get("fault_recovery_s", {})
    slow = [k for k, v in rec.items() if v is None or v > MAX_RECOVERY_S]
    frac = rep.get("overconfident_fraction")
    return {
        "no_crash": not rep.get("crashed"),
        "bench_ran_to_the_end": not rep.get("bench_failed"),
        "every_fault_reported": not rep.get("faults_unreported"),
        "recovered_within_limit": not slow,
        "slow_recoveries": slow,
        "overconfident_within_limit": frac is not None and frac <= MAX_OVERCONFIDENT_FRACTION,
        "no_memory_growth": rep.get("state_bytes_growth") == 0 and (rep.get("items_growth") or 0) <= 0,
    }


def passed(v: dict) -> bool:
    return all(val for k, val in v.items() if k != "slow_recoveries")
