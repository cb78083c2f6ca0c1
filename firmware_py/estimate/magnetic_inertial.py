"""Magnetic-inertial fusion: the complementary error filter of thesis ch. 6.

Roetenberg thesis (``002_cd7f1fdb7fc67471.txt``) sec 6.2: inertial dead
reckoning (strapdown, eqs 6.1-6.4) runs at the IMU rate; when a magnetic
6-DOF solution arrives, the differences between the inertial and the
magnetic position and orientation are fed to a Kalman filter on the errors
(eqs 6.5-6.6), whose estimates correct the inertial state (Fig. 6.3).

State (``layout.FUSION_LAYOUT``, eq 6.9; ``FUSION_XI_LAYOUT`` adds ``XI``,
eq 6.19): errors of position, velocity, orientation, accelerometer and
gyroscope, magnetic position and magnetic orientation. Conventions:
``true = estimate + error``; orientation errors are rotation vectors in the
global frame, ``Theta_true = exp([ori]x) Theta`` (the thesis defines them
with the opposite sign); accelerometer and gyroscope errors live in the
sensor frame, where the sensors' offsets do.

Frames. ``G`` is the global frame (z up, x magnetic north, as the ch. 2
filter). The magnetic frame ``M`` is the source; ``Phi = R_GM`` is the
source orientation, from the source's own orientation filter (sec 6.2.3) or
fixed. The filter tracks the sensor relative to the source in ``G``:
``p = Phi q_M`` (eq 6.7), and integrates the net acceleration
``a_net = a_sensor - a_source`` (eq 6.8), which with specific forces
``f`` reads ``a_net = Theta f_sensor - Phi f_source`` (gravity cancels; for a
fixed level source without IMU ``Phi f_source = (0, 0, g)``).

Nominal propagation per IMU sample (step ``T``; biases removed; the
specific force taken at mid-step, ``f + T/2 w x f``)::

    p <- p + T v + T^2/2 a_net          v <- v + T a_net
    Theta <- Theta exp([w T]x)          b_a, b_g <- exp(-beta T) b   (eqs 6.13-6.14)

Error propagation (eqs 6.10-6.17, ``A`` of eq 6.17 in this convention)::

    p_e' = p_e + T v_e                                   (6.10)
    v_e' = v_e + T (-[f_G x] ori_e - Theta acc_e)         (6.11)
    ori_e' = ori_e - T Theta gyr_e                        (6.12)
    acc_e' = exp(-beta_a T) acc_e,  gyr_e' = exp(-beta_w T) gyr_e   (6.13-6.14)
    qm_e' = 0,  psi_e' = 0  (and xi_e' = 0)               (6.15-6.16)

``Q`` is diagonal (sec 6.2.4). The white magnetic error states get, at each
magnetic update, the covariance the solver computed for that very solution
(``solver.PoseSolver.covariance`` turned into the global frame), so the
filter weights every update by the geometry it was measured in (the thesis
notes in sec 6.5 that this "can also improve the accuracy").

Measurement models (sec 6.2.5), selectable:

1. eq 6.18: ``z = [Phi q - p ; log(Psi Theta^T)]`` with
   ``C = [I 0 0 0 0 I 0 ; 0 0 I 0 0 0 I]``;
2. eq 6.20: the orientation of the ch. 2 filter ``Xi`` instead of the
   magnetic one;
3. eq 6.21 (the thesis' choice): position, and both orientations; stacking
   ``log(Psi Theta^T)`` and ``log(Xi Theta^T)`` with their own noise gives
   exactly the variance-weighted sum of the two orientations the thesis
   describes. Between magnetic updates only the gyroscopes track the
   orientation.

Delayed measurement. A magnetic solution refers to an instant ``t_ref`` in
the middle of the X-Y-Z burst; it is available only after the last pulse's
trailing baseline, about 170 ms later. The filter keeps a snapshot of its
state at ``t_ref`` (taken when the IMU stream crosses it, splitting that IMU
step), the IMU samples since, and replays them after the update: the update
is applied exactly at ``t_ref`` (rewind and replay; thesis sec 6.2.3 notes
the magnetic and inertial estimates are compared at the end of an inertial
tracking period).

Motion within the burst (thesis sec 6.5). ``pose_at`` interpolates the
inertial pose history at any recent instant, so the firmware can bring the
three pulses, measured 100 ms apart, to ``t_ref`` before solving
(``Firmware._compensate``).

All buffers are created in ``__init__``; a step allocates no numpy array.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.estimate.ekf import EKF_OK, CovariancePredict, KalmanUpdate
from coiltrack.firmware.estimate.layout import ACC, GYR, ORI, POS, PSI, QM, VEL, XI, fusion_layout
from coiltrack.firmware.linalg import exp_rotvec, rotvec_from_matrix
from coiltrack.firmware.rotation import quat_from_elements

# fusion health flags (bit field, beside the ekf flags)
FUS_NOT_INITIALISED = 64
FUS_NO_SNAPSHOT = 128       # the IMU stream has not reached t_ref (or it left the ring)
FUS_REINITIALISED = 256     # too many consecutive rejections: restarted from the magnetic pose
FUS_INITIALISED = 512       # this update initialised the filter

#: rows of the IMU ring: specific force (3), rate (3), source specific force in G (3), Phi (9)
_IMU_W = 18
#: rows of the pose history: p_M (3), R_MS (9)
_HIST_W = 12
#: rows of the output ring: p_M (3), q (4), var (6), status (1)
_OUT_W = 14


class FusionParams:
    """Parameters of the ch. 6 filter (SI units; per-sample noise figures)."""

    def __init__(self, measurement_model=3, acc_noise=0.015, gyro_noise=0.006,
                 source_acc_noise=0.0, acc_bias_sigma=0.03, gyro_bias_sigma=0.01,
                 acc_bias_rw=2e-4, gyro_bias_rw=1.7e-4,
                 acc_bias_tau_s=3600.0, gyro_bias_tau_s=3600.0, velocity0_sigma=0.3,
                 gate_probability=0.9999, reinit_after=3, xi_var_scale=1.0, xi_sigma_floor=0.005,
                 xi_heading_sigma_floor=0.035, mag_var_scale=1.0,
                 qm_sigma=0.01, psi_sigma=0.05, meas_sigma=1e-5, max_gap_us=100_000,
                 stale_us=2_000_000):
        if measurement_model not in (1, 2, 3):
            raise ValueError("measurement_model must be 1, 2 or 3")
        self.measurement_model = int(measurement_model)
        self.acc_noise = float(acc_noise)
        self.gyro_noise = float(gyro_noise)
        self.source_acc_noise = float(source_acc_noise)
        self.acc_bias_sigma = float(acc_bias_sigma)      # initial offset uncertainty
        self.gyro_bias_sigma = float(gyro_bias_sigma)
        self.acc_bias_rw = float(acc_bias_rw)            # m/s^2/sqrt(s), driving noise of eq 6.13
        self.gyro_bias_rw = float(gyro_bias_rw)          # rad/s/sqrt(s), driving noise of eq 6.14
        self.acc_bias_tau_s = float(acc_bias_tau_s)
        self.gyro_bias_tau_s = float(gyro_bias_tau_s)
        self.velocity0_sigma = float(velocity0_sigma)
        self.gate_probability = float(gate_probability)
        self.reinit_after = int(reinit_after)
        self.xi_var_scale = float(xi_var_scale)
        # Xi's error is not white: the accelerometer offset tilts it (offset / g)
        # and, through the dip, turns its heading (the accelerometer fixes the
        # rotation about the field, mostly vertical: heading error ~ tilt / cos(dip));
        # and the source's Phi has the same errors. Floors (rad) on the tilt axes
        # and on the heading axis of G cover them.
        self.xi_sigma_floor = float(xi_sigma_floor)
        self.xi_heading_sigma_floor = float(xi_heading_sigma_floor)
        self.mag_var_scale = float(mag_var_scale)
        self.qm_sigma = float(qm_sigma)
        self.psi_sigma = float(psi_sigma)
        self.meas_sigma = float(meas_sigma)
        self.max_gap_us = int(max_gap_us)
        self.stale_us = int(stale_us)


class FusionFilter:
    """The thesis ch. 6 complementary error filter (see module docstring).

    Parameters
    ----------
    params : FusionParams
    xi_filter : orientation.OrientationFilter, optional
        The sensor's ch. 2 filter (its ``R``, covariance and gyroscope
        offset), needed by measurement models 2 and 3 and used to initialise.
    imu_capacity, history_capacity, output_capacity : int
        Ring sizes (IMU samples kept for replay, pose history for motion
        compensation, poses waiting to be sent).
    """

    def __init__(self, params: FusionParams, xi_filter=None, imu_capacity: int = 128,
                 history_capacity: int = 128, output_capacity: int = 16):
        self.prm = params
        self.layout = fusion_layout(params.measurement_model)
        n = self.layout.n
        self.n = n
        self.model = params.measurement_model
        if self.model != 1 and xi_filter is None:
            raise ValueError("measurement models 2 and 3 need the orientation filter Xi")
        self.xi = xi_filter
        # nominal state
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.Th = np.eye(3)
        self.ba = np.zeros(3)
        self.bg = np.zeros(3)
        self.t_us = 0
        self.P = np.zeros((n, n))
        self._pv = memoryview(self.p)
        self._vv = memoryview(self.v)
        self._Thv = memoryview(self.Th)
        self._bav = memoryview(self.ba)
        self._bgv = memoryview(self.bg)
        self._Pv = memoryview(self.P)
        self.pred = CovariancePredict(n)
        self._Av = memoryview(self.pred.A)
        self._Qv = memoryview(self.pred.Q)
        for s in (QM, PSI) + ((XI,) if n > 21 else ()):
            for i in range(s.start, s.stop):
                self._Av[i, i] = 0.0
        m = 9 if self.model == 3 else 6
        self.m = m
        self.upd = KalmanUpdate(n, m, params.gate_probability)
        self._Hv = memoryview(self.upd.H)
        self._Rmv = memoryview(self.upd.R)
        self._yv = self.upd._yv
        # the measurement matrix C is constant (eqs 6.18, 6.20, 6.21)
        for i in range(3):
            self._Hv[i, POS.start + i] = 1.0
            self._Hv[i, QM.start + i] = 1.0
            self._Hv[3 + i, ORI.start + i] = 1.0
            self._Hv[3 + i, (PSI if self.model != 2 else XI).start + i] = 1.0
            if self.model == 3:
                self._Hv[6 + i, ORI.start + i] = 1.0
                self._Hv[6 + i, XI.start + i] = 1.0
        r = params.meas_sigma ** 2
        for i in range(m):
            self._Rmv[i, i] = r
        self._dt_last = -1.0
        self._ka = self._kg = 1.0
        #: the source is fixed (Phi = I): history and output skip the frame change
        self.source_fixed = False
        # scratch
        self._E = np.zeros((3, 3))
        self._Ev = memoryview(self._E)
        self._T = np.zeros((3, 3))
        # snapshot at t_ref
        self._sp = np.zeros(3)
        self._sv = np.zeros(3)
        self._sTh = np.zeros((3, 3))
        self._sba = np.zeros(3)
        self._sbg = np.zeros(3)
        self._sP = np.zeros((n, n))
        self._sPhi = np.eye(3)
        self._sXi = np.eye(3)
        self._sXiP = np.zeros((3, 3))
        self._sXiB = np.zeros(3)
        self._sPhiv = memoryview(self._sPhi)
        self._sXiv = memoryview(self._sXi)
        self._sXiPv = memoryview(self._sXiP)
        self.snap_t = 0
        self.snap_pending = False
        self.snap_valid = False
        self.snap_initialized = False
        self.snap_xi = False
        # IMU ring
        self.imu_t = np.zeros(imu_capacity, dtype=np.int64)
        self.imu_d = np.zeros((imu_capacity, _IMU_W))
        self._itv = memoryview(self.imu_t)
        self._idv = memoryview(self.imu_d)
        self._icap = imu_capacity
        self._ihead = 0
        self._icount = 0
        # pose history (M frame)
        self.hist_t = np.zeros(history_capacity, dtype=np.int64)
        self.hist_d = np.zeros((history_capacity, _HIST_W))
        self._htv = memoryview(self.hist_t)
        self._hdv = memoryview(self.hist_d)
        self._hcap = history_capacity
        self._hhead = 0
        self._hcount = 0
        # output ring
        self.out_t = np.zeros(output_capacity, dtype=np.int64)
        self.out_d = np.zeros((output_capacity, _OUT_W))
        self._otv = memoryview(self.out_t)
        self._odv = memoryview(self.out_d)
        self._ocap = output_capacity
        self._ohead = 0
        self._ocount = 0
        self.out_dropped = 0
        # bookkeeping
        self.initialized = False
        self.replaying = False
        self.rejects_in_row = 0
        self.accepted_in_row = 0
        self.last_update_t = 0
        self.last_flags = 0
        self.last_nis = 0.0
        self.updates = 0
        self.rejected = 0
        self.reinits = 0
        self.steps = 0
        self.recorder = None       # optional offline hook (smoother); None on the board

    # ------------------------------------------------------------ inputs
    def schedule_snapshot(self, t_ref_us: int) -> None:
        """Keep the state at ``t_ref_us`` (the instant the next magnetic
        solution will refer to)."""
        self.snap_t = int(t_ref_us)
        self.snap_pending = True
        self.snap_valid = False

    def push_imu(self, t_us: int, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi) -> bool:
        """One sensor IMU sample (specific force m/s^2, rate rad/s, sensor
        frame) with the source's specific force in ``G`` (``r*``) and the
        source orientation ``Phi`` (3x3, memoryview or array). Returns True
        when a fused pose was produced (put in the output ring)."""
        # ring entry (kept for replay)
        k = self._ihead
        self._itv[k] = t_us
        d = self._idv
        d[k, 0], d[k, 1], d[k, 2] = fx, fy, fz
        d[k, 3], d[k, 4], d[k, 5] = wx, wy, wz
        d[k, 6], d[k, 7], d[k, 8] = rx, ry, rz
        if not self.source_fixed:          # a fixed source keeps Phi = I (columns unused)
            for i in range(3):
                for j in range(3):
                    d[k, 9 + 3 * i + j] = Phi[i, j]
        self._ihead = k + 1 if k + 1 < self._icap else 0
        if self._icount < self._icap:
            self._icount += 1
        if not self.initialized:
            if self.snap_pending and t_us >= self.snap_t:
                self._snapshot_aux(k)
            return False
        if t_us <= self.t_us:
            return False
        if t_us - self.t_us > self.prm.max_gap_us:
            # the stream broke off: the inertial state is not worth keeping
            self.initialized = False
            self.snap_valid = False
            return False
        self._advance(k)
        self._output(t_us)
        return True

    def _advance(self, k: int) -> None:
        """Propagate to ring entry ``k``'s time, splitting the step at a pending snapshot."""
        t = self._itv[k]
        if self.snap_pending and self.t_us < self.snap_t <= t:
            ts = self.snap_t
            if ts > self.t_us:
                self._step(k, self.t_us, ts)
                self.t_us = ts
                self._history(k)
            self._snapshot(k)
            if t > ts:
                self._step(k, ts, t)
        else:
            self._step(k, self.t_us, t)
        self.t_us = t
        self._history(k)

    # ------------------------------------------------------------ model
    def _step(self, k: int, t0: int, t1: int) -> None:
        """Strapdown and covariance step over ``[t0, t1]`` with the IMU
        samples of ring entries ``k - 1`` and ``k`` (trapezoidal in the rate
        and in the global-frame specific force: the samples are instantaneous
        values; inputs at ``t0`` / ``t1`` interpolated linearly between the
        two entries)."""
        dt = (t1 - t0) * 1e-6
        d = self._idv
        tv = self._itv
        tk = tv[k]
        kp = k - 1 if k > 0 else self._icap - 1
        tp = tv[kp]
        # interpolation weights of entry k at t0 and t1 (1: entry k alone)
        if self._icount > 1 and tp < tk:
            span = 1.0 / (tk - tp)
            a0 = (t0 - tp) * span
            a1 = (t1 - tp) * span
            if a0 < 0.0:
                a0 = 0.0
        else:
            kp = k
            a0 = a1 = 1.0
        b0 = 1.0 - a0
        b1 = 1.0 - a1
        ba = self._bav
        bg = self._bgv
        xa, xb, xc = ba[0], ba[1], ba[2]
        p0, p1, p2, p3, p4, p5, p6, p7, p8 = (d[kp, 0], d[kp, 1], d[kp, 2], d[kp, 3], d[kp, 4], d[kp, 5],
                                              d[kp, 6], d[kp, 7], d[kp, 8])
        q0, q1, q2, q3, q4, q5, q6, q7, q8 = (d[k, 0], d[k, 1], d[k, 2], d[k, 3], d[k, 4], d[k, 5],
                                              d[k, 6], d[k, 7], d[k, 8])
        f0x = b0 * p0 + a0 * q0 - xa
        f0y = b0 * p1 + a0 * q1 - xb
        f0z = b0 * p2 + a0 * q2 - xc
        f1x = b1 * p0 + a1 * q0 - xa
        f1y = b1 * p1 + a1 * q1 - xb
        f1z = b1 * p2 + a1 * q2 - xc
        am = 0.5 * (a0 + a1)
        bm = 1.0 - am
        wx = bm * p3 + am * q3 - bg[0]
        wy = bm * p4 + am * q4 - bg[1]
        wz = bm * p5 + am * q5 - bg[2]
        r0x, r0y, r0z = b0 * p6 + a0 * q6, b0 * p7 + a0 * q7, b0 * p8 + a0 * q8
        r1x, r1y, r1z = b1 * p6 + a1 * q6, b1 * p7 + a1 * q7, b1 * p8 + a1 * q8
        Th = self._Thv
        # specific force at t0 in G with the attitude at t0
        g0x = Th[0, 0] * f0x + Th[0, 1] * f0y + Th[0, 2] * f0z
        g0y = Th[1, 0] * f0x + Th[1, 1] * f0y + Th[1, 2] * f0z
        g0z = Th[2, 0] * f0x + Th[2, 1] * f0y + Th[2, 2] * f0z
        exp_rotvec(wx * dt, wy * dt, wz * dt, self._Ev)
        np.matmul(self.Th, self._E, out=self._T)
        np.copyto(self.Th, self._T)
        t00, t01, t02 = Th[0, 0], Th[0, 1], Th[0, 2]
        t10, t11, t12 = Th[1, 0], Th[1, 1], Th[1, 2]
        t20, t21, t22 = Th[2, 0], Th[2, 1], Th[2, 2]
        g1x = t00 * f1x + t01 * f1y + t02 * f1z
        g1y = t10 * f1x + t11 * f1y + t12 * f1z
        g1z = t20 * f1x + t21 * f1y + t22 * f1z
        a0x, a0y, a0z = g0x - r0x, g0y - r0y, g0z - r0z
        a1x, a1y, a1z = g1x - r1x, g1y - r1y, g1z - r1z
        p = self._pv
        v = self._vv
        c0 = dt * dt / 3.0
        c1 = dt * dt / 6.0
        p[0] += v[0] * dt + c0 * a0x + c1 * a1x
        p[1] += v[1] * dt + c0 * a0y + c1 * a1y
        p[2] += v[2] * dt + c0 * a0z + c1 * a1z
        h = 0.5 * dt
        v[0] += h * (a0x + a1x)
        v[1] += h * (a0y + a1y)
        v[2] += h * (a0z + a1z)
        gx, gy, gz = 0.5 * (g0x + g1x), 0.5 * (g0y + g1y), 0.5 * (g0z + g1z)
        prm = self.prm
        if dt != self._dt_last:
            self._set_dt(dt)
        ka = self._ka
        kg = self._kg
        ba[0] *= ka
        ba[1] *= ka
        ba[2] *= ka
        bg[0] *= kg
        bg[1] *= kg
        bg[2] *= kg
        # transition matrix blocks (eq 6.17)
        A = self._Av
        p0, v0, o0, a0, g0 = POS.start, VEL.start, ORI.start, ACC.start, GYR.start
        # VEL-ORI: -T [f_G x]
        A[v0, o0 + 1] = dt * gz
        A[v0, o0 + 2] = -dt * gy
        A[v0 + 1, o0] = -dt * gz
        A[v0 + 1, o0 + 2] = dt * gx
        A[v0 + 2, o0] = dt * gy
        A[v0 + 2, o0 + 1] = -dt * gx
        A[v0, a0], A[v0, a0 + 1], A[v0, a0 + 2] = -dt * t00, -dt * t01, -dt * t02
        A[v0 + 1, a0], A[v0 + 1, a0 + 1], A[v0 + 1, a0 + 2] = -dt * t10, -dt * t11, -dt * t12
        A[v0 + 2, a0], A[v0 + 2, a0 + 1], A[v0 + 2, a0 + 2] = -dt * t20, -dt * t21, -dt * t22
        A[o0, g0], A[o0, g0 + 1], A[o0, g0 + 2] = -dt * t00, -dt * t01, -dt * t02
        A[o0 + 1, g0], A[o0 + 1, g0 + 1], A[o0 + 1, g0 + 2] = -dt * t10, -dt * t11, -dt * t12
        A[o0 + 2, g0], A[o0 + 2, g0 + 1], A[o0 + 2, g0 + 2] = -dt * t20, -dt * t21, -dt * t22
        self.pred.predict(self.P)
        self.steps += 1
        if self.recorder is not None:
            self.recorder.on_step(self, k, t1)

    def _set_dt(self, dt: float) -> None:
        """The parts of ``A`` and ``Q`` that depend on the step alone
        (eqs 6.10, 6.13-6.14; the white magnetic states), rewritten only when
        the step changes."""
        prm = self.prm
        self._dt_last = dt
        ka = math.exp(-dt / prm.acc_bias_tau_s) if prm.acc_bias_tau_s > 0.0 else 1.0
        kg = math.exp(-dt / prm.gyro_bias_tau_s) if prm.gyro_bias_tau_s > 0.0 else 1.0
        self._ka = ka
        self._kg = kg
        A = self._Av
        Q = self._Qv
        p0, v0, o0, a0, g0 = POS.start, VEL.start, ORI.start, ACC.start, GYR.start
        qv = (prm.acc_noise ** 2 + prm.source_acc_noise ** 2) * dt * dt
        qo = (prm.gyro_noise * dt) ** 2
        qa = prm.acc_bias_rw * prm.acc_bias_rw * dt
        qg = prm.gyro_bias_rw * prm.gyro_bias_rw * dt
        qq = prm.qm_sigma ** 2
        qs = prm.psi_sigma ** 2
        for i in range(3):
            A[p0 + i, v0 + i] = dt
            A[a0 + i, a0 + i] = ka
            A[g0 + i, g0 + i] = kg
            Q[v0 + i, v0 + i] = qv
            Q[o0 + i, o0 + i] = qo
            Q[a0 + i, a0 + i] = qa
            Q[g0 + i, g0 + i] = qg
            Q[QM.start + i, QM.start + i] = qq
            Q[PSI.start + i, PSI.start + i] = qs
            if self.n > 21:
                Q[XI.start + i, XI.start + i] = qs

    def _history(self, k: int) -> None:
        """Append the current pose in the source frame: ``p_M = Phi^T p``,
        ``R_MS = Phi^T Theta`` (Phi of IMU ring entry ``k``)."""
        d = self._idv
        h = self._hhead
        self._htv[h] = self.t_us
        hd = self._hdv
        p = self._pv
        Th = self._Thv
        if self.source_fixed:
            hd[h, 0], hd[h, 1], hd[h, 2] = p[0], p[1], p[2]
            hd[h, 3], hd[h, 4], hd[h, 5] = Th[0, 0], Th[0, 1], Th[0, 2]
            hd[h, 6], hd[h, 7], hd[h, 8] = Th[1, 0], Th[1, 1], Th[1, 2]
            hd[h, 9], hd[h, 10], hd[h, 11] = Th[2, 0], Th[2, 1], Th[2, 2]
        else:
            for i in range(3):
                f0, f1, f2 = d[k, 9 + i], d[k, 12 + i], d[k, 15 + i]     # column i of Phi
                hd[h, i] = f0 * p[0] + f1 * p[1] + f2 * p[2]
                for j in range(3):
                    hd[h, 3 + 3 * i + j] = f0 * Th[0, j] + f1 * Th[1, j] + f2 * Th[2, j]
        self._hhead = h + 1 if h + 1 < self._hcap else 0
        if self._hcount < self._hcap:
            self._hcount += 1

    def _output(self, t_us: int) -> None:
        """Queue the fused pose (source frame) with its variances: position
        ``diag(Phi^T P_pp Phi)``, orientation in the sensor frame
        ``diag(R^T P_oo R)`` with ``R = Theta`` (as the POSE message defines)."""
        if self._ocount == self._ocap:
            self.out_dropped += 1
            return
        slot = self._ohead + self._ocount
        if slot >= self._ocap:
            slot -= self._ocap
        self._ocount += 1
        self._otv[slot] = t_us
        od = self._odv
        h = self._hhead - 1 if self._hhead > 0 else self._hcap - 1
        hd = self._hdv
        od[slot, 0], od[slot, 1], od[slot, 2] = hd[h, 0], hd[h, 1], hd[h, 2]
        _quat_into(hd, h, od, slot)
        k = self._ihead - 1 if self._ihead > 0 else self._icap - 1
        d = self._idv
        P = self._Pv
        Th = self._Thv
        p0 = POS.start
        o0 = ORI.start
        # orientation: diag(Theta^T P_oo Theta) = sum_i Theta[i, c] (P_oo Theta)[i, c]
        o00, o01, o02 = P[o0, o0], P[o0, o0 + 1], P[o0, o0 + 2]
        o11, o12, o22 = P[o0 + 1, o0 + 1], P[o0 + 1, o0 + 2], P[o0 + 2, o0 + 2]
        for c in range(3):
            x, y, z = Th[0, c], Th[1, c], Th[2, c]
            od[slot, 10 + c] = (x * (o00 * x + o01 * y + o02 * z) + y * (o01 * x + o11 * y + o12 * z)
                                + z * (o02 * x + o12 * y + o22 * z))
        if self.source_fixed:
            od[slot, 7], od[slot, 8], od[slot, 9] = P[p0, p0], P[p0 + 1, p0 + 1], P[p0 + 2, p0 + 2]
        else:
            q00, q01, q02 = P[p0, p0], P[p0, p0 + 1], P[p0, p0 + 2]
            q11, q12, q22 = P[p0 + 1, p0 + 1], P[p0 + 1, p0 + 2], P[p0 + 2, p0 + 2]
            for c in range(3):
                x, y, z = d[k, 9 + c], d[k, 12 + c], d[k, 15 + c]      # column c of Phi
                od[slot, 7 + c] = (x * (q00 * x + q01 * y + q02 * z) + y * (q01 * x + q11 * y + q12 * z)
                                   + z * (q02 * x + q12 * y + q22 * z))
        status = 0
        if t_us - self.last_update_t > self.prm.stale_us:
            status |= 1
        if self.last_flags & ~FUS_INITIALISED:
            status |= 2
        od[slot, 13] = status

    def pop_output(self):
        """Index of the oldest queued pose in ``out_t`` / ``out_d`` (or -1);
        call :meth:`release_output` when sent."""
        if self._ocount == 0:
            return -1
        return self._ohead

    def release_output(self) -> None:
        if self._ocount:
            self._ohead = self._ohead + 1 if self._ohead + 1 < self._ocap else 0
            self._ocount -= 1

    # ------------------------------------------------------------ snapshot
    def _snapshot_aux(self, k: int) -> None:
        """Source orientation and Xi at t_ref (all that initialisation needs)."""
        d = self._idv
        S = self._sPhiv
        for i in range(3):
            for j in range(3):
                S[i, j] = (1.0 if i == j else 0.0) if self.source_fixed else d[k, 9 + 3 * i + j]
        if self.xi is not None and self.xi.initialized:
            np.copyto(self._sXi, self.xi.R)
            self.xi.theta_covariance_global(self._sXiPv)
            np.copyto(self._sXiB, self.xi.bias)
            self.snap_xi = True
        else:
            self.snap_xi = False
        self.snap_pending = False
        self.snap_valid = True
        self.snap_initialized = self.initialized

    def _snapshot(self, k: int) -> None:
        np.copyto(self._sp, self.p)
        np.copyto(self._sv, self.v)
        np.copyto(self._sTh, self.Th)
        np.copyto(self._sba, self.ba)
        np.copyto(self._sbg, self.bg)
        np.copyto(self._sP, self.P)
        self._snapshot_aux(k)

    def _restore(self) -> None:
        np.copyto(self.p, self._sp)
        np.copyto(self.v, self._sv)
        np.copyto(self.Th, self._sTh)
        np.copyto(self.ba, self._sba)
        np.copyto(self.bg, self._sbg)
        np.copyto(self.P, self._sP)
        self.t_us = self.snap_t
        if self.recorder is not None:
            self.recorder.on_rewind(self, self.snap_t)

    def _replay(self) -> None:
        """Re-run the IMU samples after ``t_us`` (the restored instant)."""
        t0 = self.t_us
        # drop history after t0
        while self._hcount and self._htv[self._hhead - 1 if self._hhead > 0 else self._hcap - 1] > t0:
            self._hhead = self._hhead - 1 if self._hhead > 0 else self._hcap - 1
            self._hcount -= 1
        if self.recorder is not None:
            self.recorder.on_rewind(self, t0)
        n = self._icount
        start = self._ihead - n
        if start < 0:
            start += self._icap
        self.replaying = True
        for i in range(n):
            k = start + i
            if k >= self._icap:
                k -= self._icap
            if self._itv[k] > self.t_us:
                self._advance(k)
        self.replaying = False

    def _ring_covers(self, t_us: int) -> bool:
        if self._icount == 0:
            return False
        start = self._ihead - self._icount
        if start < 0:
            start += self._icap
        return self._itv[start] <= t_us

    # ------------------------------------------------------------ update
    def magnetic_update(self, t_ref_us: int, q, R_ms, C, final: bool = True) -> int:
        """Fuse one magnetic solution referring to ``t_ref_us``: position
        ``q`` (3, source frame), orientation ``R_ms`` (3x3, sensor to source)
        and their covariance ``C`` (6x6, ``(p, dtheta)`` as ``solver``).
        Initialises the filter when needed. Returns health flags (ekf flags,
        ``FUS_*``); never raises. With ``final=False`` a rejected solution
        leaves the snapshot in place (and counts nothing), so the caller can
        offer another solution of the same burst."""
        if not (self.snap_valid and self.snap_t == t_ref_us and self._ring_covers(t_ref_us)):
            self.last_flags = FUS_NO_SNAPSHOT
            return FUS_NO_SNAPSHOT
        self.snap_valid = False
        if not (self.initialized and self.snap_initialized):
            if self.model != 1 and not self.snap_xi:
                self.last_flags = FUS_NOT_INITIALISED
                return FUS_NOT_INITIALISED
            self._initialize(t_ref_us, q, R_ms, C)
            self._replay()
            self.last_flags = FUS_INITIALISED
            self.last_update_t = t_ref_us
            return FUS_INITIALISED
        self._restore()
        self._measurement(q, R_ms, C)
        if self.recorder is not None:
            self.recorder.on_prior(self)
        flags = self.upd.update(self.P)
        self.last_nis = self.upd.nis
        if flags == EKF_OK:
            self._correct(self.upd._dxv)
            self.rejects_in_row = 0
            self.accepted_in_row += 1
            self.updates += 1
            self.last_update_t = t_ref_us
            if self.recorder is not None:
                self.recorder.on_update(self, self.upd.dx)
        elif not final:
            self.snap_valid = True
            self._replay()
            self.last_flags = flags
            return flags
        else:
            self.rejected += 1
            self.rejects_in_row += 1
            self.accepted_in_row = 0
            if self.rejects_in_row >= self.prm.reinit_after and (self.model == 1 or self.snap_xi):
                self._initialize(t_ref_us, q, R_ms, C)
                self.reinits += 1
                self.rejects_in_row = 0
                flags |= FUS_REINITIALISED
                self.last_update_t = t_ref_us
        self._replay()
        self.last_flags = flags
        return flags

    def _measurement(self, q, R_ms, C) -> None:
        """Innovation (eqs 6.18-6.21) and the white blocks of ``P``."""
        y = self._yv
        Phi = self._sPhiv
        p = self._pv
        Th = self._Thv
        P = self._Pv
        s = self.prm.mag_var_scale
        # position: Phi q - p
        for i in range(3):
            y[i] = Phi[i, 0] * q[0] + Phi[i, 1] * q[1] + Phi[i, 2] * q[2] - p[i]
        # Psi = Phi R_ms
        psi = self._E
        np.matmul(self._sPhi, R_ms, out=psi)
        Psi = self._Ev
        # white-state covariances: Phi C_pp Phi^T, Psi C_tt Psi^T, Phi C_pt Psi^T
        q0, s0 = QM.start, PSI.start
        for i in range(3):
            for j in range(3):
                cpp = cpt = ctt = 0.0
                for a in range(3):
                    fa = Phi[i, a]
                    pa = Psi[i, a]
                    for b in range(3):
                        cpp += fa * C[a, b] * Phi[j, b]
                        cpt += fa * C[a, 3 + b] * Psi[j, b]
                        ctt += pa * C[3 + a, 3 + b] * Psi[j, b]
                P[q0 + i, q0 + j] = cpp * s
                P[q0 + i, s0 + j] = cpt * s
                P[s0 + j, q0 + i] = cpt * s
                P[s0 + i, s0 + j] = ctt * s
        row = 3
        if self.model != 2:
            _log_diff(Psi, Th, y, row)
            row = 6
        if self.model != 1:
            _log_diff(self._sXiv, Th, y, row)
            x0 = XI.start
            xs = self.prm.xi_var_scale
            fl = self.prm.xi_sigma_floor ** 2
            fh = self.prm.xi_heading_sigma_floor ** 2
            XP = self._sXiPv
            for i in range(3):
                for j in range(3):
                    P[x0 + i, x0 + j] = XP[i, j] * xs
                P[x0 + i, x0 + i] += fh if i == 2 else fl
        if self.model == 2:
            # the magnetic orientation is not used: keep its white block inert
            for i in range(3):
                for j in range(3):
                    P[s0 + i, s0 + j] = (self.prm.psi_sigma ** 2) if i == j else 0.0
                    P[q0 + i, s0 + j] = 0.0
                    P[s0 + j, q0 + i] = 0.0

    def _correct(self, dx) -> None:
        p = self._pv
        v = self._vv
        ba = self._bav
        bg = self._bgv
        for i in range(3):
            p[i] += dx[POS.start + i]
            v[i] += dx[VEL.start + i]
            ba[i] += dx[ACC.start + i]
            bg[i] += dx[GYR.start + i]
        o = ORI.start
        exp_rotvec(dx[o], dx[o + 1], dx[o + 2], self._Ev)
        np.matmul(self._E, self.Th, out=self._T)
        np.copyto(self.Th, self._T)

    def _initialize(self, t_ref_us: int, q, R_ms, C) -> None:
        """State at ``t_ref``: position from the magnetic solution, velocity
        zero, orientation from Xi (models 2, 3) or the magnetic one (model 1),
        gyroscope offset from the ch. 2 filter."""
        prm = self.prm
        Phi = self._sPhiv
        p = self._pv
        for i in range(3):
            p[i] = Phi[i, 0] * q[0] + Phi[i, 1] * q[1] + Phi[i, 2] * q[2]
        self.v.fill(0.0)
        self.ba.fill(0.0)
        self.P.fill(0.0)
        P = self._Pv
        use_xi = self.model != 1 and self.snap_xi
        if use_xi:
            np.copyto(self.Th, self._sXi)
            np.copyto(self.bg, self._sXiB)
        else:
            np.matmul(self._sPhi, R_ms, out=self.Th)
            self.bg.fill(0.0)
        Th = self._Thv
        p0, o0 = POS.start, ORI.start
        for i in range(3):
            for j in range(3):
                cpp = 0.0
                coo = 0.0
                for a in range(3):
                    for b in range(3):
                        cpp += Phi[i, a] * C[a, b] * Phi[j, b]
                        coo += Th[i, a] * C[3 + a, 3 + b] * Th[j, b]
                P[p0 + i, p0 + j] = cpp
                if use_xi:
                    P[o0 + i, o0 + j] = self._sXiPv[i, j]
                else:
                    P[o0 + i, o0 + j] = coo
        for i in range(3):
            P[VEL.start + i, VEL.start + i] = prm.velocity0_sigma ** 2
            P[ACC.start + i, ACC.start + i] = prm.acc_bias_sigma ** 2
            P[GYR.start + i, GYR.start + i] = prm.gyro_bias_sigma ** 2
            P[QM.start + i, QM.start + i] = prm.qm_sigma ** 2
            P[PSI.start + i, PSI.start + i] = prm.psi_sigma ** 2
            if self.n > 21:
                P[XI.start + i, XI.start + i] = prm.psi_sigma ** 2
        self.t_us = t_ref_us
        self.initialized = True
        self.rejects_in_row = 0
        self.accepted_in_row = 0
        self._hcount = 0
        self._hhead = 0
        if self.recorder is not None:
            self.recorder.on_init(self)

    # ------------------------------------------------------------ queries
    def pose_at(self, t_us: int, out_p, out_R) -> bool:
        """Inertial pose in the source frame at ``t_us`` (linear
        interpolation of the history; ``out_R`` is not re-orthonormalised,
        which is second order in the step rotation). False when ``t_us`` is
        outside the history."""
        n = self._hcount
        if n < 2:
            return False
        cap = self._hcap
        start = self._hhead - n
        if start < 0:
            start += cap
        ht = self._htv
        if ht[start] > t_us:
            return False
        prev = start
        for i in range(1, n):
            k = start + i
            if k >= cap:
                k -= cap
            tk = ht[k]
            if tk >= t_us:
                t0 = ht[prev]
                a = (t_us - t0) / (tk - t0) if tk > t0 else 1.0
                hd = self._hdv
                b = 1.0 - a
                for c in range(3):
                    out_p[c] = b * hd[prev, c] + a * hd[k, c]
                for i2 in range(3):
                    for j in range(3):
                        out_R[i2, j] = b * hd[prev, 3 + 3 * i2 + j] + a * hd[k, 3 + 3 * i2 + j]
                return True
            prev = k
        return False

    def velocity_sigma(self) -> float:
        """rms velocity uncertainty per axis, m/s."""
        P = self._Pv
        v0 = VEL.start
        return math.sqrt(max(P[v0, v0] + P[v0 + 1, v0 + 1] + P[v0 + 2, v0 + 2], 0.0) / 3.0)

    def speed_squared(self) -> float:
        v = self._vv
        return v[0] * v[0] + v[1] * v[1] + v[2] * v[2]

    def nees(self, p_true_g, R_true_g, v_true_g=None) -> float:
        """Normalised estimation error squared of position, orientation (and
        velocity) against a truth in the global frame (tests; allocates)."""
        e = []
        idx = []
        e.extend(np.asarray(p_true_g) - self.p)
        idx.extend(range(POS.start, POS.stop))
        if v_true_g is not None:
            e.extend(np.asarray(v_true_g) - self.v)
            idx.extend(range(VEL.start, VEL.stop))
        M = np.asarray(R_true_g) @ self.Th.T
        e.extend(rotvec_from_matrix(*M.reshape(9)))
        idx.extend(range(ORI.start, ORI.stop))
        e = np.array(e)
        Ps = self.P[np.ix_(idx, idx)]
        return float(e @ np.linalg.solve(Ps, e))


def _log_diff(Z, Th, y, row) -> None:
    """``y[row:row+3] = log(Z Theta^T)`` (rotation vector, global frame)."""
    r00 = Z[0, 0] * Th[0, 0] + Z[0, 1] * Th[0, 1] + Z[0, 2] * Th[0, 2]
    r01 = Z[0, 0] * Th[1, 0] + Z[0, 1] * Th[1, 1] + Z[0, 2] * Th[1, 2]
    r02 = Z[0, 0] * Th[2, 0] + Z[0, 1] * Th[2, 1] + Z[0, 2] * Th[2, 2]
    r10 = Z[1, 0] * Th[0, 0] + Z[1, 1] * Th[0, 1] + Z[1, 2] * Th[0, 2]
    r11 = Z[1, 0] * Th[1, 0] + Z[1, 1] * Th[1, 1] + Z[1, 2] * Th[1, 2]
    r12 = Z[1, 0] * Th[2, 0] + Z[1, 1] * Th[2, 1] + Z[1, 2] * Th[2, 2]
    r20 = Z[2, 0] * Th[0, 0] + Z[2, 1] * Th[0, 1] + Z[2, 2] * Th[0, 2]
    r21 = Z[2, 0] * Th[1, 0] + Z[2, 1] * Th[1, 1] + Z[2, 2] * Th[1, 2]
    r22 = Z[2, 0] * Th[2, 0] + Z[2, 1] * Th[2, 1] + Z[2, 2] * Th[2, 2]
    x, yy, z = rotvec_from_matrix(r00, r01, r02, r10, r11, r12, r20, r21, r22)
    y[row] = x
    y[row + 1] = yy
    y[row + 2] = z


def _quat_into(hd, h, od, slot) -> None:
    """Unit quaternion (w, x, y, z), w >= 0, of the rotation in history row
    ``h`` (columns 3..11) into output columns 3..6."""
    w, x, y, z = quat_from_elements(hd[h, 3], hd[h, 4], hd[h, 5], hd[h, 6], hd[h, 7], hd[h, 8],
                                    hd[h, 9], hd[h, 10], hd[h, 11])
    od[slot, 3], od[slot, 4], od[slot, 5], od[slot, 6] = w, x, y, z
