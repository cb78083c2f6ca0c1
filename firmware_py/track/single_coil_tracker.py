"""The single-coil tracker and its actuation (``actuation = "adaptive"``, or
the fixed cycle with ``single_coil_fusion``).

Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``) sec. 2.1 and
Fig. 1, as stages of the firmware tick (:meth:`SingleCoilTracker.actuate`,
:meth:`SingleCoilTracker.measure`; the IMU samples arrive through
:meth:`SingleCoilTracker.on_imu`):

* between pulses the IMU carries each sensor's state: every ``IMU_SAMPLE``
  propagates that sensor's error-state EKF (``coiltrack.firmware.estimate.single_coil``)
  and a ``POSE`` goes out at the IMU rate (every ``pose_every`` samples);
* when: once per tick, when a pulse could start (``adaptive_lead_us`` ahead,
  after the quiet gap the previous window needs), the pose covariance is
  predicted for the instant that pulse would be measured, including the
  effect of a pulse still in flight (eq 4 does not need its value); if a
  position or orientation standard deviation would reach its ``sigma_max``
  (or no update was made for ``adaptive_max_interval_us``) a pulse is due
  (``adaptive.ActuationPolicy``); a tick that has run an EKF update leaves
  the decision to the next tick, for the same start (bounded tick: the two
  heaviest pieces of work of the mode never share one);
* which and how strong: the coil whose eq-4 update reduces the normalised
  uncertainty most, at the smallest candidate current that brings the
  triggering variable to its ``sigma_min``, within the driver limit and the
  magnetometer range (``adaptive.CoilChooser``,
  ``adaptive.saturation_current_limit`` with the latest quiet field);
* one ``COIL_PULSE_CMD`` is sent, scheduled ahead on the master clock and
  kept within the driver's duty limit; the EKF clones the pose at the
  pulse's mid time; when the pulse window closes (``coiltrack.firmware.measure.pulse``) its
  amplitude updates every sensor's EKF through the clone, with the
  commanded current (the driver regulates it; its 1 mA readback replaces it
  only when the driver reports a sag) and the current tolerance and the
  field-model error in the measurement covariance;
* consistency: the NIS of every update is gated (chi-square) and monitored
  over a window (``adaptive.NisMonitor``); a ferromagnetic object that makes
  the updates inconsistent (Schepers sec. 3.3) is reported
  (``EVT_DISTORTION``, ``POSE_DISTORTED``) and, until the window is
  consistent again, the measurement covariance is inflated by the observed
  excess and the gate steps aside, so the filter neither diverges on the
  biased pulses nor drifts on the IMU alone with every pulse rejected;
* acquisition: a sensor without a pose (boot, lost track, IMU gap) gets a
  full burst of every coil at its nominal current once its IMU streams. The
  amplitudes are brought to the burst's mid instant with the gyroscope,
  solved (the firmware's ``solver.PoseSolver``: Kuipers start, exact-model
  least squares), and the solution starts the EKF (the orientation carried
  to the present by the gyroscope integration); the burst's pulses are then
  applied again as single-coil updates at their own instants
  (``SchepersEKF.back_clone``), so the motion during the burst, which near
  the source biases the solution badly, is absorbed. Without an IMU the mode
  keeps acquiring once a cycle and reports magnetic-only poses;
* set/reset flips: about every 2 s no new pulse is decided until the
  windows in flight are closed, then the sensors are told to flip in the
  gap (``supervisor.flips``), which also keeps them from flipping on their
  own inside a window.

All arrays are allocated here, at start-up; the per-tick paths, the
acquisition included, write into them and create no numpy array
(``tests/adaptive/test_bench_adaptive.py`` counts).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.protocol.schema import (COIL_FAULT_CURRENT_SAG, CURRENT_LSB_A, EVT_DISTORTION,
                                       POSE_DEGRADED, POSE_DISTORTED, POSE_FUSED, POSE_INCONSISTENT, POSE_SATURATED,
                                       POSE_STALE, POSE_VALID)

from coiltrack.firmware.actuate.accuracy import FixedCycleReference, fixed_cycle_bounds, nis_bound_factor
from coiltrack.firmware.actuate.coil_choice import (POSE_DIM, ActuationPolicy, CoilChooser, NisMonitor, PoseCovUpdate, SingleCoilModel,
                       current_ladder, saturation_current_limit)
from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NONFINITE, EKF_NOT_PD, chi2_gate
from coiltrack.firmware.linalg import exp_rotvec
from coiltrack.firmware.actuate.fixed_cycle import FixedCycle
from coiltrack.firmware.measure.imu import ImuRing
from coiltrack.firmware.measure.pulse import PULSE_TOO_FEW, PULSE_UNUSABLE as _UNUSABLE
from coiltrack.firmware.rotation import quat_tuple as _quat
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.single_coil import CORE, ORI, POS, SchepersEKF
from coiltrack.firmware.pose.solver import PoseSolver
from coiltrack.firmware.track.magnetic import SOLVE_FAILED as _SOLVE_FAILED
from coiltrack.firmware.track.quality import PoseQuality, quality_from
from coiltrack.firmware.track.status import COIL_FATAL as _FATAL, input_status
#: EVT_DISTORTION detail: bit 8 marks the NIS monitor as the detector, bit 31 the all-clear
_EVT_NIS = 1 << 8
_EVT_CLEAR = 1 << 31
#: pulses per coil remembered for the duty-cycle check (an array size: at most
#: ``coil_duty_window_us`` / (pulse + gap) pulses fit in the window, 12 at the defaults)
_DUTY_HIST = 32


class _Pulse:
    """One commanded pulse whose window is not closed yet."""

    __slots__ = ("active", "coil", "pid", "start", "end", "current", "measured", "faults", "status",
                 "clone", "acq")

    def __init__(self):
        self.active = False
        self.coil = 0
        self.pid = 0
        self.start = 0
        self.end = 0
        self.current = 0.0
        self.measured = 0.0
        self.faults = 0
        self.status = False
        self.clone = -1
        self.acq = False


class _Sensor:
    """Per-sensor state of the adaptive mode (one EKF per sensor and IMU)."""

    def __init__(self, channel, cfg, n_coils: int, ekf: SchepersEKF, monitor: NisMonitor):
        self.track = channel
        self.node = channel.node
        self.ekf = ekf
        self.monitor = monitor
        self.mon_t = 0                             # when the monitor last heard an update
        self.P6 = np.zeros((POSE_DIM, POSE_DIM))
        self.pp = np.zeros(3)
        self.Rd = np.eye(3)                        # the orientation a decision was made at
        self.quiet = np.zeros(3)
        self.have_quiet = False
        self.acc = np.zeros(3)
        self.gyr = np.zeros(3)
        self.imu = ImuRing(cfg.imu_ring_capacity)
        self.q = np.zeros(4)
        self.var6 = np.zeros(POSE_DIM)
        self.i_lim = np.zeros(n_coils)
        self.S = np.zeros((3, n_coils))          # acquisition burst amplitudes
        self.Svar = np.zeros((3, n_coils))
        self.Sflags = np.zeros(n_coils, dtype=np.int64)
        self.acq_R = np.zeros((n_coils, 3, 3))   # gyro-integrated orientation at each burst pulse
        self.Ssig = np.zeros((3, n_coils))
        self.Sraw = np.zeros((3, n_coils))       # the burst as measured, each pulse in its own frame
        self.acq_G = np.zeros((n_coils, 3, 3))   # R_now^T R(t_j) from the gyroscope
        self.col = np.zeros(3)
        self.Rnow = np.eye(3)
        self.acq_have = np.zeros(n_coils, dtype=bool)
        self.dR = np.eye(3)
        self.R3 = np.eye(3)
        self.last_update_us = 0
        self.last_imu_us: int | None = None
        self.imu_samples = 0
        self.gated_in_row = 0
        self.bits = 0                  # sticky POSE_* bits of the last magnetic update
        self.hemisphere = np.array(cfg.hemisphere, dtype=float)
        self.position = np.zeros(3)
        self.have_pose = False
        self.distorted = False
        self.updates = 0
        self.gated = 0
        self.ref: FixedCycleReference | None = None     # accuracy_target = "fixed"
        self.ref_start_us = 0
        self.smax6 = np.zeros(POSE_DIM)                  # the bounds of the latest decision (m, rad)
        self.smin6 = np.zeros(POSE_DIM)


class SingleCoilTracker:
    """One single-coil EKF per sensor, and the pulses that feed it.

    Stages (composed by ``coiltrack.firmware.loop.Firmware``):
    :meth:`actuate` (decide the next pulse, or the fixed cycle's; flips),
    :meth:`measure` (close the windows, each an EKF update); inputs
    :meth:`on_imu` for every ``IMU_SAMPLE`` (propagation, fused POSEs),
    :meth:`on_coil_status`; :meth:`counters` for the status.
    """

    def __init__(self, cfg, coils, channels, pulses, closer, supervisor, tx, schedule: str = "adaptive",
                 core=_DEFAULT_CORE):
        self.cfg = cfg
        self.pulses_sched = pulses
        self.closer = closer
        self.supervisor = supervisor
        self.tx = tx
        self.solver = PoseSolver(coils, cfg.field_model, core=core)
        self.now_us = 0
        self.boot_us: int | None = None
        if schedule not in ("adaptive", "fixed"):
            raise ValueError("schedule must be 'adaptive' or 'fixed'")
        #: "adaptive" (Schepers) or "fixed": the X, Y, Z cycle at the nominal currents
        #: (``cycle_us``, ``spacing_us``, ``pulse_us``), each pulse a single-coil update
        self.schedule = schedule
        n = len(coils)
        self.n = n
        self.model = SingleCoilModel(coils, cfg.field_model, core)       # updates
        self.pmodel = SingleCoilModel(coils, cfg.field_model, core)      # decisions
        self.rmodel = SingleCoilModel(coils, cfg.field_model, core)      # the fixed-cycle reference
        d2r = math.pi / 180.0
        smax = (cfg.sigma_max_pos_m,) * 3 + (cfg.sigma_max_ori_deg * d2r,) * 3
        smin = (cfg.sigma_min_pos_m,) * 3 + (cfg.sigma_min_ori_deg * d2r,) * 3
        currents = cfg.adaptive_currents_a or current_ladder(
            min(cfg.adaptive_min_current_a, cfg.adaptive_max_current_a), cfg.adaptive_max_current_a,
            cfg.adaptive_current_levels)
        trace = cfg.bound_on == "trace"
        self.chooser = CoilChooser(n, currents, smax, smin, cfg.field_model_rel_sigma, cfg.current_tolerance_a,
                                   trace)
        self.policy = ActuationPolicy(smax, cfg.adaptive_max_interval_us, trace)
        self.pending_update = PoseCovUpdate()
        self.pulse_us = cfg.adaptive_pulse_us or cfg.pulse_us
        self.lead_us = cfg.adaptive_lead_us
        # expected amplitude variance of one pulse (coiltrack.firmware.measure.pulse: sigma^2 (1/n + 1/n_b))
        per = 1e6 / cfg.mag_rate_hz
        n_used = max(1, int((self.pulse_us - cfg.settle_us - cfg.guard_us) / per) - 1)
        n_base = max(2, 2 * int(cfg.baseline_us / per))
        self.var_amp = cfg.mag_sigma_t ** 2 * (1.0 / n_used + 1.0 / n_base)
        # mid time of the used samples, from the start edge
        self.mid_us = (cfg.settle_us + self.pulse_us - cfg.guard_us) // 2
        self.gap_us = cfg.fall_us + cfg.baseline_us + cfg.guard_us
        self.nominal = np.array([c.current for c in cfg.coils])
        self._cur = np.zeros(n)
        self._lim = np.zeros(n)
        self._zero3 = np.zeros(3)
        # recent pulses per coil (start, end), to stay within the driver's duty limit
        self._hist = np.zeros((n, _DUTY_HIST, 2), dtype=np.int64)
        self._histv = memoryview(self._hist)     # elements read as Python ints
        self._hist_k = [0] * n
        self.t_ref = 0
        self.acq_t = np.zeros(n, dtype=np.int64)        # mid times of the burst's pulses
        self.gravity = np.array(cfg.gravity_mps2, dtype=float)
        gate_p = cfg.nis_gate_probability
        self.sensors: dict[int, _Sensor] = {}
        for tr in channels:
            sid = tr.node
            ekf = SchepersEKF.from_config(cfg, core=core)
            mon = NisMonitor(window=cfg.nis_window, dof=3, gate=chi2_gate(3, gate_p), z=cfg.nis_alarm_z,
                             min_count=min(cfg.nis_window, 3), min_excess=cfg.nis_alarm_excess,
                             max_scale=cfg.nis_max_scale, feedback_updates=cfg.nis_feedback_updates)
            self.sensors[sid] = _Sensor(tr, cfg, n, ekf, mon)
            if cfg.accuracy_target == "fixed" and schedule == "adaptive":
                # the fixed cycle of [timing], its pulses' amplitude variance and mid time
                nf = max(1, int((cfg.pulse_us - cfg.settle_us - cfg.guard_us) / per) - 1)
                var_f = cfg.mag_sigma_t ** 2 * (1.0 / nf + 1.0 / n_base)
                self.sensors[sid].ref = FixedCycleReference(
                    self.nominal, cfg.first_cycle_us, cfg.cycle_us, cfg.spacing_us,
                    (cfg.settle_us + cfg.pulse_us - cfg.guard_us) // 2, var_f, cfg.field_model_rel_sigma,
                    cfg.current_tolerance_a, cfg.reference_avg_s * 1e6, cfg.sigma_range_exp_pos,
                    cfg.sigma_range_exp_ori, cfg.reference_warmup_us, core)
        self._sens = tuple(self.sensors.values())
        # POSE.quality (track.quality): a single pulse leaves no residual freedom, so the
        # consistency is the update's NIS per dimension and the quiet field's, kept per sensor
        # and applied to the filter's position covariance at each fused pose
        self.quality = PoseQuality(cfg, 0, channels)
        self.q_scale = float(cfg.quality_error_scale_m)
        self.q_x = {sid: 0.0 for sid in self.sensors}
        self.slots = tuple(_Pulse() for _ in range(max(2, n)))
        self._order = [0] * len(self.slots)
        self._s6 = [0.0] * 6                 # one popped IMU sample (f, w)
        self.next_free_us = cfg.first_cycle_us - self.lead_us
        self.next_acq_us = cfg.first_cycle_us - cfg.lead_us
        self.acq_active = False
        self._decided_stamp = -1
        self._decided_us = 0
        self._updated_us = -1            # the tick of the last EKF update (the decision then waits)
        self._held_start = -1            # the start a decision put off to the next tick keeps
        self._dec_phase = 0              # the decision's next part (0: none in progress; see _decide_predict)
        self._dec_start = 0
        self._dec_ws = None
        self._dec_var = 0.0
        self._pm_for = None              # the sensor pmodel was last evaluated for, in this decision
        self.cycle = FixedCycle(n, cfg.first_cycle_us, cfg.cycle_us, cfg.spacing_us, cfg.pulse_us, self.lead_us)
        self.last_flip_cmd_us = -(1 << 62)
        self._warming = False            # the fixed cycle after a start (``reference_warmup_us``)
        self.last_pulse_end = 0
        # counters
        self.pulses = 0
        self.acquisitions = 0
        self.updates = 0
        self.gated = 0
        self.unusable = 0
        self.distortion_events = 0
        self.reacquired = 0
        self.no_current = 0

    # ------------------------------------------------------------ inputs
    def on_mag(self, msg, lsb: float) -> None:
        """Samples of nodes that are not tracked sensors are not used."""

    def on_imu(self, msg, now_us: int) -> None:
        """Queue an IMU sample; the track stage propagates it."""
        s = self.sensors.get(msg.node)
        if s is not None:
            s.imu.push(msg)

    def track(self, now_us: int) -> None:
        """Propagate each sensor's EKF through its queued IMU samples."""
        s6 = self._s6
        for s in self._sens:
            while True:
                t = s.imu.pop_sample(s6)
                if t < 0:
                    break
                a, g = s.acc, s.gyr
                a[0], a[1], a[2], g[0], g[1], g[2] = s6
                self._propagate(s, t, now_us)

    def _propagate(self, s: _Sensor, t: int, now_us: int) -> None:
        ekf = s.ekf
        if s.last_imu_us is not None:
            gap = t - s.last_imu_us
            if gap <= 0:
                return
            if gap > self.cfg.imu_timeout_us:
                # a hole in the stream: the state cannot be carried across it
                ekf.restart_inputs()
                if ekf.initialized:
                    self._lose(s)
        s.last_imu_us = t
        ekf.propagate(t, s.acc, s.gyr)
        if s.ref is not None and ekf.initialized:
            s.ref.step(ekf, t, self.rmodel)
        s.imu_samples += 1
        if self.acq_active:
            self._note_acq_orientation(s, t)
        if ekf.initialized and s.imu_samples % self.cfg.pose_every == 0:
            self._emit_fused(s, t, now_us)

    def _note_acq_orientation(self, s: _Sensor, t: int) -> None:
        """Gyro-integrated orientation at the mid time of each burst pulse
        (``R(t_j) = R(t) exp(-[w (t - t_j)]x)``), to bring the burst's
        amplitudes to one instant before solving."""
        ekf = s.ekf
        w = ekf.w
        for j in range(self.n):
            if not s.acq_have[j] and t >= self.acq_t[j]:
                h = -(t - int(self.acq_t[j])) * 1e-6
                exp_rotvec(float(w[0]) * h, float(w[1]) * h, float(w[2]) * h, s.dR)
                np.matmul(ekf.R, s.dR, out=s.acq_R[j])
                s.acq_have[j] = True

    def on_coil_status(self, msg) -> None:
        for sl in self.slots:
            if sl.active and sl.coil == msg.coil and sl.pid == msg.pulse_id:
                sl.measured = msg.current_ma * CURRENT_LSB_A
                sl.faults = msg.faults
                sl.status = True
                if msg.end_us > msg.start_us:
                    sl.start = msg.start_us
                    sl.end = msg.end_us
                return      # (the firmware reports the fault event)

    # ------------------------------------------------------------ stages
    def actuate(self, now_us: int) -> None:
        """Decide the next pulse (or the fixed cycle's), and the flips."""
        if self.boot_us is None:
            self.boot_us = now_us
        self.now_us = now_us
        self._decide(now_us)
        self._flip(now_us)

    def measure(self, now_us: int) -> None:
        """Close the windows whose samples are in: each an EKF update."""
        if self.boot_us is None:
            self.boot_us = now_us
        self.now_us = now_us
        self._close(now_us)

    def _flip(self, now_us: int) -> None:
        """Set/reset flips outside every pulse window (thesis sec 5.5, 7.2).

        Pulses are decided just in time, so there is no planned quiet gap as
        in the fixed cycle: every ``flip_every_us`` no new pulse is decided
        until those in flight are closed, then the sensors are told to flip
        a few milliseconds ahead and the next pulse may not start before that
        flip's trailing baseline has passed. The command also keeps the
        sensors from flipping on their own (which could land in a window)."""
        if now_us - self.last_flip_cmd_us < self.cfg.flip_every_us or self._n_active() or self._dec_phase:
            return
        cfg = self.cfg
        fl = self.supervisor.flips
        t0 = now_us + 1_000
        if (self.schedule == "fixed" or self._warming) and not self.acq_active:
            nxt = self.cycle.start_us()
            if nxt - cfg.baseline_us - 2 * cfg.guard_us < t0 + fl.min_gap_us:
                return
        fl.plan(now_us, t0, t0 + fl.min_gap_us, self.tx.send)
        at = fl.last_at_us
        self.next_free_us = max(self.next_free_us, at + cfg.baseline_us + cfg.guard_us + cfg.guard_us)
        self.last_flip_cmd_us = now_us

    # ------------------------------------------------------------ windows
    def _close(self, now_us: int) -> None:
        cfg = self.cfg
        # oldest first, so the updates are applied in time order
        m = 0
        for i, sl in enumerate(self.slots):
            if sl.active and not (sl.acq and sl.clone == -2):
                self._order[m] = i
                m += 1
        for a in range(1, m):
            j = a
            while j > 0 and self.slots[self._order[j - 1]].start > self.slots[self._order[j]].start:
                self._order[j - 1], self._order[j] = self._order[j], self._order[j - 1]
                j -= 1
        for k in range(m):
            sl = self.slots[self._order[k]]
            if not self.closer.ready(sl.start, sl.end, now_us):
                continue
            self._close_one(sl, now_us)
            if not sl.acq:
                sl.active = False
        if self.acq_active:
            for sl in self.slots:
                if sl.active and sl.acq and sl.clone != -2:
                    return
            self._finish_acquisition(now_us)

    def _close_one(self, sl: _Pulse, now_us: int) -> None:
        cfg = self.cfg
        # the driver regulates the commanded current; its measurement (1 mA steps, noisy)
        # replaces it only when the driver reports that it could not (supply sag)
        current = sl.current
        sag = bool(sl.faults & COIL_FAULT_CURRENT_SAG) and sl.measured != 0.0
        if sag:
            current = sl.measured
        fatal = bool(sl.faults & _FATAL) or (sl.status and sl.measured == 0.0)
        health = self.supervisor.health
        for s in self._sens:
            tr = s.track
            flags = self.closer.close_one(tr, sl.coil, sl.pid, sl.start, sl.end)
            t0 = sl.start - cfg.baseline_us - cfg.guard_us
            t1 = sl.end + cfg.fall_us + cfg.baseline_us
            suspect = health.suspect(tr.node, t0, t1) or health.suspect(cfg.coil_driver_id, t0, t1)
            if sl.acq:
                j = sl.coil
                s.S[:, j] = tr.amp
                s.Svar[:, j] = tr.amp_var
                s.Sflags[j] = flags | (PULSE_TOO_FEW if (fatal or suspect) else 0)
                self._cur[j] = current
                continue
            bits = input_status(flags, sl.faults | (COIL_FAULT_CURRENT_SAG if sag else 0))
            if (flags & _UNUSABLE) or fatal or suspect or not s.ekf.initialized:
                self.unusable += 1
                s.bits = bits | (s.bits & POSE_DISTORTED)
                continue
            self._update(s, sl, current, bits, now_us)
        if sl.acq:
            sl.clone = -2
        else:
            for s in self._sens:
                if sl.clone >= 0:
                    s.ekf.release_clone(sl.clone)

    def _update(self, s: _Sensor, sl: _Pulse, current: float, bits: int, now_us: int) -> None:
        self._updated_us = now_us
        cfg = self.cfg
        ekf = s.ekf
        # one NIS monitor per sensor: inflating the pulses of single coils instead proved
        # unstable (once the state is biased, the consistent-looking coil is the disturbed one)
        mon = s.monitor
        tr = s.track
        # the NIS tests the model only where the linearisation holds: the prior position
        # std small against the range
        P = ekf.P
        b = POS.start
        sp2 = max(float(P[b, b]), float(P[b + 1, b + 1]), float(P[b + 2, b + 2]))
        k = sl.clone
        pc = ekf.clone_p[k] if k >= 0 else ekf.p
        r2 = float(pc[0] * pc[0] + pc[1] * pc[1] + pc[2] * pc[2])
        linear = sp2 < cfg.nis_linear_fraction * cfg.nis_linear_fraction * r2
        # relative errors of the predicted field: the model, and the current
        rc = cfg.current_tolerance_a / max(abs(current), 1e-6)
        rel = math.sqrt(cfg.field_model_rel_sigma * cfg.field_model_rel_sigma + rc * rc)
        # once the monitor has judged the pulses inconsistent, the inflated covariance is the
        # protection: gating them as well would reject them all and leave the state to the IMU
        flags = ekf.update_single_coil(sl.clone, tr.amp, tr.amp_var, sl.coil, current, self.model,
                                       rel, mon.r_scale, gate=not mon.inconsistent)
        if flags & (EKF_NOT_PD | EKF_NONFINITE):
            self.unusable += 1
            return
        self.q_x[s.node] = self.quality.consistency(s.node, 0.0, ekf.nis / 3.0)
        was = s.distorted
        if linear:
            mon.add(ekf.nis_nominal)
            mon.add_used(ekf.nis)
            s.mon_t = now_us
        if flags & EKF_GATED:
            s.gated += 1
            self.gated += 1
            mon.gated += 1
            if not (mon.inconsistent or s.distorted):
                # rejections a flagged disturbance explains are no sign of a lost track:
                # an acquisition now would only start from a distorted solution
                s.gated_in_row += 1
            bits |= POSE_INCONSISTENT
        else:
            s.gated_in_row = 0
            s.updates += 1
            self.updates += 1
            s.last_update_us = now_us
        hdist = self.supervisor.health.is_distorted(s.node)
        self._forget(s, now_us)
        dist = mon.inconsistent
        if dist:
            bits |= POSE_DISTORTED | POSE_INCONSISTENT
        elif hdist:
            bits |= POSE_DISTORTED
        s.bits = bits
        if dist != was:
            self.distortion_events += 1 if dist else 0
            self.tx.event(EVT_DISTORTION, (s.node | _EVT_NIS) | (0 if dist else _EVT_CLEAR))
        s.distorted = dist
        # lost: updates rejected again and again, or an uncertainty beyond any use
        P = ekf.P
        big = cfg.acquire_sigma_m * cfg.acquire_sigma_m
        if (s.gated_in_row >= cfg.reacquire_after
                or P[POS.start, POS.start] > big or P[POS.start + 1, POS.start + 1] > big
                or P[POS.start + 2, POS.start + 2] > big):
            self.reacquired += 1
            self._lose(s)

    def _forget(self, s: _Sensor, now_us: int) -> None:
        """Forget a verdict that no update has tested for a while."""
        if s.monitor.count and now_us - s.mon_t > self.cfg.nis_forget_us:
            s.monitor.reset()

    def _lose(self, s: _Sensor) -> None:
        if s.ref is not None:
            s.ref.stop()
        s.ekf.reset()
        s.monitor.reset()
        s.gated_in_row = 0
        self.next_acq_us = min(self.next_acq_us, self.now_us)

    # ------------------------------------------------------------ decisions
    def _free_slot(self) -> int:
        for i, sl in enumerate(self.slots):
            if not sl.active:
                return i
        return -1

    def _n_active(self) -> int:
        k = 0
        for sl in self.slots:
            if sl.active:
                k += 1
        return k

    def _decide(self, now_us: int) -> None:
        if self._dec_phase:                 # the decision's next part
            if self._dec_phase == 1:
                self._decide_limits()
            else:
                self._decide_choose()
            return
        cfg = self.cfg
        held = self._held_start
        self._held_start = -1
        if self.acq_active:
            return
        need_acq = False
        for s in self._sens:
            if not s.ekf.initialized:
                need_acq = True
        if need_acq:
            if self._n_active() == 0 and now_us >= self.next_acq_us and self._imu_ready(now_us):
                self._start_acquisition(now_us)
            return
        # lost: an uncertainty beyond any use, or no usable pulse for a long time
        big = cfg.acquire_sigma_m * cfg.acquire_sigma_m
        for s in self._sens:
            P = s.ekf.P
            b = POS.start
            if (P[b, b] > big or P[b + 1, b + 1] > big or P[b + 2, b + 2] > big
                    or now_us - s.last_update_us > 4 * cfg.adaptive_max_interval_us):
                self.reacquired += 1
                self._lose(s)
                return
        if self._n_active() >= 2:
            return
        # after a start the fixed cycle itself, for reference_warmup_us (accuracy_target "fixed"):
        # its full-current pulses of every coil, while the errors are too large for eq 4
        self._warming = False
        for s in self._sens:
            if s.ref is not None and s.ref.active and now_us - s.ref_start_us < cfg.reference_warmup_us:
                self._warming = True
        if self.schedule == "fixed":
            self._decide_fixed(now_us)
            return
        if self._warming:
            n0 = self.pulses
            self._decide_fixed(now_us)
            if self.pulses != n0 or self._n_active() >= 2:
                return
            # between the cycle's pulses, a pulse on demand only where the filter is far behind the
            # fixed cycle's present covariance (see _bounds), ending before the cycle's next pulse
        elif now_us - self.last_flip_cmd_us >= cfg.flip_every_us:
            return      # a flip is due: let the pulses in flight close first (see _flip)
        start = max(now_us + self.lead_us, self.next_free_us)
        if held >= 0:           # put off from the last tick: the start it had (lead less one tick)
            start = max(held, self.next_free_us, now_us + cfg.tick_us)
        if start - now_us > self.lead_us + cfg.tick_us:
            return
        if self._warming and start + self.pulse_us + self.gap_us + cfg.tick_us > self.cycle.start_us():
            return
        # the prediction changes only when an IMU sample (or an update) has moved a filter
        stamp = 0
        for s in self._sens:
            stamp += s.imu_samples + s.updates + s.gated
        if stamp == self._decided_stamp and now_us - self._decided_us < cfg.decision_refresh_us:
            return
        if self._updated_us == now_us and held < 0 and start - now_us > 2 * cfg.tick_us:
            # bounded tick: this tick has run an EKF update (the heaviest matrix work of the mode);
            # the decision (a prediction per sensor and pulse in flight, the coil choice) runs in
            # the next one, for the same start
            self._held_start = start
            return
        self._decided_stamp = stamp
        self._decided_us = now_us
        self._decide_predict(start)

    # A decision runs in three ticks (bounded tick): the prediction at the measurement time
    # (``_decide_predict``), the current limits (``_decide_limits``) and the coil choice with its
    # command (``_decide_choose``). The first reads everything the others use of the filters
    # (covariance, orientation, quiet sample, NIS verdict) in its own tick, so the decision is the
    # one a single tick would make; its command leaves two ticks later, for the same start
    # (``adaptive_lead_us`` ahead). No flip and no other decision runs in between.
    def _decide_predict(self, start: int) -> None:
        """Predicted covariance at the measurement time, with the pulses in flight; which sensor
        is worst off, and whether a pulse is due."""
        cfg = self.cfg
        now_us = self.now_us
        t_m = start + self.mid_us
        self._pm_for = None
        worst = -1.0
        ws = None
        due = False
        for s in self._sens:
            ekf = s.ekf
            np.copyto(s.Rd, ekf.R)
            ekf.predict_pose(t_m - (ekf.t_us if ekf.t_us is not None else now_us), s.P6, s.pp)
            self._bounds(s)
            self.policy.set_bounds(s.smax6)
            for sl in self.slots:
                if sl.active and not sl.acq:
                    self._model_at(s)
                    self.pending_update.apply(s.P6, self.pmodel.H[sl.coil], self.pmodel.h[sl.coil], sl.current,
                                              self.var_amp * s.monitor.r_scale,
                                              cfg.field_model_rel_sigma, cfg.current_tolerance_a)
            if self.policy.due(s.P6, now_us, s.last_update_us):
                due = True
            u = self.policy.worst(s.P6)
            if u > worst:
                worst = u
                ws = s
        if not due or ws is None:
            return
        for s in self._sens:
            self._refresh_quiet(s)
        # the expected amplitude variance, inflated while the pulses prove inconsistent
        self._forget(ws, now_us)
        self._dec_var = self.var_amp * ws.monitor.r_scale
        self._dec_ws = ws
        self._dec_start = start
        self._dec_phase = 1

    def _decide_limits(self) -> None:
        """Current limits: the driver's, every sensor's magnetometer range, the coils' duty."""
        cfg = self.cfg
        lim = self._lim
        lim.fill(cfg.adaptive_max_current_a)
        for s in self._sens:
            self._model_at(s)
            # the field grows as r^-3: allow for the sensor being saturation_sigmas stds closer
            r = math.sqrt(float(s.pp[0] * s.pp[0] + s.pp[1] * s.pp[1] + s.pp[2] * s.pp[2]))
            sp = math.sqrt(max(float(s.P6[0, 0] + s.P6[1, 1] + s.P6[2, 2]), 0.0))
            gain = (r / max(r - cfg.saturation_sigmas * sp, 0.5 * r)) ** 3 if r > 0.0 else 8.0
            for c in range(self.n):
                if s.have_quiet:
                    i = saturation_current_limit(self.pmodel.h[c], s.quiet, cfg.mag_range_t,
                                                 cfg.saturation_margin, gain)
                else:       # no quiet sample yet: assume the largest earth field on every axis
                    i = saturation_current_limit(self.pmodel.h[c], self._zero3,
                                                 cfg.mag_range_t - cfg.earth_field_max_t / cfg.saturation_margin,
                                                 cfg.saturation_margin, gain)
                if i < lim[c]:
                    lim[c] = i
        for c in range(self.n):
            if not self._duty_ok(c, self._dec_start, self.pulse_us):
                lim[c] = 0.0
        ws = self._dec_ws
        self._model_at(ws)
        self.policy.set_bounds(ws.smax6)
        self.chooser.set_bounds(ws.smax6, ws.smin6)
        self._dec_phase = 2

    def _decide_choose(self) -> None:
        """The coil and current of the pulse (``actuate.coil_choice``), and its command."""
        self._dec_phase = 0
        ws = self._dec_ws
        coil = self.chooser.choose(ws.P6, self.pmodel, self._dec_var, self._lim)
        if coil < 0:
            self.no_current += 1
            return
        self._command(coil, self.chooser.current, self._dec_start, self.pulse_us, False, self.now_us)

    def _model_at(self, s: _Sensor) -> None:
        """``pmodel`` at sensor ``s``'s predicted pose (``s.pp``, and ``s.Rd``: the filter's
        orientation in the decision's first tick), evaluated once per decision and sensor: the model keeps the last evaluation, and nothing
        in a decision moves the pose it is evaluated at (3 coil field evaluations saved
        per pulse in flight and per decision)."""
        if self._pm_for is not s:
            self.pmodel.evaluate(s.pp, s.Rd)
            self._pm_for = s

    def _bounds(self, s: _Sensor) -> None:
        """The bounds (``s.smax6``, ``s.smin6``; m, rad) the decision holds for sensor ``s``
        at its predicted position ``s.pp``.

        ``accuracy_target = "stated"``: ``sigma_max_*`` and ``sigma_min_*``, scaled as
        ``(r / sigma_range_ref_m)^exp`` when ``sigma_range_ref_m`` > 0 (an accuracy stated
        relative to the range). ``"fixed"``: from the fixed cycle's predicted mean variance
        (``accuracy.fixed_cycle_bounds``; the stated bounds until the reference has started).
        With ``nis_feedback`` the variance bounds are then divided by the NIS excess
        (``accuracy.nis_bound_factor``): the accuracy is asked of the errors, not of the
        covariance."""
        cfg = self.cfg
        mx, mn = s.smax6, s.smin6
        if s.ref is not None and s.ref.active:
            ref = s.ref
            r = math.sqrt(float(s.pp[0] * s.pp[0] + s.pp[1] * s.pp[1] + s.pp[2] * s.pp[2]))
            fixed_cycle_bounds(ref.avg, cfg.fixed_accuracy_ratio, cfg.adaptive_min_ratio, mx, mn,
                               ref.law_now(r, 0), ref.law_now(r, 1))
            if self._warming:
                # the fixed cycle runs; a pulse between its pulses only when the filter's variance
                # would pass reference_catchup times the fixed cycle's present one
                Pr = ref.P
                k2 = cfg.reference_catchup * cfg.fixed_accuracy_ratio ** 2
                for k, i in ((0, POS.start), (1, POS.start + 1), (2, POS.start + 2),
                             (3, ORI.start), (4, ORI.start + 1), (5, ORI.start + 2)):
                    v = float(Pr[i, i]) * k2
                    mx[k] = math.sqrt(v) if v > 0.0 else 0.0
                    mn[k] = cfg.adaptive_min_ratio * float(mx[k])
        else:
            sp = so = 1.0
            if cfg.sigma_range_ref_m > 0.0:
                r = math.sqrt(float(s.pp[0] * s.pp[0] + s.pp[1] * s.pp[1] + s.pp[2] * s.pp[2]))
                x = max(r, 1e-3) / cfg.sigma_range_ref_m
                sp = x ** cfg.sigma_range_exp_pos
                so = x ** cfg.sigma_range_exp_ori
            d2r = math.pi / 180.0
            for k in range(3):
                mx[k] = cfg.sigma_max_pos_m * sp
                mn[k] = cfg.sigma_min_pos_m * sp
                mx[3 + k] = cfg.sigma_max_ori_deg * d2r * so
                mn[3 + k] = cfg.sigma_min_ori_deg * d2r * so
        if cfg.nis_feedback:
            f = math.sqrt(nis_bound_factor(s.monitor.excess, cfg.nis_feedback_max))
            if f != 1.0:
                for k in range(POSE_DIM):
                    mx[k] = float(mx[k]) / f
                    mn[k] = float(mn[k]) / f

    def _decide_fixed(self, now_us: int) -> None:
        """The fixed X, Y, Z cycle, each pulse commanded ``adaptive_lead_us``
        before its start and used as a single-coil update."""
        cyc = self.cycle
        if not cyc.due(now_us):
            return
        start = cyc.start_us()
        if start >= now_us + self.cfg.tick_us:
            j = cyc.coil
            self._command(j, float(self.nominal[j]), start, cyc.pulse_us, False, now_us)
        cyc.advance(now_us)      # a cycle that could not be scheduled in time is skipped

    def _duty_ok(self, c: int, start: int, length: int) -> bool:
        """Whether coil ``c`` may carry a pulse ``[start, start + length)``
        within ``coil_max_duty`` over any ``coil_duty_window_us`` (the limit
        the driver enforces; a refused pulse is a wasted decision)."""
        cfg = self.cfg
        end = start + length
        w0 = end - cfg.coil_duty_window_us
        on = length
        h = self._histv
        for k in range(_DUTY_HIST):
            s0 = h[c, k, 0]
            e0 = h[c, k, 1]
            if e0 > w0 and e0 > s0:
                on += min(e0, end) - max(s0, w0)
        return on <= cfg.duty_margin * cfg.coil_max_duty * cfg.coil_duty_window_us

    def _refresh_quiet(self, s: _Sensor) -> None:
        """The newest magnetometer sample, if no pulse was on when it was taken."""
        ring = s.track.ring
        nn = len(ring)
        if nn == 0:
            return
        t = ring.latest_t_us
        cfg = self.cfg
        for sl in self.slots:
            if sl.active and sl.start - cfg.guard_us <= t <= sl.end + cfg.fall_us + cfg.guard_us:
                return
        if self.last_pulse_end and self.last_pulse_end - self.pulse_us - cfg.guard_us <= t <= \
                self.last_pulse_end + cfg.fall_us + cfg.guard_us:
            return
        p = ring.slot(nn - 1)
        s.quiet[0] = ring.b[p, 0]
        s.quiet[1] = ring.b[p, 1]
        s.quiet[2] = ring.b[p, 2]
        s.have_quiet = True

    def _command(self, coil: int, current: float, start: int, length: int, acq: bool, now_us: int) -> int:
        i = self._free_slot()
        if i < 0:
            return -1
        sl = self.slots[i]
        pid, sl.current = self.pulses_sched.command(coil, current, start, length)   # as the driver regulates it
        sl.active = True
        sl.coil = coil
        sl.pid = pid
        sl.start = start
        sl.end = start + length
        sl.measured = 0.0
        sl.faults = 0
        sl.status = False
        sl.acq = acq
        sl.clone = -1
        if not acq:
            # a clone slot of the EKFs: the one no pulse in flight uses
            used0 = used1 = False
            for o in self.slots:
                if o is not sl and o.active and not o.acq:
                    used0 |= o.clone == 0
                    used1 |= o.clone == 1
            sl.clone = 0 if not used0 else (1 if not used1 else -1)
            if sl.clone >= 0:
                for s in self._sens:
                    s.ekf.schedule_clone(sl.clone, start + self.mid_us)
        self.next_free_us = start + length + self.gap_us
        self.last_pulse_end = start + length
        k = self._hist_k[coil]
        self._hist[coil, k, 0] = start
        self._hist[coil, k, 1] = start + length
        self._hist_k[coil] = (k + 1) % _DUTY_HIST
        self.pulses += 1
        return i

    # ------------------------------------------------------------ acquisition
    def _imu_ready(self, now_us: int) -> bool:
        """Acquire when every sensor's IMU is streaming (the burst is brought to one
        instant with the gyroscope, and the filter starts from it); a sensor that
        has sent no IMU sample for ``no_imu_us`` gets magnetic-only acquisitions."""
        for s in self._sens:
            live = s.last_imu_us is not None and now_us - s.last_imu_us <= self.cfg.imu_timeout_us
            if not live and now_us - (self.boot_us or 0) < self.cfg.no_imu_us:
                return False
        return True

    def _start_acquisition(self, now_us: int) -> None:
        cfg = self.cfg
        start0 = max(now_us + cfg.lead_us, self.next_free_us)
        mid = (cfg.settle_us + cfg.pulse_us - cfg.guard_us) // 2
        for s in self._sens:
            s.Sflags.fill(0)
            s.acq_have.fill(False)
        for j in range(self.n):
            self._command(j, float(self.nominal[j]), start0 + j * cfg.spacing_us, cfg.pulse_us, True, now_us)
            self.acq_t[j] = start0 + j * cfg.spacing_us + mid
        t_ref = (start0 + (self.n - 1) * cfg.spacing_us + start0 + cfg.pulse_us) // 2
        self.t_ref = t_ref
        for s in self._sens:
            s.ekf.schedule_clone(0, t_ref)
        last_end = start0 + (self.n - 1) * cfg.spacing_us + cfg.pulse_us
        self.supervisor.flips.plan(now_us, last_end + self.gap_us, last_end + self.gap_us + cfg.cycle_us // 4,
                                   self.tx.send)
        self.last_flip_cmd_us = now_us
        self.acq_active = True
        self.acquisitions += 1

    def _finish_acquisition(self, now_us: int) -> None:
        cfg = self.cfg
        for sl in self.slots:
            if sl.acq:
                sl.active = False
                sl.acq = False
                sl.clone = -1
        self.acq_active = False
        self.next_acq_us = now_us + cfg.cycle_us // 2
        lag_sig = cfg.init_sigma_vel
        for s in self._sens:
            ekf = s.ekf
            flags = 0
            for j in range(self.n):
                flags |= int(s.Sflags[j])
            status = input_status(flags, 0)
            imu = ekf.t_us is not None and bool(ekf.clone_taken[0]) and ekf.t_us >= self.t_ref
            have = True
            for j in range(self.n):
                have = have and bool(s.acq_have[j])
            np.copyto(s.Sraw, s.S)
            if imu and have:
                # the sensor turned during the burst: bring every amplitude to the
                # sensor frame at t_ref, S_ref[:, j] = R_ref^T R_j S[:, j]
                for j in range(self.n):
                    np.matmul(ekf.clone_R[0].T, s.acq_R[j], out=s.R3)
                    np.copyto(s.col, s.S[:, j])
                    np.matmul(s.R3, s.col, out=s.S[:, j])
            solved = False
            sv = self.solver             # the allocation-free PoseSolver
            if not (flags & PULSE_TOO_FEW):
                floor = (0.1 * cfg.mag_sigma_t) ** 2
                for i in range(3):
                    for j in range(self.n):
                        v = float(s.Svar[i, j])
                        s.Ssig[i, j] = math.sqrt(v if v > floor else floor)
                hemi = s.position if s.have_pose else s.hemisphere
                solved = not (sv.solve(s.S, self._cur, s.Ssig, hemi) & _SOLVE_FAILED)
            if not solved:
                ekf.release_clone(0)
                continue
            p, R, cov = sv.position, sv.rotation, sv.covariance
            s.position[:] = p
            s.have_pose = True
            status |= POSE_VALID
            self.tx.pose_cov6(s.node, self.t_ref, p, _quat(R), cov, status)
            if not (imu and have):
                ekf.release_clone(0)
                continue    # no IMU over the burst: stay magnetic-only, acquire again
            # carry the orientation from t_ref to the present with the gyroscope integration
            np.matmul(R, ekf.clone_R[0].T, out=s.R3)
            np.matmul(s.R3, ekf.R, out=s.Rnow)
            lag = (ekf.t_us - self.t_ref) * 1e-6
            half = (cfg.pulse_us + (self.n - 1) * cfg.spacing_us) * 0.5e-6
            # the solution is blurred by the motion during the burst (position) and carried
            # by an uncalibrated gyroscope (orientation): widen its covariance accordingly
            P6 = s.P6
            np.copyto(P6, cov)
            extra = (lag_sig * (lag + half)) ** 2
            gb = cfg.imu_gyro_bias_sigma * (lag + half)
            for i in range(3):
                P6[i, i] += extra
                P6[3 + i, 3 + i] += gb * gb + cfg.init_sigma_ori_deg ** 2 * (math.pi / 180.0) ** 2
            ekf.release_clone(0)
            for j in range(self.n):
                np.matmul(ekf.R.T, s.acq_R[j], out=s.acq_G[j])     # before R is replaced
            ekf.initialize(p, s.Rnow, P6, ekf.t_us, cfg.init_sigma_vel, cfg.imu_acc_bias_sigma,
                           cfg.imu_gyro_bias_sigma)
            self._refine(s)
            if s.ref is not None:
                s.ref.start(ekf.P[CORE, CORE], ekf.t_us)
                s.ref_start_us = now_us
            s.monitor.reset()
            s.last_update_us = now_us
            s.bits = status & (POSE_DEGRADED | POSE_SATURATED)

    def _refine(self, s: _Sensor) -> None:
        """Use the burst's pulses once more, as single-coil updates at their own instants.

        The burst solution assumes the sensor still for the whole burst; near the source a
        centimetre of motion between the pulses changes the fields by tens of percent and
        the solver fits a compromise pose with a tiny covariance. Applied one by one through
        clones predicted backwards from the new state (``SchepersEKF.back_clone``: the
        gyroscope's rotation increments, the velocity and the offsets in the transition),
        the nine amplitudes correct the position, orientation and velocity together."""
        cfg = self.cfg
        ekf = s.ekf
        for j in range(self.n):
            if s.Sflags[j] & _UNUSABLE:
                continue
            dt = (ekf.t_us - int(self.acq_t[j])) * 1e-6
            ekf.back_clone(1, dt, s.acq_G[j])
            c = float(self._cur[j])
            rc = cfg.current_tolerance_a / max(abs(c), 1e-6)
            rel = math.sqrt(cfg.field_model_rel_sigma * cfg.field_model_rel_sigma + rc * rc)
            col = s.col
            for i in range(3):
                col[i] = float(s.Svar[i, j])
            ekf.update_single_coil(1, s.Sraw[:, j], col, j, c, self.model, rel, 1.0, gate=False)
            ekf.release_clone(1)

    # ------------------------------------------------------------ output
    def _emit_fused(self, s: _Sensor, t_us: int, now_us: int) -> None:
        ekf = s.ekf
        status = POSE_VALID | POSE_FUSED | s.bits
        if s.distorted:
            status |= POSE_DISTORTED
        if now_us - s.last_update_us > self.cfg.stale_us:
            status |= POSE_STALE
        qw, qx, qy, qz = _quat(ekf.R)
        P = ekf.P
        p = ekf.p
        o = ORI.start
        b = POS.start
        vp = float(P[b, b]) + float(P[b + 1, b + 1]) + float(P[b + 2, b + 2])
        self.tx.pose(s.node, t_us, float(p[0]), float(p[1]), float(p[2]), qw, qx, qy, qz,
                     float(P[b, b]), float(P[b + 1, b + 1]), float(P[b + 2, b + 2]),
                     float(P[o, o]), float(P[o + 1, o + 1]), float(P[o + 2, o + 2]), status,
                     quality_from(vp, self.q_x[s.node], self.q_scale))

    def counters(self) -> dict:
        mons = [s.monitor for s in self._sens]
        return {
            "adaptive_pulses": self.pulses,
            "adaptive_acquisitions": self.acquisitions,
            "adaptive_updates": self.updates,
            "adaptive_gated": self.gated,
            "adaptive_unusable": self.unusable,
            "adaptive_reacquired": self.reacquired,
            "adaptive_distortion_events": self.distortion_events,
            "adaptive_distorted_updates": sum(m.flagged for m in mons),
            "adaptive_no_current": self.no_current,
            "adaptive_energy_j": round(self.pulses_sched.energy_j, 4),
        }
