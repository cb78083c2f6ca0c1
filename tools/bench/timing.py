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
class LoopTrace:
    """An optional per-tick trace of :func:`tools.bench.realtime.firmware_loop` (off unless
    given; ``COILTRACK_LOOP_TRACE=FILE`` for ``coiltrack firmware``): for each tick, on the
    loop's clock (us), the end of the previous tick, this tick's start and end, the sleeps
    between them (count, time asked, the longest one measured and what it asked), the
    stage durations (``Firmware.tick_timed``, ns) and the process's scheduler figures across the gap
    (``/proc/self/schedstat``: ns on the CPU, ns runnable but waiting). Rows are preallocated;
    :meth:`save` writes them (``numpy.savez``) with their column names."""

    COLS = ("prev_end", "start", "end", "sleeps", "sleep_asked", "sleep_max", "sleep_max_asked",
            "run_ns", "wait_ns", "st_receive", "st_measure", "st_track", "st_actuate", "st_supervise",
            "st_transmit", "steal_cs", "rx_bytes", "tx_bytes")

    def __init__(self, cap: int = 200_000, path: str | None = None):
        import os

        self.rows = np.zeros((cap, len(self.COLS)), dtype=np.int64)
        self.stages = np.zeros(6, dtype=np.int64)
        self.n = 0
        self.path = path
        self.link = None                    # a link with bytes_rx / bytes_tx counters (FdLink), if any
        self._sched_fd = None
        try:
            self._sched_fd = os.open("/proc/self/schedstat", os.O_RDONLY)
        except OSError:
            pass
        self._run0 = self._wait0 = 0
        self._stat_fd = None
        try:
            self._stat_fd = os.open("/proc/stat", os.O_RDONLY)
        except OSError:
            pass
        self._steal0 = self._steal()
        self.gap_begin(0)

    def _steal(self) -> int:
        """Time the hypervisor ran something else on this CPU (``/proc/stat``'s steal, 1/100 s)."""
        import os

        if self._stat_fd is None:
            return 0
        cpu = os.sched_getaffinity(0)
        if len(cpu) != 1:
            return 0
        tag = b"cpu%d " % next(iter(cpu))
        for line in os.pread(self._stat_fd, 8192, 0).split(b"\n"):
            if line.startswith(tag):
                return int(line.split()[8])
        return 0

    def _sched(self):
        import os

        if self._sched_fd is None:
            return 0, 0
        f = os.pread(self._sched_fd, 128, 0).split()
        return int(f[0]), int(f[1])

    def gap_begin(self, t_end: int) -> None:
        """A tick ended at ``t_end``: the gap to the next one begins."""
        self._prev_end = t_end
        self._sleeps = self._asked = self._smax = self._smax_asked = 0
        self._run0, self._wait0 = self._sched()

    def slept(self, asked_us: int, took_us: int) -> None:
        self._sleeps += 1
        self._asked += asked_us
        if took_us > self._smax:
            self._smax, self._smax_asked = took_us, asked_us

    def tick(self, start: int, end: int) -> None:
        """A tick ran from ``start`` to ``end`` (its stage times in :attr:`stages`)."""
        if self.n < self.rows.shape[0]:
            run, wait = self._sched()
            r = self.rows[self.n]
            r[0], r[1], r[2], r[3], r[4], r[5], r[6] = (self._prev_end, start, end, self._sleeps, self._asked,
                                                        self._smax, self._smax_asked)
            r[7], r[8] = run - self._run0, wait - self._wait0
            r[9:15] = self.stages
            if self.link is not None:
                r[16], r[17] = self.link.bytes_rx, self.link.bytes_tx
            if start - self._prev_end > 3000 or self.n % 128 == 0:
                st = self._steal()
                r[15], self._steal0 = st - self._steal0, st
            self.n += 1
        self.gap_begin(end)

    def save(self, path: str | None = None) -> None:
        path = path or self.path
        if path:
            np.savez(path, rows=self.rows[:self.n], cols=np.array(self.COLS))


class StealProbe:
    """The hypervisor's steal time of the CPU this process is pinned to (``/proc/stat``, 1/100 s),
    for traces: :meth:`delta` is the steal since the last :meth:`mark`."""

    def __init__(self):
        import os

        self._fd = None
        try:
            self._fd = os.open("/proc/stat", os.O_RDONLY)
        except OSError:
            pass
        self.base = self.read()

    def read(self) -> int:
        import os

        if self._fd is None:
            return 0
        cpus = os.sched_getaffinity(0)
        tags = tuple(b"cpu%d " % c for c in cpus)
        tot = 0
        for line in os.pread(self._fd, 8192, 0).split(b"\n"):
            if line.startswith(tags):
                tot += int(line.split()[8])
        return tot

    def mark(self) -> None:
        self.base = self.read()

    def delta(self) -> int:
        return self.read() - self.base
