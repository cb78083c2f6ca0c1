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
        """The node restarts at ``true_us``: its counter reads ``start_local_us`` then.
        Steps already scheduled for later (a fault schedule adds them at start-up)
        stay jumps of the restarted counter."""
        true_us = int(true_us)
        jump = int(start_local_us) - self.local(true_us)
        k = bisect.bisect_right(self._step_t, true_us)
        before = self._step_cum[k - 1] if k > 0 else 0
        self._step_t.insert(k, true_us)
        self._step_cum.insert(k, before + jump)
        for i in range(k + 1, len(self._step_cum)):
            self._step_cum[i] += jump

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
    ``master - local = c0 + c1 (local - local_last)`` over the last
    ``window`` points (``c0`` is minus the offset at the newest point, ``c1``
    minus the relative drift): the slope by least squares, the line shifted to
    the least delayed point (frames are late, never early), so reception
    jitter neither tilts nor lifts it much and a drifting oscillator is
    followed. A broadcast can be
    late but never early: a point earlier than predicted by more than
    ``step_threshold_us`` is a clock step taken at once, a later one is a late
    frame unless ``confirm`` consecutive points agree on it (then a step); the
    history is dropped and the line restarts, keeping the drift (see
    :meth:`update`). Stale points (not newer than the last) are ignored. The drift is fitted only once the points span
    ``min_span_us`` (before that the previous drift, initially zero, is kept
    and only the offset is fitted), so reception jitter over a short span
    cannot produce a wild drift. The transmission latency of the broadcast is
    common to every node of the bus and so cancels between a coil driver and
    a sensor (both see the master late by the same amount).

    Before the first point ``synced`` is False and :meth:`to_master` returns
    the local time unchanged.
    """

    def __init__(self, window: int = 32, step_threshold_us: int = 1500, min_span_us: int = 1_000_000,
                 max_drift: float = 1e-3, acquire: int = 4, confirm: int = 3):
        self.window = int(window)
        self.step_threshold_us = int(step_threshold_us)
        self.acquire = int(acquire)
        self.confirm = int(confirm)
        self.min_span_us = int(min_span_us)
        self.max_drift = float(max_drift)
        self._pts: deque[tuple[int, int]] = deque(maxlen=self.window)
        self.c0 = 0.0          # master - local at local_ref
        self.c1 = 0.0          # d(master - local)/d(local)
        self.local_ref = 0
        self.synced = False
        self.updates = 0
        self.steps = 0
        self.rejected = 0
        self.last_residual_us = 0
        self._cands: list[tuple[int, int, int]] = []

    def reset(self) -> None:
        self._pts.clear()
        self._cands.clear()
        self.c0 = self.c1 = 0.0
        self.local_ref = 0
        self.synced = False

    def update(self, local_rx_us: int, master_us: int) -> bool:
        """Add one sync point; return True when it established a clock step (history dropped).

        A broadcast can arrive late, never early. With ``r`` the point's residual
        (predicted master time at its arrival minus its master time):

        * a stale point (master time not newer than the last) is ignored;
        * during acquisition (fewer than ``acquire`` points) the line follows the
          lower envelope: a late point (``r > threshold``) is ignored, an early one
          (``r < -threshold``: the anchor was late) restarts the line; no step;
        * ``r < -threshold`` later: the node's clock stepped back (or the master's
          forward): the line restarts there at once, a step;
        * ``r > threshold``: a late frame or a forward step; it is held, and a step
          is taken only when ``confirm`` consecutive points agree within the
          threshold (one stall delays frames sent 2 ms apart by amounts 2 ms
          apart, so it cannot fake this); otherwise they are dropped.
        """
        local_rx_us, master_us = int(local_rx_us), int(master_us)
        thr = self.step_threshold_us
        if self.synced:
            if self._pts and master_us <= self._pts[-1][1]:
                self.rejected += 1
                return False
            r = self.to_master(local_rx_us) - master_us
            self.last_residual_us = -r
            if len(self._pts) < self.acquire:
                if r > thr:
                    self.rejected += 1
                    return False
                if r < -thr:
                    self._pts.clear()
            elif r < -thr:
                self._pts.clear()
                self._cands.clear()
                self._pts.append((local_rx_us, master_us))
                self.steps += 1
                self.updates += 1
                self._fit()
                return True
            elif r > thr:
                self._cands.append((local_rx_us, master_us, r))
                rs = [c[2] for c in self._cands]
                if max(rs) - min(rs) > thr:
                    self._cands[:] = self._cands[-1:]
                elif len(self._cands) >= self.confirm:
                    self._pts.clear()
                    for l, m, _ in self._cands:
                        self._pts.append((l, m))
                    self._cands.clear()
                    self.steps += 1
                    self.updates += 1
                    self._fit()
                    return True
                self.rejected += 1
                return False
        self._cands.clear()
        self._pts.append((local_rx_us, master_us))
        self.updates += 1
        self._fit()
        self.synced = True
        return False

    def _fit(self) -> None:
        pts = self._pts
        lref = pts[-1][0]
        n = len(pts)
        xs = [float(l - lref) for l, _ in pts]
        ys = [float(m - l) for l, m in pts]
        xm = sum(xs) / n
        ym = sum(ys) / n
        sxx = sum((x - xm) ** 2 for x in xs)
        span = xs[-1] - xs[0]
        c1 = self.c1
        if n >= 3 and span >= self.min_span_us and sxx > 0.0:
            fit = sum((x - xm) * (y - ym) for x, y in zip(xs, ys)) / sxx
            if abs(fit) <= self.max_drift:
                c1 = fit
        # with a short span the drift is kept and only the offset is fitted
        c0 = ym - c1 * xm                   # least-squares value at x = 0 (local_ref)
        # frames are late, never early: y = master - local is largest for the least delayed
        # frame; put the line through it (the lower envelope of the delay, as NTP's clock
        # filter), so frames that were a little late do not bias the offset
        c0 += max(y - (c0 + c1 * x) for x, y in zip(xs, ys))
        self.c1 = c1
        self.c0 = c0
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
