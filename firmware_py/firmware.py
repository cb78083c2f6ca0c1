"""The firmware main loop: one fixed-step ``tick(now_us)``.

Each tick, in order (no blocking call, no sleep):

1. receive: drain the Port, decode frames, route samples into the per-sensor
   sample rings, coil status into the schedule;
2. actuate: when the next cycle is ``lead_us`` away, send its X, Y, Z pulse
   commands (scheduled ahead on the master clock);
3. pulse windows: close each pulse window whose trailing baseline is
   complete (``firmware_py.pulse``);
4. solve: once all coils of a cycle are in, solve the 6-DOF pose (Kuipers
   acquisition, exact-model least squares; ``firmware_py.solve``);
5. transmit: pose, window reports, heartbeat.

Time is an integer count of microseconds on the master clock.
"""
from __future__ import annotations

import math

import numpy as np

from protocol import MSG, FrameDecoder, FrameEncoder, SCHEMA_HASH, PROTOCOL_VERSION
from protocol.schema import (CURRENT_LSB_A, EVT_COIL_FAULT, EVT_SCHEMA_MISMATCH, MAG_LSB_T,
                             POSE_COIL_FAULT, POSE_DEGRADED, POSE_SATURATED, POSE_VALID,
                             ROLE_FIRMWARE, STATE_RUNNING)

from .config import FirmwareConfig
from .field import Coil
from .port import Port
from .pulse import PULSE_SATURATED, PULSE_TOO_FEW, PulseExtractor, SampleRing
from .rotation import quat_from_matrix
from .solve import solve_pose
from .supervisor import Supervisor

HeartbeatMsg = MSG["HEARTBEAT"]
PulseCmdMsg = MSG["COIL_PULSE_CMD"]
PoseMsg = MSG["POSE"]
WindowMsg = MSG["PULSE_WINDOW"]
FaultMsg = MSG["FAULT_EVENT"]

_UNUSABLE = PULSE_TOO_FEW


class _SensorTrack:
    """Per-sensor state: sample ring, extractor, the cycle's amplitude matrix."""

    def __init__(self, node: int, cfg: FirmwareConfig):
        n = len(cfg.coils)
        self.node = node
        self.ring = SampleRing(cfg.ring_capacity)
        self.extractor = PulseExtractor(
            self.ring, settle_us=cfg.settle_us, fall_us=cfg.fall_us, baseline_us=cfg.baseline_us,
            guard_us=cfg.guard_us, min_pulse_samples=cfg.min_pulse_samples,
            min_baseline_samples=cfg.min_baseline_samples, drift_limit_t=cfg.drift_limit_t,
            sigma_t=cfg.mag_sigma_t,
            max_samples=max(64, int(2 * (cfg.pulse_us + 2 * cfg.baseline_us) * 1e-6 * cfg.mag_rate_hz) + 8))
        self.S = np.zeros((3, n))          # amplitudes, sensor frame, column per coil
        self.var = np.zeros((3, n))        # their variances
        self.flags = np.zeros(n, dtype=np.int64)
        self.done = np.zeros(n, dtype=bool)
        self.amp = np.zeros(3)
        self.used_times = np.zeros(self.extractor.max_samples, dtype=np.int64)
        self.amp_var = np.zeros(3)
        self.position = np.zeros(3)
        self.rotation = np.eye(3)
        self.have_pose = False
        self.hemisphere = np.array(cfg.hemisphere, dtype=float)
        self.samples = 0


class Firmware:
    """Fixed-size firmware state built once from a :class:`FirmwareConfig`."""

    def __init__(self, cfg: FirmwareConfig, port: Port):
        self.cfg = cfg.validate()
        self.port = port
        n = len(cfg.coils)
        self.coils = [Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.coils]
        self.nominal_current = np.array([c.current for c in cfg.coils])
        self.decoder = FrameDecoder()
        self.encoder = FrameEncoder(cfg.node_id)
        self.tracks = {sid: _SensorTrack(sid, cfg) for sid in cfg.sensor_ids}
        # pulse schedule of the current cycle
        self.cycle_start_us = cfg.first_cycle_us
        self.cycle_sent = False
        self.pulse_start = np.zeros(n, dtype=np.int64)
        self.pulse_end = np.zeros(n, dtype=np.int64)
        self.pulse_id = np.zeros(n, dtype=np.int64)
        self.measured_current = np.zeros(n)
        self.coil_faults = np.zeros(n, dtype=np.int64)
        self.next_pulse_id = 0
        self.pending_cycle: int | None = None   # start of the cycle whose windows are open
        self.q = np.zeros(4)
        self.next_heartbeat_us = 0
        self.boot_us: int | None = None
        # counters (status)
        self.ticks = 0
        self.poses = 0
        self.cycles = 0
        self.windows_flagged = 0
        self.schema_mismatches = 0
        self.peer_hashes: dict[int, int] = {}
        self.tx_errors = 0
        self.last_tick_us: int | None = None
        # time sync, node health, flip scheduling (firmware_py.supervisor)
        self.supervisor = Supervisor(self)

    # ------------------------------------------------------------------ tick
    def tick(self, now_us: int) -> None:
        if self.boot_us is None:
            self.boot_us = now_us
        self.ticks += 1
        self.last_tick_us = now_us
        self._receive()
        self._actuate(now_us)
        self._close_windows(now_us)
        self.supervisor.step(now_us, self._send, self._event)
        if now_us >= self.next_heartbeat_us:
            self._send(HeartbeatMsg(self.cfg.node_id, ROLE_FIRMWARE, STATE_RUNNING, PROTOCOL_VERSION,
                                    SCHEMA_HASH, now_us - self.boot_us, min(self.decoder.frames_bad, 0xFFFF)))
            self.next_heartbeat_us = now_us + self.cfg.heartbeat_us

    # ------------------------------------------------------------- receive
    def _receive(self) -> None:
        data = self.port.read()
        if not data:
            return
        for msg in self.decoder.feed(data):
            mid = msg.ID
            self.supervisor.on_message(msg, self.last_tick_us)
            if mid == 0x20:  # MAG_SAMPLE
                tr = self.tracks.get(msg.node)
                if tr is not None:
                    tr.ring.push(msg.t_us, msg.x * MAG_LSB_T, msg.y * MAG_LSB_T, msg.z * MAG_LSB_T,
                                 bool(msg.flip & 2), msg.flip & 1)
                    tr.samples += 1
            elif mid == 0x11:  # COIL_STATUS
                self._on_coil_status(msg)
            elif mid == 0x01:  # HEARTBEAT
                self.peer_hashes[msg.node] = msg.schema_hash
                if msg.schema_hash != SCHEMA_HASH or msg.proto_version != PROTOCOL_VERSION:
                    self.schema_mismatches += 1
                    self._event(EVT_SCHEMA_MISMATCH, msg.node)

    def _on_coil_status(self, msg) -> None:
        c = msg.coil
        if c >= len(self.coils) or msg.pulse_id != self.pulse_id[c]:
            return
        self.measured_current[c] = msg.current_ma * CURRENT_LSB_A
        self.coil_faults[c] = msg.faults
        if msg.faults:
            self._event(EVT_COIL_FAULT, (c << 8) | msg.faults)
        # the driver reports the actual edges on the master clock
        if msg.end_us > msg.start_us:
            self.pulse_start[c] = msg.start_us
            self.pulse_end[c] = msg.end_us

    # ------------------------------------------------------------- actuate
    def _actuate(self, now_us: int) -> None:
        cfg = self.cfg
        if self.cycle_sent or now_us < self.cycle_start_us - cfg.lead_us:
            return
        if self.pending_cycle is not None:
            return  # previous cycle's windows still open; keep the schedule aligned
        t0 = self.cycle_start_us
        for j in range(len(self.coils)):
            start = t0 + j * cfg.spacing_us
            pid = self.next_pulse_id
            self.next_pulse_id = (pid + 1) & 0xFFFF
            self.pulse_start[j] = start
            self.pulse_end[j] = start + cfg.pulse_us
            self.pulse_id[j] = pid
            self.measured_current[j] = 0.0
            self.coil_faults[j] = 0
            ma = int(round(self.nominal_current[j] / CURRENT_LSB_A))
            self._send(PulseCmdMsg(j, pid, ma, start, cfg.pulse_us))
        for tr in self.tracks.values():
            tr.done[:] = False
            tr.flags[:] = 0
        self.cycle_sent = True
        self.pending_cycle = t0

    # --------------------------------------------------------- pulse windows
    def _close_windows(self, now_us: int) -> None:
        if self.pending_cycle is None:
            return
        n = len(self.coils)
        all_done = True
        for tr in self.tracks.values():
            for j in range(n):
                if tr.done[j]:
                    continue
                start, end = int(self.pulse_start[j]), int(self.pulse_end[j])
                timed_out = now_us > end + self.cfg.fall_us + self.cfg.baseline_us + self.cfg.cycle_us // 2
                if not tr.extractor.ready(start, end) and not timed_out:
                    all_done = False
                    continue
                flags, n_used, n_base = tr.extractor.extract(start, end, tr.amp, tr.amp_var)
                tr.S[:, j] = tr.amp
                tr.var[:, j] = tr.amp_var
                tr.flags[j] = flags
                tr.done[j] = True
                if flags:
                    self.windows_flagged += 1
                first = last = 0
                if n_used:
                    m = tr.extractor.last_used_times(tr.used_times)
                    if m:
                        first, last = int(tr.used_times[0]), int(tr.used_times[m - 1])
                self._send(WindowMsg(tr.node, j, int(self.pulse_id[j]), first, last,
                                     min(n_used, 255), min(n_base, 255), flags & 0xFF))
        if not all_done:
            return
        for tr in self.tracks.values():
            self._solve_and_report(tr)
        self.cycles += 1
        self.pending_cycle = None
        self.cycle_sent = False
        self.cycle_start_us += self.cfg.cycle_us
        # a cycle that could not be scheduled in time is skipped, not crammed in
        while self.cycle_start_us - self.cfg.lead_us < now_us:
            self.cycle_start_us += self.cfg.cycle_us

    # --------------------------------------------------------------- solve
    def _solve_and_report(self, tr: _SensorTrack) -> None:
        cfg = self.cfg
        status = 0
        flags = int(np.bitwise_or.reduce(tr.flags))
        if flags & PULSE_SATURATED:
            status |= POSE_SATURATED
        if flags:
            status |= POSE_DEGRADED
        if np.any(self.coil_faults):
            status |= POSE_COIL_FAULT
        # pose time: middle of the burst
        t_pose = int((int(self.pulse_start[0]) + int(self.pulse_end[-1])) // 2)
        usable = not (flags & _UNUSABLE) and not np.any(self.coil_faults & 0x03)
        status |= self.supervisor.pose_status(tr.node)
        if self.supervisor.veto:   # coil status missing/fatal or a node clock stepped in the burst
            usable = False
        cov = None
        if usable:
            currents = np.where(self.measured_current != 0.0, self.measured_current, self.nominal_current)
            sigma = np.sqrt(np.maximum(tr.var, (0.1 * cfg.mag_sigma_t) ** 2))
            hemi = tr.position if tr.have_pose else tr.hemisphere
            try:
                p, R, cov = solve_pose(tr.S, self.coils, currents, sigma, hemisphere=hemi,
                                       model=cfg.field_model)
            except (ValueError, np.linalg.LinAlgError, FloatingPointError):
                p = R = cov = None
            if p is not None and np.all(np.isfinite(p)) and np.all(np.isfinite(cov)):
                tr.position[:] = p
                tr.rotation[:] = R
                tr.have_pose = True
                status |= POSE_VALID
            else:
                cov = None
        q = quat_from_matrix(tr.rotation, self.q)
        var = np.diag(cov) if cov is not None else np.full(6, float("inf"))
        p = tr.position
        self._send(PoseMsg(tr.node, t_pose, float(p[0]), float(p[1]), float(p[2]),
                           float(q[0]), float(q[1]), float(q[2]), float(q[3]),
                           *(float(min(v, 3.0e38)) for v in var), status))
        if status & POSE_VALID:
            self.poses += 1

    # ------------------------------------------------------------ transmit
    def _event(self, code: int, detail: int) -> None:
        t = self.last_tick_us or 0
        self._send(FaultMsg(self.cfg.node_id, t, code, detail & 0xFFFFFFFF))

    def _send(self, msg) -> None:
        try:
            self.port.write(self.encoder.encode(msg))
        except Exception:  # a full or broken link must not stop the loop
            self.tx_errors += 1

    # --------------------------------------------------------------- status
    def status(self) -> dict:
        d = {
            "ticks": self.ticks, "cycles": self.cycles, "poses": self.poses,
            "windows_flagged": self.windows_flagged, "schema_mismatches": self.schema_mismatches,
            "tx_errors": self.tx_errors,
        }
        d.update({"rx_" + k: v for k, v in self.decoder.counters().items()})
        d.update(self.supervisor.counters())
        return d
