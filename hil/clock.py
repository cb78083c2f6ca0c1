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
  broadcasts: the lower envelope of the last few sync points (offset and
  drift), corrections slewed, steps detected. A node stamps its
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
    when the frame arrived and the master time written in it. Frames are
    late, never early, by a latency that on a loaded host or a USB-serial CAN
    adapter varies by milliseconds; the node therefore fits the *lower
    envelope* of the delay, as NTP's clock filter and PTP servos do:

    * the drift (slope) from the two least delayed points of the older and
      the newer half of the last ``window`` points, once they span
      ``min_span_us`` (a least-squares slope through points jittered by 2 ms
      over 3 s is off by ~500 ppm; the envelope slope by the spread of the
      minimum delay only);
    * the offset through the least delayed point of the window.

    **Corrections are slewed, not stepped.** When a new point moves the line,
    the time the node stamps with (:meth:`to_master`) does not jump: the
    difference between the old and the new line is worked off at
    ``slew_ppm`` (500 ppm, the largest slew of NTP's ``adjtime``: 4 us over
    one 120 Hz sample period, far inside the firmware's 400 us sample-grid
    tolerance). Only a clock step is applied at once:

    * a point earlier than predicted by more than ``step_threshold_us`` (and
      than ``late_scale`` times the jitter: an envelope that rose during a long
      stall is re-anchored and slewed), or
      ``confirm`` consecutive points later than predicted and agreeing
      within the threshold (see :meth:`update`): the node's clock stepped; the
      history is dropped, the line restarts there keeping the drift. For late
      points the threshold is at least ``late_scale`` times the link's jitter
      (the median lateness of the window's points above the envelope): with
      latencies spread exponentially (median m), a frame is ``10 m`` late
      with probability 2^-10, three in a row once in 10^9, while three beyond
      a fixed 1.5 ms happen every few seconds on a loaded host. A step smaller
      than that on such a link is slewed off instead (the firmware still sees
      its jump on the sample grid); on a quiet link the threshold is
      ``step_threshold_us``;
    * three consecutive points whose master times run back from the
      newest one, each newer than the last of them: the master restarted
      with a lower clock; the node re-acquires.

    Stale points (not newer than the last) are otherwise ignored, so a
    duplicated or reordered broadcast changes nothing. Before the first point
    ``synced`` is False and :meth:`to_master` returns the local time unchanged.
    """

    def __init__(self, window: int = 32, step_threshold_us: int = 1500, min_span_us: int = 1_000_000,
                 max_drift: float = 1e-3, acquire: int = 4, confirm: int = 5, slew_ppm: float = 500.0,
                 late_scale: float = 10.0):
        self.window = int(window)
        self.step_threshold_us = int(step_threshold_us)
        self.acquire = int(acquire)
        self.confirm = int(confirm)
        self.min_span_us = int(min_span_us)
        self.max_drift = float(max_drift)
        self.slew = float(slew_ppm) * 1e-6
        self._pts: deque[tuple[int, int]] = deque(maxlen=self.window)
        self.c0 = 0.0          # master - local at local_ref (the fitted line)
        self.c1 = 0.0          # d(master - local)/d(local)
        self.local_ref = 0
        self.e0 = 0.0          # correction still to be slewed off at local_ref (applied = line + e)
        self.synced = False
        self.updates = 0
        self.steps = 0
        self.restarts = 0
        self.rejected = 0
        self.last_residual_us = 0
        self.jitter_us = 0.0   # median lateness of the window's points above the envelope
        self.late_scale = float(late_scale)
        self._cands: list[tuple[int, int, int]] = []
        self._stale: list[tuple[int, int]] = []
        self._seen = 0         # broadcasts since (re)acquisition

    def reset(self) -> None:
        self._seen = 0
        self._pts.clear()
        self._cands.clear()
        self._stale.clear()
        self.c0 = self.c1 = self.e0 = 0.0
        self.local_ref = 0
        self.synced = False

    def update(self, local_rx_us: int, master_us: int) -> bool:
        """Add one sync point; return True when it established a clock step (history dropped).

        A broadcast can arrive late, never early. With ``r`` the point's residual
        (predicted master time at its arrival minus its master time):

        * a stale point (master time not newer than the last) is ignored, unless
          three of them in a row run forward together: the master restarted
          (a step, re-acquired from them);
        * during acquisition (fewer than ``acquire`` points) the line follows the
          lower envelope: a late point (``r > threshold``) is ignored, an early one
          (``r < -threshold``: the anchor was late) restarts the line; no step;
        * ``r < -threshold`` later: the node's clock stepped back (or the master's
          forward): the line restarts there at once, a step; on a jittery link,
          an early point within ``late_scale`` times the jitter re-anchors the
          line and is slewed to (every frame of the last window was late);
        * ``r > threshold``: a late frame or a forward step; it is held, and a step
          is taken only when ``confirm`` (5) consecutive points agree within the
          threshold (one stall delays frames sent 2 ms apart by amounts 2 ms
          apart, so it cannot fake this; a loaded host's random delays agree
          within 1.5 ms five times in a row far more rarely than three times);
          otherwise they are dropped.
        """
        local_rx_us, master_us = int(local_rx_us), int(master_us)
        thr = self.step_threshold_us
        self._seen += 1
        if self.synced:
            if self._pts and master_us <= self._pts[-1][1]:
                return self._on_stale(local_rx_us, master_us)
            self._stale.clear()
            r = self._line(local_rx_us) - master_us
            self.last_residual_us = int(-r)
            if len(self._pts) < self.acquire:
                if r > thr:
                    self.rejected += 1
                    return False
                if r < -thr:
                    self._pts.clear()
            elif r < -max(thr, self.late_scale * self.jitter_us):
                self._restart([(local_rx_us, master_us)])
                return True
            elif r < -thr:
                # early, but within the link's jitter: the envelope had risen with a long stall
                # (every frame of the window late); re-anchor the line here and slew to it
                before = self.to_master(local_rx_us)
                self._pts.clear()
                self._pts.append((local_rx_us, master_us))
                self.updates += 1
                self._fit()
                self.e0 = float(before - local_rx_us) - self.c0
                return False
            elif r > max(thr, self.late_scale * self.jitter_us):
                self._cands.append((local_rx_us, master_us, int(r)))
                rs = [c[2] for c in self._cands]
                if max(rs) - min(rs) > thr:
                    self._cands[:] = self._cands[-1:]
                elif len(self._cands) >= self.confirm:
                    self._restart([(l, m) for l, m, _ in self._cands])
                    return True
                self.rejected += 1
                return False
        self._cands.clear()
        # acquisition is the first `acquire` broadcasts answered (accepted or not), as the
        # firmware counts them from the replies: steps are free there, slewed after
        first = not self.synced or self._seen <= self.acquire
        before = self.to_master(local_rx_us) if not first else 0
        self._pts.append((local_rx_us, master_us))
        self.updates += 1
        self._fit()
        self.synced = True
        # slew from what the node stamped with to the new line (acquisition: take the line as it is)
        self.e0 = 0.0 if first else float(before - local_rx_us) - self.c0
        return False

    def _on_stale(self, local_rx_us: int, master_us: int) -> bool:
        st = self._stale
        if st and master_us <= st[-1][1]:
            st.clear()
        st.append((local_rx_us, master_us))
        if len(st) < 3:                     # three stale points running forward: a new master timeline
            self.rejected += 1
            return False
        pts = list(st)
        st.clear()
        self.restarts += 1
        self._restart(pts)
        return True

    def _restart(self, pts) -> None:
        self._seen = self.acquire + 1
        self._pts.clear()
        self._cands.clear()
        for p in pts:
            self._pts.append(p)
        self.steps += 1
        self.updates += 1
        self._fit()
        self.e0 = 0.0

    def _fit(self) -> None:
        pts = self._pts
        lref = pts[-1][0]
        n = len(pts)
        c1 = self.c1
        span = pts[-1][0] - pts[0][0]
        if n >= 4 and span >= self.min_span_us:
            # the least delayed point (largest master - local) of each half
            h = n // 2
            i1 = max(range(h), key=lambda i: pts[i][1] - pts[i][0])
            i2 = max(range(h, n), key=lambda i: pts[i][1] - pts[i][0])
            dx = pts[i2][0] - pts[i1][0]
            if dx > 0:
                fit = ((pts[i2][1] - pts[i2][0]) - (pts[i1][1] - pts[i1][0])) / dx
                if abs(fit) <= self.max_drift:
                    c1 = fit
        # the line through the least delayed point of the window
        self.c0 = max(float(m - l) - c1 * (l - lref) for l, m in pts)
        self.c1 = c1
        self.local_ref = lref
        # the window's typical lateness (median distance above the envelope): the link's jitter
        d = sorted(self.c0 + c1 * (l - lref) - float(m - l) for l, m in pts)
        self.jitter_us = d[n // 2]

    def _line(self, local_us: int) -> float:
        return local_us + self.c0 + self.c1 * (local_us - self.local_ref)

    def _e(self, local_us: int) -> float:
        e0 = self.e0
        if e0 == 0.0:
            return 0.0
        left = abs(e0) - self.slew * max(0, local_us - self.local_ref)
        return 0.0 if left <= 0.0 else math.copysign(left, e0)

    def to_master(self, local_us: int) -> int:
        if not self.synced:
            return int(local_us)
        local_us = int(local_us)
        return int(round(self._line(local_us) + self._e(local_us)))

    def to_local(self, master_us: int) -> int:
        if not self.synced:
            return int(master_us)
        # master = L + c0 + c1 (L - Lr) + e(L), |de/dL| <= slew: a fixed point, two passes
        L = float(self.local_ref)
        for _ in range(3):
            L = self.local_ref + (int(master_us) - self._e(int(round(L))) - self.local_ref - self.c0) / (1.0 + self.c1)
        return int(round(L))

    @property
    def offset_us(self) -> int:
        """``local - master`` the node applies at the newest sync point (slewing included)."""
        return -int(round(self.c0 + self.e0))

    @property
    def drift_ppb(self) -> int:
        """Estimated drift of the local clock against the master (ppb)."""
        return int(round(-self.c1 / (1.0 + self.c1) * 1e9)) if self.synced else 0
