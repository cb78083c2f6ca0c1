"""The firmware's supervisor: time sync, node health, flip scheduling and the
pose status bits that come from them.

It joins :class:`coiltrack.firmware.supervise.timesync.TimeSyncMaster`,
:class:`coiltrack.firmware.supervise.health.Health` and
:class:`coiltrack.firmware.supervise.flips.FlipScheduler` to the firmware's tick with
three calls: ``on_message(msg, now)`` for every decoded frame,
``step(now)`` once per tick, and ``pose_status(node, window_flags)``
when a pose is made (it returns extra ``POSE_*`` bits and sets ``veto``
when the firmware cannot vouch for the pose: a coil status missing or fatal,
a node clock that stepped during the burst, or a saturated sample in a
window). It reads the pulse schedule
(:class:`coiltrack.firmware.actuate.schedule.PulseSchedule`) without changing
it, and sends through the transmitter.

Per burst: a ``TIME_SYNC`` right when the commands leave and three right after
the last pulse ends (plus the periodic ones), and one ``MAG_FLIP_CMD`` per
sensor for the quiet gap after the burst (``flips_per_tick`` of them a tick, from the
burst's first).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from coiltrack.protocol import MSG
from coiltrack.protocol.schema import MAG_LSB_T, POSE_COIL_FAULT, POSE_DEGRADED, POSE_DISTORTED, POSE_INCONSISTENT

from coiltrack.firmware.supervise.flips import FlipScheduler
from coiltrack.firmware.measure.pulse import PULSE_SATURATED
from coiltrack.firmware.supervise.health import _SUSPECT, Health, HealthConfig
from coiltrack.firmware.supervise.timesync import _ACQUIRE as ts_ACQUIRE, _HISTORY as ts_HISTORY
from coiltrack.firmware.supervise.timesync import _REPLIES as ts_REPLIES, TimeSyncMaster

_ID_HEARTBEAT = MSG["HEARTBEAT"].ID
_ID_SYNC_REPLY = MSG["TIME_SYNC_REPLY"].ID
_ID_COIL_STATUS = MSG["COIL_STATUS"].ID
_ID_MAG = MSG["MAG_SAMPLE"].ID
_ID_IMU = MSG["IMU_SAMPLE"].ID

#: with ``sync_around_burst``: broadcasts this long (us) after the last pulse of a burst ends, besides
#: one as the commands leave (``tools/commands/busload.py`` models the bus load from the same table)
BURST_SYNCS_AFTER_US = (1_000, 3_000, 5_000)


@dataclass(frozen=True)
class SupervisorConfig:
    sync_period_us: int = 250_000
    sync_latency_us: int = 0            # constant link latency added to the broadcast master time
    sync_step_threshold_us: int = 1_500
    sync_around_burst: bool = True
    flips: bool = True
    flip_min_gap_us: int = 10_000
    flips_per_tick: int = 4             # MAG_FLIP_CMDs sent in one tick (0: all of a burst at once)
    health: HealthConfig = field(default_factory=HealthConfig)


class Supervisor:
    def __init__(self, cfg, schedule, tx, scfg: SupervisorConfig | None = None):
        self.cfg = cfg
        self.schedule = schedule
        self.tx = tx
        self.scfg = scfg = scfg or SupervisorConfig()
        self.n = len(cfg.source.coils)
        self.sensor_ids = tuple(cfg.link.sensor_ids)
        self.driver_id = cfg.link.coil_driver_id
        self.timesync = TimeSyncMaster(self.sensor_ids + (self.driver_id,), scfg.sync_period_us,
                                       scfg.sync_latency_us, scfg.sync_step_threshold_us)
        self.health = Health(self.sensor_ids, self.driver_id, cfg.pulse.mag_rate_hz, scfg.health)
        self.health.set_coils(self.n)
        self.flips = FlipScheduler(self.sensor_ids, scfg.flip_min_gap_us)
        self._ps = memoryview(schedule.start)
        self._pe = memoryview(schedule.end)
        self._pid = memoryview(schedule.pulse_id)
        self._burst = None
        self._first_burst = True
        self._margin = scfg.health.quiet_margin_us
        self._fall = cfg.pulse.fall_us
        self.veto = False
        self.poses_vetoed = 0
        self._sup = None                # the compiled kernels (mag_kernel), bound once
        self._sup_payloads = False

    # ------------------------------------------------------------ receive
    def on_message(self, msg, now_us: int) -> None:
        mid = msg.ID
        h = self.health
        if mid == _ID_MAG:
            node = msg.node
            h.heard(node, now_us)
            self.flips.observe(node, msg.flip)
            h.on_mag(node, msg.t_us, msg.x * MAG_LSB_T, msg.y * MAG_LSB_T, msg.z * MAG_LSB_T,
                     bool(msg.flip & 2), now_us, self._quiet(msg.t_us), msg.flip & 1)
        elif mid == _ID_IMU:
            h.heard(msg.node, now_us)
        elif mid == _ID_COIL_STATUS:
            h.heard(self.driver_id, now_us)
            c = msg.coil
            if c < self.n and msg.pulse_id == self._pid[c]:
                h.on_coil_status(c, msg.faults)
        elif mid == _ID_SYNC_REPLY:
            node = msg.node
            h.heard(node, now_us)
            ts = self.timesync
            for back in h.back_nodes():
                ts.forget(back)             # it came back (rebooted): its replies re-acquire
            i = ts.slot(node)
            # asked before the reply is booked: does it answer one of the node's first four
            # broadcasts? The node applies all four as steps, the fourth included
            acquiring = ts.acquiring(i)
            prev = ts.first_suspect_us(i, now_us)           # before the candidates of a forward step
            stepped = ts.on_reply(msg, now_us)
            h.on_sync_reply(node, stepped, prev, now_us)
            if acquiring:
                h.restart_stamps(node)      # acquisition steps the node's time base: check anew
        elif mid == _ID_HEARTBEAT:
            h.heard(msg.node, now_us)

    def mag_kernel(self, core, payloads=None):
        """The MAG_SAMPLE branch of :meth:`on_message` on the compiled core, or None on the python core
        (or for a node id the kernel's slot table cannot hold): ``kernel(node, t_us, x, y, z, flip,
        now_us)`` returns 0 when it did the whole branch (``ct_sup_mag``, ``core/src/supervise.c``: the
        same operations on the same state, which the health and the flip scheduler then keep in its
        arrays), 1 for a rare case (a lost node, a stamp off the grid, saturation, a distortion flag
        that changes, ...) that :meth:`on_message` must do: the kernel changed nothing then. Binds
        :meth:`pose_status` on the compiled core too (``ct_sup_pose_status``), and with
        ``payloads`` (the frame decoder's payload table) :meth:`reply_kernel`."""
        ext = core.ext
        h = self.health
        if ext is None or any(not 0 <= nid < ext.SUP_SLOTS for nid in h.ids) or self.n < 1:
            return None
        if self._sup is None:
            assert (ext.SUP_SUSPECT, ext.SUP_HISTORY, ext.SUP_REPLIES, ext.SUP_ACQUIRE) == (
                _SUSPECT, ts_HISTORY, ts_REPLIES, ts_ACQUIRE) and self.timesync.node_ids == h.ids and ext.SUP_NI == 18
            n, nc = len(h.ids), self.n
            ni, nd, slots = ext.SUP_NI, ext.SUP_ND, ext.SUP_SLOTS
            at_ts = ni + slots + 12 * n + 2 * nc + 2 * _SUSPECT * n
            self._si = si = np.zeros(at_ts + 2 * ts_HISTORY + 9 * n + ts_REPLIES * n, dtype=np.int64)
            self._sd = sd = np.zeros(nd + 6 * n)
            h.use_arrays(si, sd, ni, nd, slots)
            iv = memoryview(si)
            p = self.cfg.pulse
            iv[6], iv[7], iv[9], iv[10] = self._margin, self._fall, p.baseline_us + p.guard_us, p.fall_us + p.baseline_us
            iv[12], iv[13], iv[14], iv[15] = (PULSE_SATURATED, POSE_COIL_FAULT, POSE_INCONSISTENT | POSE_DEGRADED,
                                              POSE_DISTORTED)
            iv[17] = self.timesync.step_threshold_us
            memoryview(sd)[3] = MAG_LSB_T
            at = ni + slots + 7 * n
            self.flips.use_array(iv[at:at + len(self.sensor_ids)])
            self.timesync.use_arrays(iv[at_ts:])
            self._sup = ext.SupMag(si, sd, self.schedule.start, self.schedule.end, payloads)
            h.bind_suspect(ext.SuspectSpan(si, sd))
            self._sup_payloads = payloads is not None
            self._pose_k = self._sup.pose_status
            self.pose_status = self._pose_status_compiled
        return self._sup.mag

    def driver_heard(self, now_us: int) -> None:
        """The coil driver spoke in a message the supervisor is not given (``AC_DRIVE_STATUS``)."""
        self.health.heard(self.driver_id, now_us)

    def coil_report(self, coil: int, faults: int) -> None:
        """The driver's word on ``coil`` of the running plan outside ``COIL_STATUS`` (``faults``:
        its ``COIL_FAULT_*`` bits; ``AC_DRIVE_STATUS`` of AC excitation)."""
        self.health.on_coil_status(coil, faults)

    def on_imu_saturated(self, node: int, now_us: int) -> None:
        """An IMU sample of ``node`` clipped at full scale (the receiver does not use it)."""
        self.health.on_imu_saturated(node, now_us)

    def _quiet(self, t_us: int) -> bool:
        ps, pe, m = self._ps, self._pe, self._margin
        for j in range(self.n):
            if ps[j] - m <= t_us <= pe[j] + self._fall + m:
                return False
        return True

    # ------------------------------------------------------------ tick
    def step(self, now_us: int) -> None:
        """A new burst's time syncs and flip commands; the time sync, the nodes' liveness and
        the events they raised. A tick with nothing due is a few comparisons: each part keeps
        the time of its next work."""
        pc = self.schedule.burst_start
        if pc is not None and pc != self._burst:
            self._new_burst(pc, now_us)
        elif self.flips.pending:                    # the burst's flip commands, a few a tick
            self.flips.step(self.tx.send, self.tx.mag_flip, self.scfg.flips_per_tick)
        h = self.health
        if h.kick_sync and h.take_kick_sync():
            self.timesync.kick()
            for node in h.back_nodes():
                self.timesync.forget(node)          # it re-acquires: its first replies are no step
        ts = self.timesync
        if now_us >= ts.due_us:                     # (before it, nothing to broadcast)
            ts.step(now_us, self.tx.time_sync)
        if now_us > h.check_us:                     # (until then no node can be lost)
            h.step(now_us)
        if h.events_queued:
            h.flush_events(self.tx.event)

    def _new_burst(self, pc: int, now_us: int) -> None:
        """The burst opened at ``pc``: its coil-status check, the time syncs around it and the
        flip commands for the quiet gap after it."""
        self._burst = pc
        missing = self.health.new_burst()
        if not self._first_burst:
            self.health.note_missing_status(missing)
        self._first_burst = False
        last_end = self.schedule.burst_end
        cfg = self.cfg
        if self.scfg.sync_around_burst:
            # one as the commands leave, three 2 ms apart right after the last pulse: a node
            # takes a forward clock step only when three broadcasts agree (a stall of the
            # link delays frames 2 ms apart by amounts 2 ms apart, so it cannot fake one),
            # so a step during the burst shows in the replies before the burst's pose
            self.timesync.request(now_us)
            for d in BURST_SYNCS_AFTER_US:
                self.timesync.request(last_end + d)
        if self.scfg.flips:
            quiet_from = last_end + cfg.pulse.fall_us + cfg.pulse.baseline_us + cfg.pulse.guard_us
            quiet_to = pc + cfg.timing.cycle_us - cfg.pulse.baseline_us - cfg.pulse.guard_us
            self.flips.plan(now_us, quiet_from, quiet_to, self.tx.send, self.tx.mag_flip, self.scfg.flips_per_tick)

    # ------------------------------------------------------------ poses
    def pose_status(self, node: int, window_flags: int) -> int:
        """Extra POSE_* bits for the pose of ``node`` from the current burst
        (``window_flags``: its windows' flags, or-ed); sets ``veto``."""
        cfg = self.cfg
        h = self.health
        bits = 0
        veto = False
        ok, fatal = h.burst_status()
        if not ok or fatal:
            bits |= POSE_COIL_FAULT
            veto = True
        ps, pe = self._ps, self._pe
        t0 = ps[0]
        t1 = pe[0]
        for j in range(1, self.n):
            if ps[j] < t0:
                t0 = ps[j]
            if pe[j] > t1:
                t1 = pe[j]
        t0 -= cfg.pulse.baseline_us + cfg.pulse.guard_us
        t1 += cfg.pulse.fall_us + cfg.pulse.baseline_us
        if h.suspect(node, t0, t1) or h.suspect(self.driver_id, t0, t1):
            bits |= POSE_INCONSISTENT | POSE_DEGRADED
            veto = True
        if h.is_distorted(node):
            bits |= POSE_DISTORTED
        if window_flags & PULSE_SATURATED:   # clipped samples: the amplitude is meaningless
            veto = True
        self.veto = veto
        if veto:
            self.poses_vetoed += 1
        return bits

    def reply_kernel(self):
        """The TIME_SYNC_REPLY branch of :meth:`on_message` on the compiled core (bound by
        :meth:`mag_kernel` with the decoder's payloads), or None: ``kernel(offset, now_us)`` reads
        the reply's payload at ``payloads[offset]`` and returns 0 when it did the whole branch
        (``ct_sup_reply``: the same operations on the same state), 1 for a rare case (a node back
        or lost, a reply showing a clock step, a suspect interval open) that :meth:`on_message`
        must do: the kernel changed nothing then."""
        return self._sup.reply if self._sup is not None and self._sup_payloads else None

    def _pose_status_compiled(self, node: int, window_flags: int) -> int:
        """:meth:`pose_status` on the compiled core (``ct_sup_pose_status``: the same operations on
        the same state; bit 32 of its result the veto)."""
        r = self._pose_k(node, window_flags)
        self.vetoed(r >> 32)
        return r & 0xFFFFFFFF

    def vetoed(self, veto: int) -> None:
        """:meth:`pose_status`'s veto from its compiled kernel (``ct_sup_pose_status``'s bit 32, or a
        kernel's that chains it: :meth:`pose_kernel`): ``veto`` set, a veto counted."""
        self.veto = veto == 1
        if veto:
            self.poses_vetoed += 1

    def pose_kernel(self):
        """The ``SupMag`` whose ``pose_status`` :meth:`pose_status` calls on the compiled core (for a
        kernel that chains it; its veto then taken with :meth:`vetoed`), or None."""
        return self._sup if self.pose_status == self._pose_status_compiled else None

    # ------------------------------------------------------------ status
    def counters(self) -> dict:
        h, ts = self.health, self.timesync
        return {
            "sync_sent": ts.sent,
            "sync_replies": sum(ts.replies),
            "sync_rtt_us_min": min((r for r in ts.rtt_min_us if r), default=0),
            "sup_nodes_lost": h.lost_events,
            "sup_nodes_back": h.back_events,
            "sup_clock_steps": h.clock_steps,
            "sup_saturation_events": h.saturation_events,
            "sup_saturated_samples": h.saturated_samples,
            "sup_distortion_events": h.distortion_events,
            "sup_coil_status_missing": h.missing_status,
            "sup_flip_cmds": self.flips.sent,
            "sup_poses_vetoed": self.poses_vetoed,
            "sup_events_dropped": h.events_dropped,
        }
