"""Acquisition of the single-coil mode: a burst of every coil starts a sensor's filter.

A sensor without a pose (boot, lost track, IMU gap) gets a full burst of
every coil at its nominal current once its IMU streams. The amplitudes are
brought to the burst's mid instant with the gyroscope, solved (the
firmware's ``pose.solver.PoseSolver``: Kuipers start, exact-model least
squares), and the solution starts the EKF (the orientation carried to the
present by the gyroscope integration); the burst's pulses are then applied
again as single-coil updates at their own instants
(``SchepersEKF.back_clone``, Schepers & Veltink 2010,
``seeds/000_e46ec0e8bf7ea271.txt`` sec. 2.1, eq 4), so the motion during the
burst, which near the source biases the solution badly, is absorbed. Without
an IMU the mode keeps acquiring once a cycle and reports magnetic-only poses.

:class:`BurstAcquisition` owns the burst's amplitudes and the solution; the
tracker (its ``host``) takes a started filter over (``tracking_started``).
All arrays are allocated here, at start-up.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.protocol.schema import POSE_VALID

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.linalg import exp_rotvec
from coiltrack.firmware.measure.pulse import PULSE_TOO_FEW, PULSE_UNUSABLE as _UNUSABLE
from coiltrack.firmware.pose.solver import PoseSolver
from coiltrack.firmware.rotation import quat_tuple as _quat
from coiltrack.firmware.track.magnetic import SOLVE_FAILED as _SOLVE_FAILED
from coiltrack.firmware.track.status import input_status

__all__ = ["BurstAcquisition"]


class _Burst:
    """One sensor's burst: amplitudes, their frames, the solution's start."""

    def __init__(self, cfg, n_coils: int):
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
        self.P6 = np.zeros((6, 6))
        self.hemisphere = np.array(cfg.source.hemisphere, dtype=float)
        self.position = np.zeros(3)
        self.have_pose = False


class BurstAcquisition:
    """The burst of every coil, its solution, and the filter it starts.

    ``sensors``: the tracker's ``SensorTrack`` records; ``book``: the pulses; ``model``:
    the single-coil model the refinement updates through; ``host``: the tracker
    (``tracking_started(sensor, status, now_us)``, ``boot_us``)."""

    def __init__(self, cfg, coils, sensors, book, model, supervisor, tx, host, distortion=None,
                 core=_DEFAULT_CORE):
        self.cfg = cfg
        self.n = len(coils)
        self._sens = tuple(sensors)
        self.book = book
        self.model = model
        self.supervisor = supervisor
        self.tx = tx
        self.host = host
        self.solver = PoseSolver(coils, cfg.source.field_model, core=core)
        if distortion is not None:                  # the room's map (model.distortion)
            self.solver.signal.set_distortion(distortion)
        self.nominal = np.array([c.current for c in cfg.source.coils])
        self.bursts = tuple(_Burst(cfg, self.n) for _ in self._sens)
        self._cur = np.zeros(self.n)
        self.acq_t = np.zeros(self.n, dtype=np.int64)        # mid times of the burst's pulses
        self.t_ref = 0
        self.active = False
        self.next_acq_us = cfg.timing.first_cycle_us - cfg.timing.lead_us
        self.acquisitions = 0

    def request(self, now_us: int) -> None:
        """A sensor lost its track: acquire as soon as the pulses in flight allow."""
        self.next_acq_us = min(self.next_acq_us, now_us)

    def _imu_ready(self, now_us: int) -> bool:
        """Acquire when every sensor's IMU is streaming (the burst is brought to one
        instant with the gyroscope, and the filter starts from it); a sensor that
        has sent no IMU sample for ``no_imu_us`` gets magnetic-only acquisitions."""
        for s in self._sens:
            live = s.last_imu_us is not None and now_us - s.last_imu_us <= self.cfg.imu.imu_timeout_us
            if not live and now_us - (self.host.boot_us or 0) < self.cfg.adaptive.no_imu_us:
                return False
        return True

    def try_start(self, now_us: int) -> None:
        """Start the burst when it is due and the IMUs stream (no pulse in flight)."""
        if now_us >= self.next_acq_us and self._imu_ready(now_us):
            self._start(now_us)

    def _start(self, now_us: int) -> None:
        cfg = self.cfg
        book = self.book
        start0 = max(now_us + cfg.timing.lead_us, book.next_free_us)
        mid = (cfg.pulse.settle_us + cfg.timing.pulse_us - cfg.pulse.guard_us) // 2
        for b in self.bursts:
            b.Sflags.fill(0)
            b.acq_have.fill(False)
        for j in range(self.n):
            book.command(j, float(self.nominal[j]), start0 + j * cfg.timing.spacing_us, cfg.timing.pulse_us, True)
            self.acq_t[j] = start0 + j * cfg.timing.spacing_us + mid
        t_ref = (start0 + (self.n - 1) * cfg.timing.spacing_us + start0 + cfg.timing.pulse_us) // 2
        self.t_ref = t_ref
        for s in self._sens:
            s.ekf.schedule_clone(0, t_ref)
        last_end = start0 + (self.n - 1) * cfg.timing.spacing_us + cfg.timing.pulse_us
        self.supervisor.flips.plan(now_us, last_end + book.gap_us, last_end + book.gap_us + cfg.timing.cycle_us // 4,
                                   self.tx.send, self.tx.mag_flip)
        book.note_flip(now_us)
        self.active = True
        self.acquisitions += 1

    def note_orientation(self, s, t: int) -> None:
        """Gyro-integrated orientation at the mid time of each burst pulse
        (``R(t_j) = R(t) exp(-[w (t - t_j)]x)``), to bring the burst's
        amplitudes to one instant before solving."""
        ekf = s.ekf
        b = self.bursts[s.index]
        w = ekf.w
        for j in range(self.n):
            if not b.acq_have[j] and t >= self.acq_t[j]:
                h = -(t - int(self.acq_t[j])) * 1e-6
                exp_rotvec(float(w[0]) * h, float(w[1]) * h, float(w[2]) * h, b.dR)
                np.matmul(ekf.R, b.dR, out=b.acq_R[j])
                b.acq_have[j] = True

    def record(self, s, j: int, amp, amp_var, flags: int, current: float) -> None:
        """Coil ``j``'s amplitude in sensor ``s``'s burst (``flags``: the window's)."""
        b = self.bursts[s.index]
        b.S[:, j] = amp
        b.Svar[:, j] = amp_var
        b.Sflags[j] = flags
        self._cur[j] = current

    def finish(self, now_us: int) -> None:
        """Every window of the burst is closed: solve it for each sensor and start its filter."""
        self.book.end_burst()
        self.active = False
        self.next_acq_us = now_us + self.cfg.timing.cycle_us // 2
        for s in self._sens:
            self._finish_one(s, now_us)

    def _finish_one(self, s, now_us: int) -> None:
        ekf = s.ekf
        b = self.bursts[s.index]
        flags = 0
        for j in range(self.n):
            flags |= int(b.Sflags[j])
        status = input_status(flags, 0)
        imu = ekf.t_us is not None and bool(ekf.clone_taken[0]) and ekf.t_us >= self.t_ref
        have = True
        for j in range(self.n):
            have = have and bool(b.acq_have[j])
        np.copyto(b.Sraw, b.S)
        if imu and have:
            # the sensor turned during the burst: bring every amplitude to the
            # sensor frame at t_ref, S_ref[:, j] = R_ref^T R_j S[:, j]
            for j in range(self.n):
                np.matmul(ekf.clone_R[0].T, b.acq_R[j], out=b.R3)
                np.copyto(b.col, b.S[:, j])
                np.matmul(b.R3, b.col, out=b.S[:, j])
        if not self._solve(b, flags):
            ekf.release_clone(0)
            return
        sv = self.solver
        p, R, cov = sv.position, sv.rotation, sv.covariance
        b.position[:] = p
        b.have_pose = True
        status |= POSE_VALID
        self.tx.pose_cov6(s.node, self.t_ref, p, _quat(R), cov, status)
        if not (imu and have):
            ekf.release_clone(0)
            return    # no IMU over the burst: stay magnetic-only, acquire again
        self._start_filter(s, b, p, R, cov)
        self._refine(s, b)
        self.host.tracking_started(s, status, now_us)

    def _solve(self, b: _Burst, flags: int) -> bool:
        """The burst's pose (``PoseSolver``, warm from the last solution's hemisphere)."""
        cfg = self.cfg
        if flags & PULSE_TOO_FEW:
            return False
        floor = (0.1 * cfg.pulse.mag_sigma_t) ** 2
        for i in range(3):
            for j in range(self.n):
                v = float(b.Svar[i, j])
                b.Ssig[i, j] = math.sqrt(v if v > floor else floor)
        hemi = b.position if b.have_pose else b.hemisphere
        return not (self.solver.solve(b.S, self._cur, b.Ssig, hemi) & _SOLVE_FAILED)

    def _start_filter(self, s, b: _Burst, p, R, cov) -> None:
        """Start the filter from the solution, its orientation carried from ``t_ref`` to the
        present by the gyroscope integration."""
        cfg = self.cfg
        ekf = s.ekf
        np.matmul(R, ekf.clone_R[0].T, out=b.R3)
        np.matmul(b.R3, ekf.R, out=b.Rnow)
        lag = (ekf.t_us - self.t_ref) * 1e-6
        half = (cfg.timing.pulse_us + (self.n - 1) * cfg.timing.spacing_us) * 0.5e-6
        # the solution is blurred by the motion during the burst (position) and carried
        # by an uncalibrated gyroscope (orientation): widen its covariance accordingly
        P6 = b.P6
        np.copyto(P6, cov)
        extra = (cfg.adaptive.init_sigma_vel * (lag + half)) ** 2
        gb = cfg.imu.imu_gyro_bias_sigma * (lag + half)
        for i in range(3):
            P6[i, i] += extra
            P6[3 + i, 3 + i] += gb * gb + cfg.adaptive.init_sigma_ori_deg ** 2 * (math.pi / 180.0) ** 2
        ekf.release_clone(0)
        for j in range(self.n):
            np.matmul(ekf.R.T, b.acq_R[j], out=b.acq_G[j])     # before R is replaced
        ekf.initialize(p, b.Rnow, P6, ekf.t_us, cfg.adaptive.init_sigma_vel, cfg.imu.imu_acc_bias_sigma,
                       cfg.imu.imu_gyro_bias_sigma)

    def _refine(self, s, b: _Burst) -> None:
        """Use the burst's pulses once more, as single-coil updates at their own instants.

        The burst solution assumes the sensor still for the whole burst; near the source a
        centimetre of motion between the pulses changes the fields by tens of percent and
        the solver fits a compromise pose with a tiny covariance. Applied one by one through
        clones predicted backwards from the new state (``SchepersEKF.back_clone``: the
        gyroscope's rotation increments, the velocity and the offsets in the transition),
        the amplitudes correct the position, orientation and velocity together."""
        cfg = self.cfg
        ekf = s.ekf
        m = s.meas
        for j in range(self.n):
            if b.Sflags[j] & _UNUSABLE:
                continue
            dt = (ekf.t_us - int(self.acq_t[j])) * 1e-6
            ekf.back_clone(1, dt, b.acq_G[j])
            c = float(self._cur[j])
            rc = cfg.limits.current_tolerance_a / max(abs(c), 1e-6)
            rel = math.sqrt(cfg.adaptive.field_model_rel_sigma * cfg.adaptive.field_model_rel_sigma + rc * rc)
            col = b.col
            for i in range(3):
                col[i] = float(b.Svar[i, j])
            ekf.update_pulse(1, m.set(b.Sraw[:, j], col, j, c, rel, 1.0, False), self.model)
            ekf.release_clone(1)
