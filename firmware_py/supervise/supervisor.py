"""The firmware's supervisor: time sync, node health, flip scheduling and the
pose status bits that come from them.

It joins :class:`coiltrack.firmware.supervise.timesync.TimeSyncMaster`,
:class:`coiltrack.firmware.supervise.health.Health` and
:class:`coiltrack.firmware.supervise.flips.FlipScheduler` to the firmware's tick with
three calls: ``on_message(msg, now)`` for every decoded frame,
``step(now, send, emit_event)`` once per tick, and ``pose_status(node)``
when a pose is made (it returns extra ``POSE_*`` bits and sets ``veto``
when the firmware cannot vouch for the pose: a coil status missing or fatal,
a node clock that stepped during the burst, or a saturated sample in a
window). It reads the firmware's
pulse schedule (``pulse_start``, ``pulse_end``, ``pulse_id``,
``pending_cycle``) without changing it.

Per burst: a ``TIME_SYNC`` right when the commands leave and three right after
the last pulse ends (plus the periodic ones), and one ``MAG_FLIP_CMD`` per
sensor for the quiet gap after the burst.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from coiltrack.protocol.schema import MAG_LSB_T, POSE_COIL_FAULT, POSE_DEGRADED, POSE_DISTORTED, POSE_INCONSISTENT

from coiltrack.firmware.supervise.flips import FlipScheduler
from coiltrack.firmware.measure.pulse import PULSE_SATURATED
from coiltrack.firmware.supervise.health import Health, HealthConfig
from coiltrack.firmware.supervise.timesync import TimeSyncMaster

_ID_HEARTBEAT = 0x01
_ID_SYNC_REPLY = 0x03
_ID_COIL_STATUS = 0x11
_ID_MAG = 0x20
_ID_IMU = 0x21


@dataclass(frozen=True)
class SupervisorConfig:
    sync_period_us: int = 250_000
    sync_latency_us: int = 0            # constant link latency added to the broadcast master time
    sync_step_threshold_us: int = 1_500
    sync_around_burst: bool = True
    flips: bool = True
    flip_min_gap_us: int = 10_000
    health: HealthConfig = field(default_factory=HealthConfig)


class Supervisor:
    def __init__(self, fw, scfg: SupervisorConfig | None = None):
        self.fw = fw
        self.scfg = scfg = scfg or SupervisorConfig()
        cfg = fw.cfg
        self.n = len(cfg.coils)
        self.sensor_ids = tuple(cfg.sensor_ids)
        self.driver_id = cfg.coil_driver_id
        self.timesync = TimeSyncMaster(self.sensor_ids + (self.driver_id,), scfg.sync_period_us,
                                       scfg.sync_latency_us, scfg.sync_step_threshold_us)
        self.health = Health(self.sensor_ids, self.driver_id, cfg.mag_rate_hz, scfg.health)
        self.health.set_coils(self.n)
        self.flips = FlipScheduler(self.sensor_ids, scfg.flip_min_gap_us)
        self._ps = memoryview(fw.pulse_start)
        self._pe = memoryview(fw.pulse_end)
        self._pid = memoryview(fw.pulse_id)
        self._burst = None
        self._first_burst = True
        self._margin = scfg.health.quiet_margin_us
        self._fall = cfg.fall_us
        self.veto = False
        self.poses_vetoed = 0

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
            prev = ts.first_suspect_us(i, now_us)           # before the candidates of a forward step
            stepped = ts.on_reply(msg, now_us)
            h.on_sync_reply(node, stepped, prev, now_us)
        elif mid == _ID_HEARTBEAT:
            h.heard(msg.node, now_us)

    def _quiet(self, t_us: int) -> bool:
        ps, pe, m = self._ps, self._pe, self._margin
        for j in range(self.n):
            if ps[j] - m <= t_us <= pe[j] + self._fall + m:
                return False
        return True

    # ------------------------------------------------------------ tick
    def step(self, now_us: int, send, emit_event) -> None:
        fw = self.fw
        pc = fw.pending_cycle
        if pc is not None and pc != self._burst:
            self._burst = pc
            missing = self.health.new_burst()
            if not self._first_burst:
                self.health.note_missing_status(missing)
            self._first_burst = False
            last_end = 0
            for j in range(self.n):
                if self._pe[j] > last_end:
                    last_end = self._pe[j]
            cfg = fw.cfg
            if self.scfg.sync_around_burst:
                # one as the commands leave, three 2 ms apart right after the last pulse: a node
                # takes a forward clock step only when three broadcasts agree (a stall of the
                # link delays frames 2 ms apart by amounts 2 ms apart, so it cannot fake one),
                # so a step during the burst shows in the replies before the burst's pose
                self.timesync.request(now_us)
                self.timesync.request(last_end + 1_000)
                self.timesync.request(last_end + 3_000)
                self.timesync.request(last_end + 5_000)
            if self.scfg.flips:
                quiet_from = last_end + cfg.fall_us + cfg.baseline_us + cfg.guard_us
                quiet_to = pc + cfg.cycle_us - cfg.baseline_us - cfg.guard_us
                self.flips.plan(now_us, quiet_from, quiet_to, send)
        if self.health.kick_sync:
            self.health.kick_sync = False
            self.timesync.kick()
            for node in self.health.back_nodes():
                self.timesync.forget(node)          # it re-acquires: its first replies are no step
        self.timesync.step(now_us, send)
        self.health.step(now_us)
        self.health.flush_events(emit_event)

    # ------------------------------------------------------------ poses
    def pose_status(self, node: int) -> int:
        """Extra POSE_* bits for the pose of ``node`` from the current burst; sets ``veto``."""
        cfg = self.fw.cfg
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
        t0 -= cfg.baseline_us + cfg.guard_us
        t1 += cfg.fall_us + cfg.baseline_us
        if h.suspect(node, t0, t1) or h.suspect(self.driver_id, t0, t1):
            bits |= POSE_INCONSISTENT | POSE_DEGRADED
            veto = True
        i = h._slot.get(node, -1)
        if i >= 0 and h.distorted[i]:
            bits |= POSE_DISTORTED
        tr = self.fw.tracks.get(node)
        if tr is not None:
            for j in range(self.n):
                if int(tr.flags[j]) & PULSE_SATURATED:   # clipped samples: the amplitude is meaningless
                    veto = True
        self.veto = veto
        if veto:
            self.poses_vetoed += 1
        return bits

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
