"""Tick timing statistics: the figures of the wall-clock loops (``tools.bench.realtime``) and
their replay of an in-process run's measured tick times on an ideal real-time schedule
(:func:`inproc_timing`, used by ``tools.bench.runner``). All in microseconds; the figures are
described in ``tools.bench.realtime``'s docstring."""
from __future__ import annotations

import numpy as np


def _stats(starts: np.ndarray, exec_us: np.ndarray, late: np.ndarray, tick_us: int, misses: int) -> dict:
    periods = np.diff(starts)
    jitter = np.abs(periods - tick_us) if periods.size else np.full(1, np.nan)
    n = int(starts.size)
    return {
        "ticks": n,
        "tick_us": tick_us,
        "tick_period_us_median": float(np.median(periods)) if periods.size else None,
        "tick_jitter_us_median": float(np.median(jitter)),
        "tick_jitter_us_p99": float(np.percentile(jitter, 99)),
        "tick_jitter_us_max": float(np.max(jitter)),
        "tick_late_us_p99": float(np.percentile(late, 99)) if n else None,
        "tick_late_us_max": float(np.max(late)) if n else None,
        "tick_exec_us_median": float(np.median(exec_us)) if n else None,
        "tick_exec_us_p99": float(np.percentile(exec_us, 99)) if n else None,
        "tick_exec_us_max": float(np.max(exec_us)) if n else None,
        "deadline_misses": int(misses),
    }


def no_ticks(tick_us: int) -> dict:
    """The statistics of a loop stopped before its first tick (a signal during its set-up)."""
    empty = np.zeros(0, dtype=np.int64)
    out = _stats(empty, empty, empty, tick_us, 0)
    out["timing_source"] = "wall clock: stopped before the first tick"
    return out


def inproc_timing(exec_ns: np.ndarray, tick_us: int) -> dict:
    """Replay measured tick execution times on the schedule of :func:`firmware_loop` (a tick
    starts at its slot or when the previous one ends; a tick that overruns a period, or starts
    a period late, misses its deadline, and every slot it overran is skipped and counted)."""
    ex = np.asarray(exec_ns, dtype=np.int64) // 1000
    n = ex.size
    starts = np.zeros(n, dtype=np.int64)
    late = np.zeros(n, dtype=np.int64)
    misses = 0
    now = 0
    nxt = 0
    for k in range(n):
        s = nxt if now <= nxt else now
        e = int(ex[k])
        starts[k] = s
        late[k] = s - nxt
        end = s + e
        if s - nxt >= tick_us or e >= tick_us:
            misses += 1
        nxt += tick_us
        if nxt <= end - tick_us:
            skipped = (end - nxt) // tick_us
            misses += int(skipped)
            nxt += int(skipped) * tick_us
        now = end
    out = _stats(starts, ex, late, tick_us, misses)
    out["timing_source"] = "inproc: wall time of each fw.tick against the tick period (simulated clock)"
    return out


def inproc_cpu_timing(cpu_ns: np.ndarray, tick_us: int) -> dict:
    """The same replay as :func:`inproc_timing` on each tick's CPU time (``time.thread_time_ns``),
    which leaves out the time the process spent descheduled: what the firmware's own work costs,
    as a core of its own would run it (on a shared, loaded machine the wall figures count every
    preemption of the process, a tick descheduled for 100 ms with the 100 slots it swallowed).
    Keys ``tick_cpu_us_median``, ``_p99``, ``_p999``, ``_max`` and ``cpu_deadline_misses`` (the
    names ``coiltrack perf`` uses)."""
    rep = inproc_timing(cpu_ns, tick_us)
    us = np.asarray(cpu_ns, dtype=np.int64) / 1000.0
    pct = lambda q: round(float(np.percentile(us, q)), 1) if us.size else None  # noqa: E731
    return {"tick_cpu_us_median": pct(50), "tick_cpu_us_p99": pct(99), "tick_cpu_us_p999": pct(99.9),
            "tick_cpu_us_max": pct(100), "cpu_deadline_misses": rep["deadline_misses"]}
