"""Node and measurement health: what the firmware watches besides the poses.

Per node (the coil driver and every sensor of the configuration):

* **Liveness.** Any frame from a node counts as a sign of life. A sensor
  silent for ``sensor_timeout_us`` or a driver silent for
  ``driver_timeout_us`` (or missing the ``COIL_STATUS`` of
  ``missing_status_cycles`` bursts in a row) is lost (``EVT_NODE_LOST``);
  its next frame brings it back (``EVT_NODE_BACK``, and the time sync is
  kicked so a rebooted node re-synchronises at once).
* **Time stamps** (sensors). Samples come at a steady rate, so consecutive
  stamps differ by a whole number of sample periods (missing samples make
  multiples). A stamp from the future (beyond ``stamp_future_tol_us`` of the
  master clock) or an interval further than ``stamp_interval_tol_us`` from a
  whole number of periods is a clock step (a stamp not after the previous
  one is a duplicated or delayed frame and is skipped; a clock that stepped
  back is seen when its stamps pass the last one, off the grid). The stamps
  from there on are suspect until the node's sync replies show it has
  re-anchored its clock and its stamps run regularly again (or, for a false
  alarm, until six replies came without a step); an anomaly within 2 s of
  that is the same step resolving (no new event). A step the node's sync
  replies show (``TimeSyncMaster.on_reply``) marks the time since five
  replies back suspect (a node takes a forward step only when three
  broadcasts agree). Each step is reported once (``EVT_CLOCK_STEP``, detail =
  node, bit 8 from the samples, bit 9 from the replies). A step within the
  tolerance of a whole number of sample periods is only seen in the replies.
  A cycle whose window span overlaps a suspect interval gives a pose the
  firmware cannot vouch for.
* **Saturation.** A sample with the saturated bit raises ``EVT_SATURATION``
  (at most once per ``saturation_quiet_us``); the pulse extractor flags the
  windows (``POSE_SATURATED``).
* **IMU saturation.** An IMU sample (or an ``IMU_DELTA`` interval) clipped at
  the sensor's full scale is not used (``firmware.receive``); the receiver
  tells :meth:`Health.on_imu_saturated`, which raises ``EVT_SATURATION``
  with detail ``node | IMU_SATURATION`` once per episode: the first clipped
  sample after ``saturation_quiet_us`` without one (a fast swing clips a few
  samples in a row; a hardware fault or a part past its range clips on and
  on: one event either way, the count in ``imu_saturated_samples``).
* **Magnetic distortion** (metal near the sensor). Between pulses a sensor
  sees the earth field alone, whose magnitude does not depend on the
  sensor's position or orientation in an undisturbed field (thesis ``002``
  ch. 2 detects disturbance from the field magnitude and dip). The first
  ``distortion_learn_samples`` quiet samples of each set/reset state give
  that state's reference magnitude (the residual offset changes sign with the
  state);
  afterwards an exponential average of the quiet magnitudes
  (``distortion_avg_samples``) further than ``distortion_threshold_t`` from
  it sets the distortion flag (``EVT_DISTORTION``, ``POSE_DISTORTED``; cleared
  below half the threshold, event detail bit 31). A non-magnetic conductor
  (eddy currents only) does not change the quiet field and is not seen here;
  nor is a magnetic part in the directions where its induced field is
  nearly orthogonal to the earth field (the magnitude changes by
  ``(a/d)^3 |B| (3 cos^2 - 1)`` for a sphere of radius ``a`` at distance
  ``d``, zero near 55 deg from the field).
* **Coil status.** Every pulse of a burst must be answered by a
  ``COIL_STATUS``; a missing or refused one, an open circuit or an
  over-current makes the burst's pose one the firmware cannot vouch for
  (``POSE_COIL_FAULT``).

Fixed-size state allocated in ``__init__``; per-sample work is plain Python
arithmetic on preallocated lists (no numpy allocation).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from coiltrack.protocol.schema import (COIL_FAULT_OPEN_CIRCUIT, COIL_FAULT_OVER_CURRENT, COIL_FAULT_REFUSED,
                             EVT_CLOCK_STEP, EVT_DISTORTION, EVT_NODE_BACK, EVT_NODE_LOST, EVT_SATURATION)

#: COIL_STATUS faults after which the burst's amplitudes cannot be trusted
COIL_FAULT_FATAL = COIL_FAULT_OPEN_CIRCUIT | COIL_FAULT_OVER_CURRENT | COIL_FAULT_REFUSED

_SUSPECT = 4          # suspect intervals remembered per node
_EVENTS = 32          # pending events
_NONE = -(1 << 62)
_OPEN = 1 << 62
_SAME_STEP_US = 2_000_000   # an anomaly this soon after a suspect interval closed is the same step
#: EVT_SATURATION detail bit: the node's IMU clipped (without it: its magnetometer)
IMU_SATURATION = 1 << 8


def _adopt(obj, name: str, view, at: int, k: int) -> int:
    """``obj``'s list ``name`` (``k`` items) into ``view[at:at + k]``, kept as that view (the
    compiled core's shared state, :meth:`Health.use_arrays`); the next free item."""
    old = getattr(obj, name)
    v = view[at:at + k]
    for j in range(k):
        v[j] = old[j]
    setattr(obj, name, v)
    return at + k


@dataclass(frozen=True)
class HealthConfig:
    sensor_timeout_us: int = 250_000
    driver_timeout_us: int = 2_500_000
    missing_status_cycles: int = 2
    stamp_future_tol_us: int = 3_000
    stamp_interval_tol_us: int = 400
    saturation_quiet_us: int = 1_000_000
    distortion_threshold_t: float = 1.5e-6
    distortion_learn_samples: int = 60      # per set/reset state
    distortion_avg_samples: int = 4
    quiet_margin_us: int = 5_000


class _SuspectSpans:
    """:class:`Health`'s question of a window's span: a sensor's clock or the coil driver's suspect
    anywhere in it (``Health.suspect`` of both), one compiled call on the compiled core."""

    def suspect_either(self, node: int, other: int, t0: int, t1: int) -> bool:
        """``suspect(node, t0, t1) or suspect(other, t0, t1)``: a sensor's window and the coil
        driver's clock (``track.single_coil_tracker``). On the compiled core one call
        (:meth:`bind_suspect`: ``core/src/sc_close.c`` ``ct_scc_suspect_either`` on the arrays of
        :meth:`use_arrays`)."""
        return self.suspect(node, t0, t1) or self.suspect(other, t0, t1)

    def bind_suspect(self, kernel) -> None:
        """After :meth:`use_arrays`: :meth:`suspect_either` on ``kernel`` (``ext.SuspectSpan`` bound to
        the same arrays)."""
        self._either = kernel.either
        self.suspect_either = self._suspect_either_compiled

    def _suspect_either_compiled(self, node: int, other: int, t0: int, t1: int) -> bool:
        """:meth:`suspect_either` in one call; an argument the kernel does not take (not an int64)
        goes to the reference."""
        try:
            return self._either(node, other, t0, t1)
        except (OverflowError, TypeError):
            return _SuspectSpans.suspect_either(self, node, other, t0, t1)


class Health(_SuspectSpans):
    def __init__(self, sensor_ids, driver_id: int, mag_rate_hz: float, hcfg: HealthConfig | None = None,
                 boot_us: int = 0):
        self.hcfg = hcfg = hcfg or HealthConfig()
        self.sensor_ids = tuple(int(s) for s in sensor_ids)
        self.driver_id = int(driver_id)
        ids = self.sensor_ids + (self.driver_id,)
        n = len(ids)
        self.ids = ids
        self._slot = {nid: i for i, nid in enumerate(ids)}
        self.driver_slot = n - 1
        self.timeout_us = [hcfg.sensor_timeout_us] * (n - 1) + [hcfg.driver_timeout_us]
        self.last_heard = [boot_us] * n
        self.lost = [False] * n
        # no node can be lost before this time (us): the earliest ``last_heard + timeout_us`` of the
        # nodes not lost, or earlier (a sign of life only moves a node's deadline later): until then
        # :meth:`step` returns at once
        self._sc = [boot_us + min(self.timeout_us)]    # [check_us] (:meth:`use_arrays`: a view)
        self.lost_events = 0
        self.back_events = 0
        self._back = ()
        self._backv = [0]                   # whether _back holds nodes (use_arrays: a view)
        # time stamps (sensors)
        self.period_us = 1e6 / mag_rate_hz
        self.last_stamp = [_NONE] * n
        self.susp_t0 = [[_NONE] * _SUSPECT for _ in range(n)]
        self.susp_t1 = [[_NONE] * _SUSPECT for _ in range(n)]
        self.susp_k = [0] * n                  # next slot to write
        self.suspect_open = [False] * n
        self.suspect_reply_seen = [False] * n
        self.suspect_quiet_replies = [0] * n
        self.clock_steps = 0
        # saturation
        self.last_sat_us = [_NONE] * n
        self.saturated_samples = 0
        self.saturation_events = 0
        self.last_imu_sat_us = [_NONE] * (n + 1)       # the last slot: an IMU of another node (the source's)
        self.imu_saturated_samples = 0
        self.imu_saturation_events = 0
        # distortion
        self.ref_sum = [0.0] * (2 * n)
        self.ref_n = [0] * (2 * n)
        self.ref_mag = [0.0] * (2 * n)
        self.avg_mag = [0.0] * (2 * n)
        self.distorted = [False] * n
        self.dist_state = [False] * (2 * n)
        self.distortion_events = 0
        self._alpha = 1.0 / max(1, hcfg.distortion_avg_samples)
        # coil status of the current burst
        self.n_coils = 0
        self.status_seen: list[bool] = []
        self.status_faults: list[int] = []
        self.missing_status = 0
        self.missing_cycles = 0
        self._skip_missing = False
        # pending events (code, detail), a fixed ring
        self._ev_code = [0] * _EVENTS
        self._ev_detail = [0] * _EVENTS
        self.events_queued = 0             # events waiting for flush_events (read by the supervisor)
        self.events_dropped = 0
        self.kick_sync = False

    @property
    def check_us(self) -> int:
        """No node can be lost before this time (us); :meth:`step` returns at once until then."""
        return self._sc[0]

    @check_us.setter
    def check_us(self, v: int) -> None:
        self._sc[0] = v

    #: the per-node lists the compiled core shares (:meth:`use_arrays`), in ``ct_supervise.h``'s order
    INT_LISTS = ("last_heard", "timeout_us", "lost", "last_stamp", "suspect_open", "suspect_reply_seen", "distorted")
    FLOAT_LISTS = ("ref_sum", "ref_mag", "avg_mag")

    def use_arrays(self, si, sd, ni: int, nd: int, slots: int) -> None:
        """Keep the per-node state the compiled supervisor kernel shares (``core/src/supervise.c``)
        in ``si`` (int64) and ``sd`` (float64), laid out as ``ct_supervise.h`` says (header ``ni``,
        ``nd`` items; a node -> slot table of ``slots`` items): the same values, the lists become
        views of the arrays (the Python reference runs on them unchanged). Writes this object's
        header items; the caller writes its own (margin, fall, coils, the pose bits). After
        :meth:`set_coils`."""
        n = len(self.ids)
        hc = self.hcfg
        iv, dv = memoryview(si), memoryview(sd)
        iv[0], iv[1], iv[2] = self._sc[0], n, self.driver_slot
        iv[3], iv[4], iv[5] = hc.stamp_future_tol_us, hc.stamp_interval_tol_us, hc.distortion_learn_samples
        iv[8], iv[11] = self.n_coils, COIL_FAULT_FATAL
        dv[0], dv[1], dv[2] = self.period_us, self._alpha, hc.distortion_threshold_t
        for k in range(slots):
            iv[ni + k] = -1
        for nid, i in self._slot.items():
            iv[ni + nid] = i
        self._sc = iv[0:1]
        iv[16] = self._backv[0]
        self._backv = iv[16:17]
        at = ni + slots
        for name in self.INT_LISTS:
            at = _adopt(self, name, iv, at, n)
        at += n                                     # the flip states (FlipScheduler.use_array)
        for name in ("ref_n", "dist_state"):
            at = _adopt(self, name, iv, at, 2 * n)
        for name in ("status_seen", "status_faults"):
            at = _adopt(self, name, iv, at, self.n_coils)
        for name in ("susp_t0", "susp_t1"):        # (node slot i's intervals: a view of row i)
            rows = getattr(self, name)
            views = []
            for i in range(n):
                v = iv[at:at + _SUSPECT]
                for k in range(_SUSPECT):
                    v[k] = rows[i][k]
                views.append(v)
                at += _SUSPECT
            setattr(self, name, views)
        at = nd
        for name in self.FLOAT_LISTS:
            at = _adopt(self, name, dv, at, 2 * n)

    def take_kick_sync(self) -> bool:
        """Whether a node came back since the last call (time sync should start over for it);
        clears the request."""
        kick = self.kick_sync
        self.kick_sync = False
        return kick

    def set_coils(self, n_coils: int) -> None:
        self.n_coils = n_coils
        self.status_seen = [False] * n_coils
        self.status_faults = [0] * n_coils

    # ------------------------------------------------------------ events
    def _event(self, code: int, detail: int) -> None:
        if self.events_queued >= _EVENTS:
            self.events_dropped += 1
            return
        self._ev_code[self.events_queued] = code
        self._ev_detail[self.events_queued] = detail
        self.events_queued += 1

    def flush_events(self, emit) -> None:
        if not self.events_queued:
            return
        for i in range(self.events_queued):
            emit(self._ev_code[i], self._ev_detail[i])
        self.events_queued = 0

    # ------------------------------------------------------------ liveness
    def heard(self, node: int, now_us: int) -> None:
        i = self._slot.get(node, -1)
        if i < 0:
            return
        self.last_heard[i] = now_us
        due = now_us + self.timeout_us[i]
        if due < self.check_us:            # (a clock that went back, a node back: an earlier check)
            self.check_us = due
        if self.lost[i]:
            self.lost[i] = False
            self.back_events += 1
            self._event(EVT_NODE_BACK, node)
            self.kick_sync = True
            self._back = self._back + (node,)
            self._backv[0] = 1
            self.last_stamp[i] = _NONE
            if i == self.driver_slot:
                self.missing_cycles = 0
                self._skip_missing = True

    def back_nodes(self):
        """Nodes that came back since the last call (for the time sync to forget them)."""
        out = self._back
        if out:
            self._back = ()
            self._backv[0] = 0
        return out

    def step(self, now_us: int) -> None:
        """Mark the nodes silent past their timeout lost; nothing to look at until ``check_us``."""
        if now_us <= self.check_us:
            return
        check = _OPEN
        lost, heard, timeout = self.lost, self.last_heard, self.timeout_us
        for i in range(len(self.ids)):
            if lost[i]:
                continue
            due = heard[i] + timeout[i]
            if now_us > due:
                self._set_lost(i)
            elif due < check:
                check = due
        self.check_us = check

    def _set_lost(self, i: int) -> None:
        self.lost[i] = True
        self.lost_events += 1
        self._event(EVT_NODE_LOST, self.ids[i])

    def any_lost(self) -> bool:
        for v in self.lost:
            if v:
                return True
        return False

    # ------------------------------------------------------------ samples
    def on_mag(self, node: int, stamp: int, bx: float, by: float, bz: float, saturated: bool,
               now_us: int, quiet: bool, flip: int = 0) -> None:
        i = self._slot.get(node, -1)
        if i < 0 or i == self.driver_slot:
            return
        hc = self.hcfg
        # --- time stamp sanity
        prev = self.last_stamp[i]
        bad = stamp > now_us + hc.stamp_future_tol_us
        if not bad and prev != _NONE:
            dt = stamp - prev
            if dt <= 0:
                # a duplicated or delayed frame (out of order): skipped. A clock that stepped
                # back shows once its stamps pass the last one, off the sample grid.
                return
            P = self.period_us
            k = math.floor(dt / P + 0.5)
            if k < 1:
                k = 1
            if k <= 64 and abs(dt - k * P) > hc.stamp_interval_tol_us:
                bad = True
        if bad:
            if not self.suspect_open[i]:
                self._open_suspect(i, prev if prev != _NONE else stamp, 1 << 8)
        elif self.suspect_open[i] and self.suspect_reply_seen[i]:
            self._close_suspect(i, stamp)
        if not bad or stamp > prev:
            self.last_stamp[i] = stamp
        # --- saturation
        if saturated:
            self.saturated_samples += 1
            if now_us - self.last_sat_us[i] > hc.saturation_quiet_us:
                self.saturation_events += 1
                self._event(EVT_SATURATION, node)
            self.last_sat_us[i] = now_us
            return
        # --- distortion (quiet samples only)
        if not quiet or bad:
            return
        m = math.sqrt(bx * bx + by * by + bz * bz)
        s = 2 * i + (flip & 1)              # one reference per set/reset state (offset sign)
        if self.ref_n[s] < hc.distortion_learn_samples:
            self.ref_sum[s] += m
            self.ref_n[s] += 1
            if self.ref_n[s] == hc.distortion_learn_samples:
                self.ref_mag[s] = self.ref_sum[s] / self.ref_n[s]
                self.avg_mag[s] = self.ref_mag[s]
            return
        a = self.avg_mag[s] + self._alpha * (m - self.avg_mag[s])
        self.avg_mag[s] = a
        dev = abs(a - self.ref_mag[s])
        thr = hc.distortion_threshold_t
        if dev > thr:
            self.dist_state[s] = True
        elif dev < 0.5 * thr:
            self.dist_state[s] = False
        now_dist = self.dist_state[2 * i] or self.dist_state[2 * i + 1]
        if now_dist and not self.distorted[i]:
            self.distorted[i] = True
            self.distortion_events += 1
            self._event(EVT_DISTORTION, node | (min(int(dev * 1e8), 0xFFFF) << 8))
        elif self.distorted[i] and not now_dist:
            self.distorted[i] = False
            self._event(EVT_DISTORTION, node | (1 << 31))

    def on_imu_saturated(self, node: int, now_us: int) -> None:
        """An IMU sample of ``node`` clipped (received at ``now_us``): ``EVT_SATURATION`` with
        detail ``node | IMU_SATURATION`` at the first of an episode (module docstring)."""
        i = self._slot.get(node, len(self.ids))
        self.imu_saturated_samples += 1
        if now_us - self.last_imu_sat_us[i] > self.hcfg.saturation_quiet_us:
            self.imu_saturation_events += 1
            self._event(EVT_SATURATION, node | IMU_SATURATION)
        self.last_imu_sat_us[i] = now_us

    # ------------------------------------------------------------ clock steps
    def _open_suspect(self, i: int, t0: int, how: int) -> None:
        kp = (self.susp_k[i] - 1) % _SUSPECT
        t1p = self.susp_t1[i][kp]
        self.suspect_open[i] = True
        self.suspect_reply_seen[i] = False
        self.suspect_quiet_replies[i] = 0
        if t1p != _NONE and t1p != _OPEN and t0 - t1p < _SAME_STEP_US:
            # the same step resolving (the stamps jumping back when the node re-anchors): reopen
            self.susp_k[i] = kp
            self.susp_t1[i][kp] = _OPEN
            return
        k = self.susp_k[i]
        self.susp_t0[i][k] = t0
        self.susp_t1[i][k] = _OPEN
        self.clock_steps += 1
        self._event(EVT_CLOCK_STEP, self.ids[i] | how)

    def _close_suspect(self, i: int, t1: int) -> None:
        k = self.susp_k[i]
        self.susp_t1[i][k] = t1
        self.susp_k[i] = (k + 1) % _SUSPECT
        self.suspect_open[i] = False

    def restart_stamps(self, node: int) -> None:
        """Forget ``node``'s last sample stamp: its time base was just set (sync acquisition), so the
        next sample is not judged against the grid of the one before."""
        i = self._slot.get(node, -1)
        if i >= 0:
            self.last_stamp[i] = _NONE

    def on_sync_reply(self, node: int, stepped: bool, prev_reply_us: int, now_us: int) -> None:
        i = self._slot.get(node, -1)
        if i < 0:
            return
        if self.suspect_open[i]:
            if stepped:
                # the node has re-anchored its clock: the next regular stamp closes the interval
                self.suspect_reply_seen[i] = True
                if i == self.driver_slot:
                    self._close_suspect(i, now_us)
            else:
                self.suspect_quiet_replies[i] += 1
                if self.suspect_quiet_replies[i] >= 6:      # no step after all (or one absorbed)
                    self._close_suspect(i, now_us)
            return
        if stepped:
            k = self.susp_k[i]
            self.susp_t0[i][k] = prev_reply_us
            self.susp_t1[i][k] = now_us
            self.susp_k[i] = (k + 1) % _SUSPECT
            self.clock_steps += 1
            self._event(EVT_CLOCK_STEP, node | (1 << 9))

    def is_distorted(self, node: int) -> bool:
        """Whether ``node``'s quiet field currently looks distorted (metal)."""
        i = self._slot.get(node, -1)
        return i >= 0 and bool(self.distorted[i])

    def suspect(self, node: int, t0: int, t1: int) -> bool:
        """True when ``node``'s clock was suspect anywhere in master time ``[t0, t1]``."""
        i = self._slot.get(node, -1)
        if i < 0:
            return False
        if self.suspect_open[i]:
            return True
        a, b = self.susp_t0[i], self.susp_t1[i]
        for k in range(_SUSPECT):
            if a[k] != _NONE and a[k] <= t1 and b[k] >= t0:
                return True
        return False

    # ------------------------------------------------------------ coil status
    def new_burst(self) -> bool:
        """Start bookkeeping a new burst; return True when no pulse of the previous burst was
        answered at all (the driver is silent)."""
        seen = self.status_seen
        answered = 0
        for j in range(self.n_coils):
            if seen[j]:
                answered += 1
            seen[j] = False
            self.status_faults[j] = 0
        return self.n_coils > 0 and answered == 0

    def on_coil_status(self, j: int, faults: int) -> None:
        if 0 <= j < self.n_coils:
            self.status_seen[j] = True
            self.status_faults[j] = faults

    def burst_status(self) -> tuple[bool, bool]:
        """``(all answered, any fatal fault)`` for the current burst."""
        ok = True
        fatal = False
        for j in range(self.n_coils):
            if not self.status_seen[j]:
                ok = False
            if self.status_faults[j] & COIL_FAULT_FATAL:
                fatal = True
        return ok, fatal

    def note_missing_status(self, missing: bool) -> None:
        """Book whether the previous burst went wholly unanswered."""
        if self._skip_missing:          # that burst was commanded while the driver was away
            self._skip_missing = False
            return
        if missing:
            self.missing_status += 1
            self.missing_cycles += 1
            d = self.driver_slot
            if self.missing_cycles >= self.hcfg.missing_status_cycles and not self.lost[d]:
                self._set_lost(d)
        else:
            self.missing_cycles = 0
