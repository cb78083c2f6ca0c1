"""Injected microsecond clocks for the bench, node oscillators and the
node-side time synchronisation.

* :class:`SimClock` is advanced by the runner (deterministic, faster than real
  time); :class:`WallClock` reads CLOCK_MONOTONIC, which every process on the
  machine shares, so two processes given the same epoch agree on time.
* :class:`NodeClock` is a node's own oscillator and time-stamp counter against
  *true* time (the bench's time base, on which the world's physics and motion
  run): ``local = true + round(true * drift_ppm * 1e-6) + offset_us + steps``.
  ``steps`` are clock-step faults (the counter jumps at a true instant) and
  reboots (the counter restarts near zero).
* :class:`NodeSync` is what a node learns from the firmware's ``TIME_SYNC``
  broadcasts: a least-squares line ``master = f(local)`` over the last few
  sync points (offset and drift), with step detection. A node stamps its
  samples with ``NodeSync.to_master(clock.local(t))`` and executes commands
  given in master time at ``clock.true(sync.to_local(master))``.

All times are integer microseconds.
"""
from __future__ import annotations

import bisect
import math
import time
from collections import deque


class SimClock:
    def __init__(self, start_us: int = 0):
        self.now_us = int(start_us)

    def now(self) -> int:
        return self.now_us

    def advance_to(self, t_us: int) -> None:
        if t_us < self.now_us:
            raise ValueError("simulated time cannot run backwards")
        self.now_us = int(t_us)

    def sleep(self, seconds: float) -> None:
        """Simulated sleep: advance the clock (for loops written against an injected clock)."""
        self.now_us += max(0, int(round(seconds * 1e6)))


class WallClock:
    def __init__(self, epoch_ns: int | None = None):
        self.epoch_ns = time.monotonic_ns() if epoch_ns is None else int(epoch_ns)

    def now(self) -> int:
        return (time.monotonic_ns() - self.epoch_ns) // 1000

    @staticmethod
    def sleep(seconds: float) -> None:
        time.sleep(seconds)


class NodeClock:
    """A node's oscillator and time-stamp counter.

    ``local(true) = true + round(true * drift_ppm * 1e-6) + offset_us + S(true)``
    where ``S`` is the sum of the steps that happened at or before ``true``
    (:meth:`add_step`, :meth:`reboot`). Drift is a rate error of the
    oscillator (100 ppm: 100 us per second); a step is a jump of the counter
    (a fault), a reboot restarts the counter at ``start_local_us``.
    """

    def __init__(self, offset_us: int = 0, drift_ppm: float = 0.0):
        self.offset_us = int(offset_us)
        self.drift_ppm = float(drift_ppm)
        self._step_t: list[int] = []      # true time of each step (sorted)
        self._step_cum: list[int] = []    # cumulative step after it

    @property
    def rate(self) -> float:
        """Local microseconds per true microsecond."""
        return 1.0 + self.drift_ppm * 1e-6

    def add_step(self, true_us: int, step_us: int) -> None:
        """The counter jumps by ``step_us`` at true time ``true_us`` (steps must be added in time order)."""
        true_us = int(true_us)
        if self._step_t and true_us < self._step_t[-1]:
            raise ValueError("clock steps must be added in time order")
        cum = (self._step_cum[-1] if self._step_cum else 0) + int(step_us)
        self._step_t.append(true_us)
        self._step_cum.append(cum)

    def reboot(self, true_us: int, start_local_us: int = 0) -> None:
        """The node restarts at ``true_us``: its counter reads ``start_local_us`` then."""
        self.add_step(true_us, int(start_local_us) - self.local(true_us))

    def _cum(self, true_us: int) -> int:
        k = bisect.bisect_right(self._step_t, true_us) - 1
        return self._step_cum[k] if k >= 0 else 0

    def _free(self, true_us: int) -> int:
        return true_us + int(round(true_us * self.drift_ppm * 1e-6)) + self.offset_us

    def local(self, true_us: int) -> int:
        true_us = int(true_us)
        return self._free(true_us) + self._cum(true_us)

    def true(self, local_us: int, after_us: int | None = None) -> int:
        """First true time ``t`` (>= ``after_us`` when given) at which the counter reads ``>= local_us``.

        This is when a timer armed for ``local_us`` fires. A forward step
        that jumps over ``local_us`` fires the timer at the step.
        """
        local_us = int(local_us)
        lo = -(1 << 62) if after_us is None else int(after_us)
        # segments between steps: [seg_start, seg_end)
        bounds = [lo] + [t for t in self._step_t if t > lo]
        for i, seg_start in enumerate(bounds):
            seg_end = bounds[i + 1] if i + 1 < len(bounds) else None
            cum = self._cum(seg_start)
            if self._free(seg_start) + cum >= local_us:
                return seg_start
            t = int(math.floor((local_us - cum - self.offset_us) / self.rate))
            while self._free(t) + cum < local_us:
                t += 1
            while t - 1 >= seg_start and self._free(t - 1) + cum >= local_us:
                t -= 1
            if seg_end is None or t < seg_end:
                return max(t, seg_start)
        raise AssertionError("unreachable")  # pragma: no cover


class NodeSync:
    """Node-side estimate of the master clock from ``TIME_SYNC`` broadcasts.

    Each broadcast gives a point ``(local_rx, master)``: the node's counter
    when the frame arrived and the master time written in it. The node fits
    ``master - local = c0 + c1 (local - local_last)`` by least squares over
    the last ``window`` points (``c0`` is minus the offset at the newest
    point, ``c1`` minus the relative drift), so the estimate averages the
    reception jitter and follows a drifting oscillator. A point further than
    ``step_threshold_us`` from the prediction is a clock step (of the node
    or the master): the history is dropped and the line restarts at that
    point, keeping the drift. The transmission latency of the broadcast is
    common to every node of the bus and so cancels between a coil driver and
    a sensor (both see the master late by the same amount).

    Before the first point ``synced`` is False and :meth:`to_master` returns
    the local time unchanged.
    """

    def __init__(self, window: int = 16, step_threshold_us: int = 1500):
        self.window = int(window)
        self.step_threshold_us = int(step_threshold_us)
        self._pts: deque[tuple[int, int]] = deque(maxlen=self.window)
        self.c0 = 0.0          # master - local at local_ref
        self.c1 = 0.0          # d(master - local)/d(local)
        self.local_ref = 0
        self.synced = False
        self.updates = 0
        self.steps = 0
        self.last_residual_us = 0

    def reset(self) -> None:
        self._pts.clear()
        self.c0 = self.c1 = 0.0
        self.local_ref = 0
        self.synced = False

    def update(self, local_rx_us: int, master_us: int) -> bool:
        """Add one sync point; return True when it was a step (history dropped)."""
        local_rx_us, master_us = int(local_rx_us), int(master_us)
        stepped = False
        if self.synced:
            resid = master_us - self.to_master(local_rx_us)
            self.last_residual_us = resid
            if abs(resid) > self.step_threshold_us:
                self._pts.clear()
                self.steps += 1
                stepped = True
        self._pts.append((local_rx_us, master_us))
        self.updates += 1
        self._fit()
        self.synced = True
        return stepped

    def _fit(self) -> None:
        pts = self._pts
        lref = pts[-1][0]
        n = len(pts)
        if n == 1:
            self.local_ref, self.c0 = lref, float(pts[0][1] - pts[0][0])
            return
        xs = [float(l - lref) for l, _ in pts]
        ys = [float(m - l) for l, m in pts]
        xm = sum(xs) / n
        ym = sum(ys) / n
        sxx = sum((x - xm) ** 2 for x in xs)
        if sxx <= 0.0:
            self.local_ref, self.c0 = lref, ym
            return
        c1 = sum((x - xm) * (y - ym) for x, y in zip(xs, ys)) / sxx
        if n == 2 and abs(c1) > 1e-3:       # two close points: too noisy to trust, keep the old drift
            c1 = self.c1
        self.c1 = c1
        self.c0 = ym - c1 * xm              # value at x = 0 (local_ref)
        self.local_ref = lref

    def to_master(self, local_us: int) -> int:
        if not self.synced:
            return int(local_us)
        return int(local_us) + int(round(self.c0 + self.c1 * (int(local_us) - self.local_ref)))

    def to_local(self, master_us: int) -> int:
        if not self.synced:
            return int(master_us)
        # master = L + c0 + c1 (L - Lr)  =>  L = (master - c0 + c1 Lr) / (1 + c1)
        x = (int(master_us) - self.local_ref - self.c0) / (1.0 + self.c1)
        return self.local_ref + int(round(x))

    @property
    def offset_us(self) -> int:
        """Estimated ``local - master`` at the newest sync point."""
        return -int(round(self.c0))

    @property
    def drift_ppb(self) -> int:
        """Estimated drift of the local clock against the master (ppb)."""
        return int(round(-self.c1 / (1.0 + self.c1) * 1e9)) if self.synced else 0
