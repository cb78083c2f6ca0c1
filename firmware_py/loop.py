"""The firmware main loop: one fixed-step ``tick(now_us)``.

Each tick, in order (no blocking call, no sleep):

1. receive: drain the Port, decode frames, route samples into the per-sensor
   sample rings, coil status into the schedule;
2. actuate: when the next cycle is ``lead_us`` away, send its X, Y, Z pulse
   commands (scheduled ahead on the master clock);
3. pulse windows: close each pulse window whose trailing baseline is
   complete (``coiltrack.firmware.measure.pulse``);
4. solve: once all coils of a cycle are in, solve the 6-DOF pose (Kuipers
   acquisition, exact-model least squares; ``coiltrack.firmware.pose.solver.PoseSolver``,
   allocation-free) and send it as the magnetic-only POSE;
5. predict: each received IMU sample goes through the sensor's orientation
   filter (thesis ch. 2) and the inertial step of its fusion filter (ch. 6),
   which queues a fused POSE at the IMU rate (``coiltrack.firmware.track.burst_fusion``);
6. update: after a burst, bring the pulses to one instant with the inertial
   motion, solve again and update the fusion filter at that instant;
7. transmit: fused poses, heartbeat (window reports and magnetic poses leave
   as they are made).

With ``actuation = "adaptive"`` steps 2-6 are the adaptive mode's
(``coiltrack.firmware.track.single_coil_tracker``, Schepers & Veltink 2010): single-coil pulses
on demand, each window an update of the sensor's single-coil EKF, which the
IMU samples propagate and which sends the fused POSEs.

Every buffer is created in ``__init__`` from the configuration; the
steady-state tick allocates no numpy array (``tests/firmware/test_alloc.py``).
Time is an integer count of microseconds on the master clock.
"""
from __future__ import annotations

import math
import time

import numpy as np

from coiltrack.protocol import MSG, FrameDecoder, FrameEncoder, SCHEMA_HASH, PROTOCOL_VERSION
from coiltrack.protocol.schema import (CURRENT_LSB_A, EVT_COIL_FAULT, EVT_SCHEMA_MISMATCH, MAG_LSB_T,
                             POSE_COIL_FAULT, POSE_DEGRADED, POSE_FUSED, POSE_INCONSISTENT, POSE_SATURATED,
                             POSE_STALE, POSE_VALID, ROLE_FIRMWARE, STATE_RUNNING)

from coiltrack.firmware.track.single_coil_tracker import AdaptiveMode
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.port import Port
from coiltrack.firmware.rotation import quat_tuple as _quat
from coiltrack.firmware.track.burst_fusion import PulseGate, SensorInertial, SourceInertial
from coiltrack.firmware.measure.pulse import PULSE_SATURATED, PULSE_TOO_FEW, PulseExtractor, SampleRing
from coiltrack.firmware.pose.solver import SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_NONFINITE, PoseSolver
from coiltrack.firmware.supervise.supervisor import Supervisor

HeartbeatMsg = MSG["HEARTBEAT"]
PulseCmdMsg = MSG["COIL_PULSE_CMD"]
PoseMsg = MSG["POSE"]
WindowMsg = MSG["PULSE_WINDOW"]
FaultMsg = MSG["FAULT_EVENT"]

_UNUSABLE = PULSE_TOO_FEW
_SOLVE_FAILED = SOLVE_BAD_INPUT | SOLVE_NO_START | SOLVE_NONFINITE
_F32_MAX = 3.0e38

# tick phases timed when ``Firmware.prof`` is set (``coiltrack perf``)
PHASES = ("receive", "windows", "solve", "predict", "update", "transmit")


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
        self.sigma = np.zeros((3, n))      # amplitude std for the solver
        self.pulse_mid = np.zeros(n, dtype=np.int64)   # mean time of each window's used samples
        self._Sv = memoryview(self.S)
        self._varv = memoryview(self.var)
        self._sigv = memoryview(self.sigma)
        self._flv = memoryview(self.flags)
        self._pmv = memoryview(self.pulse_mid)
        self.inertial: SensorInertial | None = None    # IMU, orientation and fusion filters


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
        # time sync, node health, flip scheduling (coiltrack.firmware.supervise.supervisor)
        self.supervisor = Supervisor(self)
        # pose solver, inertial filters (coiltrack.firmware.pose.solver, coiltrack.firmware.track.burst_fusion)
        self.solver = PoseSolver(self.coils, cfg.field_model)
        self.currents = np.zeros(n)
        self._curv = memoryview(self.currents)
        self._nomv = memoryview(self.nominal_current)
        self._mcv = memoryview(self.measured_current)
        self._cfv = memoryview(self.coil_faults)
        self._cycle_done = False
        self.source: SourceInertial | None = None
        gate = PulseGate(self.pulse_start, self.pulse_end, cfg.fall_us, cfg.compass_guard_us)
        self._fixed_phi = np.eye(3)                                   # a fixed source: Phi = I
        self._fixed_fref = np.array([-v for v in cfg.gravity_mps2])  # its specific force, source frame
        if cfg.fusion and cfg.actuation == "fixed" and not cfg.single_coil_fusion:
            if cfg.source_imu_id:
                self.source = SourceInertial(cfg.source_imu_id, cfg, gate)
            for tr in self.tracks.values():
                tr.inertial = SensorInertial(tr.node, cfg, gate, self._fixed_phi, self._fixed_fref, self.source)
        self.fused_poses = 0
        #: per-phase durations of the last tick (ns, ``PHASES`` order) when set to an int64 array
        self.prof = None
        # actuation = "adaptive": single-coil pulses on demand and the single-coil EKF
        # (coiltrack.firmware.track.single_coil_tracker) instead of the fixed cycle and the ch. 6 fusion;
        # single_coil_fusion: the fixed X, Y, Z cycle, each pulse an update of that EKF
        self.adaptive = (AdaptiveMode(self) if cfg.actuation == "adaptive"
                         else AdaptiveMode(self, "fixed") if cfg.single_coil_fusion else None)

    # ------------------------------------------------------------------ tick
    def tick(self, now_us: int) -> None:
        if self.boot_us is None:
            self.boot_us = now_us
        self.ticks += 1
        self.last_tick_us = now_us
        prof = self.prof
        if prof is not None:
            clk = time.perf_counter_ns
            t0 = clk()
        self._receive()
        if prof is not None:
            t1 = clk()
            prof[0] = t1 - t0
        self._actuate(now_us)
        self._close_windows(now_us)
        if prof is not None:
            t0 = clk()
            prof[1] = t0 - t1
        if self._cycle_done:
            self._finish_cycle(now_us)
        if prof is not None:
            t1 = clk()
            prof[2] = t1 - t0
        self._predict()
        if prof is not None:
            t0 = clk()
            prof[3] = t0 - t1
        self._fuse()
        if prof is not None:
            t1 = clk()
            prof[4] = t1 - t0
        self._transmit()
        self.supervisor.step(now_us, self._send, self._event)
        if now_us >= self.next_heartbeat_us:
            self._send(HeartbeatMsg(self.cfg.node_id, ROLE_FIRMWARE, STATE_RUNNING, PROTOCOL_VERSION,
                                    SCHEMA_HASH, now_us - self.boot_us, min(self.decoder.frames_bad, 0xFFFF)))
            self.next_heartbeat_us = now_us + self.cfg.heartbeat_us
        if prof is not None:
            prof[5] = clk() - t1

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
                elif self.source is not None and msg.node == self.source.node:
                    self.source.mag.push(msg.t_us, msg.x * MAG_LSB_T, msg.y * MAG_LSB_T, msg.z * MAG_LSB_T,
                                         bool(msg.flip & 2), msg.flip & 1)
            elif mid == 0x21:  # IMU_SAMPLE
                tr = self.tracks.get(msg.node)
                if tr is not None:
                    if self.adaptive is not None:
                        self.adaptive.on_imu(msg, self.last_tick_us)
                    elif tr.inertial is not None:
                        tr.inertial.imu.push(msg)
                elif self.source is not None and msg.node == self.source.node:
                    self.source.imu.push(msg)
            elif mid == 0x11:  # COIL_STATUS
                self._on_coil_status(msg)
            elif mid == 0x01:  # HEARTBEAT
                self.peer_hashes[msg.node] = msg.schema_hash
                if msg.schema_hash != SCHEMA_HASH or msg.proto_version != PROTOCOL_VERSION:
                    self.schema_mismatches += 1
                    self._event(EVT_SCHEMA_MISMATCH, msg.node)

    def _on_coil_status(self, msg) -> None:
        if self.adaptive is not None:
            self.adaptive.on_coil_status(msg)
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
        if self.adaptive is not None:       # pulses on demand, windows closed as they come
            self.adaptive.step(now_us)
            return
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
            ma = int(round(self._nomv[j] / CURRENT_LSB_A))   # Python floats: no 0-d arrays
            self._send(PulseCmdMsg(j, pid, ma, start, cfg.pulse_us))
        # the burst's pose refers to its middle (fusion: state kept at that instant)
        t_ref = (t0 + t0 + (len(self.coils) - 1) * cfg.spacing_us + cfg.pulse_us) // 2
        for tr in self.tracks.values():
            tr.done.fill(False)
            tr.flags.fill(0)
            if tr.inertial is not None:
                tr.inertial.schedule(t_ref)
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
                tr.pulse_mid[j] = (first + last) // 2 if last else (start + end) // 2
                self._send(WindowMsg(tr.node, j, int(self.pulse_id[j]), first, last,
                                     min(n_used, 255), min(n_base, 255), flags & 0xFF))
        if all_done:
            self._cycle_done = True

    def _finish_cycle(self, now_us: int) -> None:
        """All windows of the burst are closed: solve, report, move the schedule on."""
        self._cycle_done = False
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
        """Magnetic-only pose of one sensor from the burst's signal matrix
        (``PoseSolver``: Kuipers start, exact-model LM, covariance), sent as a
        POSE without ``POSE_FUSED``; a usable solution is handed to the fusion
        filter (``_fuse``)."""
        cfg = self.cfg
        n = len(self.coils)
        status = 0
        flags = 0
        fl = tr._flv
        for j in range(n):
            flags |= fl[j]
        faults = 0
        cf = self._cfv
        for j in range(n):
            faults |= cf[j]
        if flags & PULSE_SATURATED:
            status |= POSE_SATURATED
        if flags:
            status |= POSE_DEGRADED
        if faults:
            status |= POSE_COIL_FAULT
        # pose time: middle of the burst
        t_pose = int((int(self.pulse_start[0]) + int(self.pulse_end[-1])) // 2)
        usable = not (flags & _UNUSABLE) and not (faults & 0x03)
        status |= self.supervisor.pose_status(tr.node)
        if self.supervisor.veto:   # coil status missing/fatal or a node clock stepped in the burst
            usable = False
        solved = False
        sv = self.solver
        if usable:
            cur = self._curv
            mc = self._mcv
            nom = self._nomv
            for j in range(n):
                cur[j] = mc[j] if mc[j] != 0.0 else nom[j]
            floor = (0.1 * cfg.mag_sigma_t) ** 2
            var = tr._varv
            sig = tr._sigv
            for i in range(3):
                for j in range(n):
                    v = var[i, j]
                    sig[i, j] = math.sqrt(v if v > floor else floor)
            hemi = tr.position if tr.have_pose else tr.hemisphere
            st = sv.solve(tr.S, self.currents, tr.sigma, hemi)
            if not st & _SOLVE_FAILED:
                np.copyto(tr.position, sv.position)
                np.copyto(tr.rotation, sv.rotation)
                tr.have_pose = True
                solved = True
                status |= POSE_VALID
        p = tr.position
        qw, qx, qy, qz = _quat(tr.rotation)
        if solved:
            c = sv._cov
            v0, v1, v2, v3, v4, v5 = (min(c[0], _F32_MAX), min(c[7], _F32_MAX), min(c[14], _F32_MAX),
                                      min(c[21], _F32_MAX), min(c[28], _F32_MAX), min(c[35], _F32_MAX))
        else:
            v0 = v1 = v2 = v3 = v4 = v5 = _F32_MAX
        self._send(PoseMsg(tr.node, t_pose, float(p[0]), float(p[1]), float(p[2]), qw, qx, qy, qz,
                           v0, v1, v2, v3, v4, v5, status))
        if status & POSE_VALID:
            self.poses += 1
        ins = tr.inertial
        if ins is not None:
            if solved:
                np.copyto(ins.mag_position, sv.position)
                np.copyto(ins.mag_rotation, sv.rotation)
                np.copyto(ins.mag_cov, sv.covariance)
                ins.pending = True
                ins.stage = 0
                ins.pending_tick = self.ticks
            else:
                ins.pending = False

    # ---------------------------------------------------------- inertial
    def _predict(self) -> None:
        """Drain the IMU rings: the source's first (its orientation and
        specific force feed eq 6.8), then each sensor's."""
        if self.source is not None:
            self.source.process()
        for tr in self.tracks.values():
            if tr.inertial is not None:
                tr.inertial.process(tr.ring)

    def _fuse(self) -> None:
        """Delayed magnetic updates of the fusion filters: in the two ticks
        after the magnetic solve, the compensated solve, then the update at the
        burst's middle with the replay (``SensorInertial.fuse``), so that no
        tick carries more than one solve."""
        for tr in self.tracks.values():
            ins = tr.inertial
            if ins is not None and ins.pending and ins.pending_tick != self.ticks:
                ins.fuse(self.solver, tr.S, self.currents, tr.sigma, tr._pmv)
                return                   # one burst step per tick

    def _transmit(self) -> None:
        """Send the fused poses queued by the fusion filters (IMU rate)."""
        for tr in self.tracks.values():
            ins = tr.inertial
            if ins is None:
                continue
            fus = ins.fusion
            while True:
                k = fus.pop_output()
                if k < 0:
                    break
                d = fus._odv
                st = int(d[k, 13])
                status = POSE_VALID | POSE_FUSED
                if st & 1:
                    status |= POSE_STALE
                if st & 2:
                    status |= POSE_INCONSISTENT
                self._send(PoseMsg(tr.node, fus._otv[k], d[k, 0], d[k, 1], d[k, 2], d[k, 3], d[k, 4], d[k, 5],
                                   d[k, 6], min(d[k, 7], _F32_MAX), min(d[k, 8], _F32_MAX),
                                   min(d[k, 9], _F32_MAX), min(d[k, 10], _F32_MAX), min(d[k, 11], _F32_MAX),
                                   min(d[k, 12], _F32_MAX), status))
                fus.release_output()
                self.fused_poses += 1

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
        if self.adaptive is not None:
            d.update(self.adaptive.counters())
        ins = [tr.inertial for tr in self.tracks.values() if tr.inertial is not None]
        if ins:
            d.update({
                "fused_poses": self.fused_poses,
                "imu_samples": sum(i.samples for i in ins),
                "fusion_updates": sum(i.fusion.updates for i in ins),
                "fusion_rejected": sum(i.fusion.rejected for i in ins),
                "fusion_reinits": sum(i.fusion.reinits for i in ins),
                "fusion_compensated": sum(i.compensated for i in ins),
                "fusion_output_dropped": sum(i.fusion.out_dropped for i in ins),
                "compass_updates": sum(i.ori.compass_used for i in ins),
            })
            if self.source is not None:
                d["source_imu_samples"] = self.source.samples
        return d
