"""Error-state EKF for single-coil magnetic updates with inertial propagation.

Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``) sec. 2.1: "a
fusion filter that predicts the change of position and orientation by
integration of acceleration and angular velocity measured by inertial
sensors"; a magnetic update takes the pulse of ONE source coil,
``y = R^T B_c(p) + v`` (eq 5, field eqs 6-8), linearised with eqs 9-11, and
corrects the error state with eq 4. The strapdown error model is the one of
the thesis' complementary filter (``seeds/002_cd7f1fdb7fc67471.txt`` ch. 6,
eqs 6.10-6.17), written for a sensor-frame orientation error, with the
accelerometer and gyroscope offsets as random walks.

State layout (``SCHEPERS_LAYOUT``, a ``coiltrack.firmware.estimate.layout.StateLayout``;
code indexes ``P`` by these names only)::

    POS  0  3  m      sensor position error, source frame
    VEL  3  3  m/s    velocity error, source frame
    ORI  6  3  rad    orientation error, sensor frame: R_true = R exp([ori]x)
    ACC  9  3  m/s^2  accelerometer offset error, sensor frame
    GYR 12  3  rad/s  gyroscope offset error, sensor frame
    C0P 15  3  m      clone 0: POS at the time pulse slot 0 is measured
    C0O 18  3  rad    clone 0: ORI at that time
    C1P, C1O 21, 24   clone 1

Error convention: ``x_true = x_est + dx`` for vectors and
``R_true = R_est exp([ori]x)`` (as ``coiltrack.firmware.pose.reference``), so the orientation
block of the measurement Jacobian is ``+[h]x`` (Schepers eq 11 carries the
opposite sign because eq 2 defines the error the other way round) and the
correction is ``dx = K (y - h)``.

Inertial propagation (one IMU sample interval ``dt``; specific force ``f``
and rate ``w`` in the sensor frame, offsets removed, mean of the interval's
two samples; the specific force is rotated with the mid-interval
orientation)::

    R_mid = R exp([w dt/2]x)
    a = R_mid f + g
    p += v dt + a dt^2 / 2,   v += a dt,   R = R_mid exp([w dt/2]x)

and the error transition (thesis eq 6.17 in this convention, plus the dt^2
terms of the position)::

    d(dp)/dt   = dv
    d(dv)/dt   = -R [f]x ori - R acc - R n_a
    d(ori)/dt  = -[w]x ori - gyr - n_g
    d(acc)/dt  = n_ba,   d(gyr)/dt = n_bg

Delayed measurements. A pulse is averaged over tens of milliseconds and its
window closes a baseline later, about 0.1 s after the instant it describes.
The filter clones the pose error at that instant (stochastic cloning: the
clone rows and columns of ``P`` are copied from ``POS``/``ORI`` and then
propagate with an identity transition, so their cross-covariance with the
live state carries the correlation), evaluates ``h`` and ``H`` at the cloned
nominal pose, and corrects the whole state when the amplitude is in.

Every update goes through the shared ``coiltrack.firmware.estimate.ekf.KalmanUpdate``
(innovation, innovation covariance, chi-square gate, gain, Joseph form,
health flags). All arrays are allocated in ``__init__``.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NONFINITE, EKF_NOT_PD, KalmanUpdate
from coiltrack.firmware.estimate.layout import (ACC, GYR, ORI, POS, POSE_ORI, POSE_POS, SCHEPERS_CORE as CORE,
                                               SCHEPERS_LAYOUT, VEL, schepers_layout)
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.strapdown import Strapdown, integrate_pv, to_nav, transition_sensor, transition_static
from coiltrack.firmware.linalg import exp_rotvec, inv3_sym, quad3_sym

__all__ = ["SCHEPERS_LAYOUT", "SchepersEKF", "EKF_NO_STATE"]

#: the filter is not initialised (no pose yet): nothing done
EKF_NO_STATE = 1024

_GRAVITY = (0.0, 0.0, -9.81)
#: margin on the linearisation error: the second-order term of an r^-3 field is 6 (d/r)^2
#: h; the iterated update removes most of it, 2 (sigma/r)^2 |h| is kept as a margin
_LIN_K = 2.0


N_CORE = CORE.stop


class SchepersEKF:
    """Inertial error-state EKF taking one coil's pulse at a time.

    Parameters
    ----------
    n_clones : int
        Pulses that may be in flight (measured but not yet closed) at once.
    gravity : (3,)
        Gravity in the source frame, m/s^2 (the accelerometer measures
        ``R^T (a - g)``).
    acc_noise, gyr_noise : float
        White-noise densities as the filter sees them, m/s^2/sqrt(Hz) and
        rad/s/sqrt(Hz) (``Q = density^2 dt`` per interval).
    acc_bias_rw, gyr_bias_rw : float
        Offset random-walk densities, m/s^2/sqrt(s) and rad/s/sqrt(s).
    pos_noise : float
        Extra position process noise, m/sqrt(s).
    gate_probability : float
        Chi-square gate of the 3-dof single-coil update (``ekf.chi2_gate``).
    iterations : int
        Passes of the iterated update (1: plain EKF).
    """

    @classmethod
    def from_config(cls, cfg=None, **overrides) -> "SchepersEKF":
        """The filter of ``cfg`` (default ``FirmwareConfig()``), with ``overrides``:
        the per-sample IMU noise at ``imu_rate_hz`` becomes the density the
        filter integrates (``Q = d^2 dt``)."""
        if cfg is None:
            from coiltrack.firmware.config import FirmwareConfig
            cfg = FirmwareConfig()
        root = math.sqrt(cfg.imu_rate_hz)
        kw = dict(n_clones=2, gravity=cfg.gravity_mps2, acc_noise=cfg.imu_acc_sigma / root,
                  gyr_noise=cfg.imu_gyro_sigma / root, acc_bias_rw=cfg.imu_acc_bias_rw,
                  gyr_bias_rw=cfg.imu_gyro_bias_rw, pos_noise=cfg.adaptive_pos_noise,
                  gate_probability=cfg.nis_gate_probability, iterations=cfg.single_coil_iterations)
        kw.update(overrides)
        return cls(**kw)

    @staticmethod
    def _make_layout(n_clones: int):
        """The state table (a subclass with more states gives its own)."""
        return schepers_layout(n_clones)

    def __init__(self, *, n_clones: int, gravity, acc_noise: float, gyr_noise: float, acc_bias_rw: float,
                 gyr_bias_rw: float, pos_noise: float, gate_probability: float, iterations: int,
                 core=_DEFAULT_CORE):
        self.n_clones = int(n_clones)
        self.layout = self._make_layout(self.n_clones)
        nx = self.layout.n
        self.nx = nx
        self._cp = tuple(getattr(self.layout, f"C{k}P") for k in range(self.n_clones))
        self._co = tuple(getattr(self.layout, f"C{k}O") for k in range(self.n_clones))
        self.g = np.array(gravity, dtype=float).reshape(3)
        self.acc_noise = float(acc_noise)
        self.gyr_noise = float(gyr_noise)
        self.acc_bias_rw = float(acc_bias_rw)
        self.gyr_bias_rw = float(gyr_bias_rw)
        self.pos_noise = float(pos_noise)
        self.iterations = max(1, int(iterations))
        # nominal state
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.R = np.eye(3)
        self.ba = np.zeros(3)
        self.bg = np.zeros(3)
        self.P = np.zeros((nx, nx))
        self._P_diag = self.P.reshape(-1)[::nx + 1]   # writable strided view
        self.initialized = False
        self.t_us: int | None = None
        self.updates = 0
        self.rejected = 0
        # last inputs (offsets removed), for prediction ahead
        self.f = np.zeros(3)
        self.w = np.zeros(3)
        self._acc_prev = np.zeros(3)
        self._gyr_prev = np.zeros(3)
        self._have_prev = False
        # clones
        self.clone_p = np.zeros((self.n_clones, 3))
        self.clone_R = np.zeros((self.n_clones, 3, 3))
        self.clone_R[:] = np.eye(3)
        self.clone_t = np.zeros(self.n_clones, dtype=np.int64)
        self.clone_due = np.zeros(self.n_clones, dtype=bool)     # scheduled, not yet taken
        self.clone_taken = np.zeros(self.n_clones, dtype=bool)
        # propagation buffers
        self.F = np.eye(nx)
        self._Ft = self.F.T
        self._T = np.zeros((nx, nx))
        self._q = np.zeros(nx)
        self._dR = np.eye(3)
        self._R2 = np.eye(3)
        self._sd = Strapdown(core)
        self._pv = memoryview(self.p)
        self._vv = memoryview(self.v)
        self._Rv = memoryview(self.R)
        self._Fv = memoryview(self.F)
        self._fref = (-float(self.g[0]), -float(self.g[1]), -float(self.g[2]))
        self._steps = 0
        # 0-d operands (a Python float in a ufunc would become a new 0-d array) and a
        # column buffer (copies between columns of P would otherwise be buffered)
        self._k0 = np.zeros(())
        self._half = np.full((), 0.5)
        self._cols = np.zeros((nx, 3))
        self._rows = np.zeros((3, nx))
        self._Tb = np.zeros((6, nx))
        self._TP = np.zeros((6, nx))
        self._TPT = np.zeros((6, 6))
        # prediction-ahead buffers (core block only)
        self._Fc = np.eye(N_CORE)
        self._Fct = self._Fc.T
        self._Fcv = memoryview(self._Fc)
        self._Pc = np.zeros((N_CORE, N_CORE))
        self._Pc_diag = self._Pc.reshape(-1)[::N_CORE + 1]
        self._Tc = np.zeros((N_CORE, N_CORE))
        self._qc = np.zeros(N_CORE)
        # update: the shared shape, plus the nominal NIS for the monitor
        self.upd = KalmanUpdate(nx, 3, gate_probability, core)
        self._PHt = np.zeros((nx, 3))
        self._S = np.zeros((3, 3))
        self.y_pred = np.zeros(3)
        self.nis = 0.0
        self.nis_nominal = 0.0
        self._P0 = np.zeros((nx, nx))
        self._Pprev = np.zeros((nx, nx))
        self._dx = np.zeros(nx)
        self._pi = np.zeros(3)
        self._Ri = np.eye(3)
        self._Hdx = np.zeros(3)

    # ------------------------------------------------------------ set-up
    def initialize(self, p, R, P6, t_us: int, sigma_vel: float, sigma_acc: float,
                   sigma_gyr: float) -> None:
        """Start from a pose (e.g. a full-cycle solution) and its 6x6
        covariance ``P6`` over ``(dp, ori)``; velocity 0 and offsets 0 with
        the given standard deviations."""
        self.p[:] = p
        self.R[:] = R
        self.v.fill(0.0)
        self.ba.fill(0.0)
        self.bg.fill(0.0)
        self.P.fill(0.0)
        self.P[POS, POS] = P6[POSE_POS, POSE_POS]
        self.P[POS, ORI] = P6[POSE_POS, POSE_ORI]
        self.P[ORI, POS] = P6[POSE_ORI, POSE_POS]
        self.P[ORI, ORI] = P6[POSE_ORI, POSE_ORI]
        for s, sig in ((VEL, sigma_vel), (ACC, sigma_acc), (GYR, sigma_gyr)):
            for i in range(s.start, s.stop):
                self.P[i, i] = sig * sig
        self.clone_due.fill(False)
        self.clone_taken.fill(False)
        self.initialized = True
        if self.t_us is None:
            self.t_us = int(t_us)

    def reset(self) -> None:
        """Forget the pose (keep the inertial integration running)."""
        self.initialized = False
        self.P.fill(0.0)
        self.clone_due.fill(False)
        self.clone_taken.fill(False)

    # ------------------------------------------------------------ clones
    def schedule_clone(self, k: int, t_us: int) -> None:
        """Clone the pose at ``t_us`` (the mid time of pulse slot k's used samples)."""
        self.clone_t[k] = int(t_us)
        self.clone_due[k] = True
        self.clone_taken[k] = False
        if self.t_us is not None and self.t_us >= t_us:
            self._take_clone(k)

    def _take_clone(self, k: int) -> None:
        self.clone_p[k] = self.p
        self.clone_R[k] = self.R
        self.clone_due[k] = False
        self.clone_taken[k] = True
        if not self.initialized:
            return
        cp, co = self._cp[k], self._co[k]
        P = self.P
        for dst, src in ((cp, POS), (co, ORI)):
            np.copyto(self._rows, P[src, :])
            np.copyto(P[dst, :], self._rows)
        for dst, src in ((cp, POS), (co, ORI)):
            np.copyto(self._cols, P[:, src])
            np.copyto(P[:, dst], self._cols)

    def back_clone(self, k: int, dt: float, G) -> None:
        """Clone k as the pose ``dt`` seconds before the filter's time, predicted
        backwards from the current state: ``G`` (3, 3) is the orientation increment
        ``R_now^T R_then`` the gyroscope integration gave. For an amplitude measured
        before the filter was started (the acquisition burst): the update then
        corrects the present state, velocity included, through the transition.

        Constant velocity back over ``dt`` (right after a start the orientation
        is too uncertain to remove gravity from the specific force; the motion's
        acceleration is left to the velocity uncertainty): nominal
        ``p_then = p - v dt``, ``R_then = R G``; error::

            dp_then  = dp - dt dv
            dori_then = G^T (dori + dt dgyr)

        (the inverse of the ``_build_F`` transition without the specific-force
        terms).
        """
        cp, co = self._cp[k], self._co[k]
        cpk = self.clone_p[k]
        for i in range(3):
            cpk[i] = float(self.p[i]) - float(self.v[i]) * dt
        np.matmul(self.R, G, out=self.clone_R[k])
        self.clone_due[k] = False
        self.clone_taken[k] = True
        if not self.initialized:
            return
        T = self._Tb
        T.fill(0.0)
        for i in range(3):
            T[POSE_POS.start + i, POS.start + i] = 1.0
            T[POSE_POS.start + i, VEL.start + i] = -dt
            for j in range(3):
                T[POSE_ORI.start + i, ORI.start + j] = float(G[j, i])
                T[POSE_ORI.start + i, GYR.start + j] = dt * float(G[j, i])
        # the clone's rows and columns: T P, and T P T^T
        P = self.P
        np.matmul(T, P, out=self._TP)
        np.matmul(self._TP, T.T, out=self._TPT)
        np.copyto(P[cp, :], self._TP[POSE_POS])
        np.copyto(P[co, :], self._TP[POSE_ORI])
        np.copyto(self._rows, self._TP[POSE_POS])
        np.copyto(P[:, cp], self._rows.T)
        np.copyto(self._rows, self._TP[POSE_ORI])
        np.copyto(P[:, co], self._rows.T)
        np.copyto(P[cp, cp], self._TPT[POSE_POS, POSE_POS])
        np.copyto(P[cp, co], self._TPT[POSE_POS, POSE_ORI])
        np.copyto(P[co, cp], self._TPT[POSE_ORI, POSE_POS])
        np.copyto(P[co, co], self._TPT[POSE_ORI, POSE_ORI])

    def release_clone(self, k: int) -> None:
        cp, co = self._cp[k], self._co[k]
        self.P[cp, :].fill(0.0)
        self.P[co, :].fill(0.0)
        self.P[:, cp].fill(0.0)
        self.P[:, co].fill(0.0)
        self.clone_due[k] = False
        self.clone_taken[k] = False

    # ------------------------------------------------------- propagation
    def propagate(self, t_us: int, acc, gyr) -> None:
        """Advance to the IMU sample at ``t_us`` (raw specific force ``acc``
        m/s^2 and angular rate ``gyr`` rad/s, sensor frame). The interval
        since the previous sample uses the mean of the two samples; a clone
        scheduled inside it is taken at its own time (the step is split)."""
        t_us = int(t_us)
        if self.t_us is None or not self._have_prev:
            self.t_us = t_us
            self._acc_prev[:] = acc
            self._gyr_prev[:] = gyr
            self._have_prev = True
            return
        if t_us <= self.t_us:
            return
        np.add(self._acc_prev, acc, out=self.f)
        np.multiply(self.f, self._half, out=self.f)
        self.f -= self.ba
        np.add(self._gyr_prev, gyr, out=self.w)
        np.multiply(self.w, self._half, out=self.w)
        self.w -= self.bg
        self._acc_prev[:] = acc
        self._gyr_prev[:] = gyr
        t = self.t_us
        while True:
            nxt = t_us
            kk = -1
            for k in range(self.n_clones):
                if self.clone_due[k] and t < self.clone_t[k] <= nxt:
                    nxt = int(self.clone_t[k])
                    kk = k
            if nxt > t:
                self._step((nxt - t) * 1e-6)
                t = nxt
            if kk >= 0:
                self._take_clone(kk)
                continue
            if t >= t_us:
                break
        for k in range(self.n_clones):
            if self.clone_due[k] and self.clone_t[k] <= t_us:
                self._take_clone(k)
        self.t_us = t_us

    def restart_inputs(self) -> None:
        """After a gap in the IMU stream: the next sample starts a new interval."""
        self._have_prev = False

    def _step(self, dt: float) -> None:
        """Nominal strapdown step and covariance propagation over ``dt`` (s).

        The specific force is rotated with the mid-interval orientation: with
        the start orientation a rate ``w`` tilts gravity by ``w dt / 2`` on
        average (0.025 m/s^2 at 0.5 rad/s and 100 Hz), a bias the error model
        does not know."""
        R = self.R
        w0, w1, w2 = float(self.w[0]) * 0.5 * dt, float(self.w[1]) * 0.5 * dt, float(self.w[2]) * 0.5 * dt
        sd = self._sd
        sd.rotate(R, w0, w1, w2)                       # R_mid
        ax, ay, az = self._accel()
        integrate_pv(self._pv, self._vv, dt, ax, ay, az, ax, ay, az)
        if self.initialized:
            self._build_F(self._Fv, self._q, dt)
            np.matmul(self.F, self.P, out=self._T)
            np.matmul(self._T, self._Ft, out=self.P)
            self._P_diag += self._q
        sd.rotate(R, w0, w1, w2)
        self._steps += 1
        if self._steps % 64 == 0:
            self._orthonormalize()

    def _build_F(self, F, q, dt: float) -> None:
        """Error transition over ``dt`` (``strapdown.transition_sensor``: the
        core block of ``F``, a memoryview; clone rows keep the identity) and
        its diagonal process noise ``q``."""
        f, w = self.f, self.w
        transition_static(F, dt, 1.0, 1.0)
        transition_sensor(F, dt, self._Rv, float(f[0]), float(f[1]), float(f[2]),
                          float(w[0]), float(w[1]), float(w[2]), self._sd)
        self._fill_q(q, dt, self.acc_noise * self.acc_noise, self.pos_noise * self.pos_noise,
                     self.gyr_noise * self.gyr_noise)

    def _fill_q(self, q, dt: float, qa: float, qpos: float, qg: float) -> None:
        """The core block's diagonal process noise over ``dt`` (s) into ``q``: acceleration noise
        ``qa`` ((m/s^2)^2 s) into velocity and position, position noise ``qpos`` (m^2/s), rate
        noise ``qg`` (rad^2/s), the offsets' random walks."""
        qp = qa * dt * dt * dt / 3.0 + qpos * dt
        qv = qa * dt
        qo = qg * dt
        qba = self.acc_bias_rw * self.acc_bias_rw * dt
        qbg = self.gyr_bias_rw * self.gyr_bias_rw * dt
        for i in range(3):
            q[POS.start + i] = qp
            q[VEL.start + i] = qv
            q[ORI.start + i] = qo
            q[ACC.start + i] = qba
            q[GYR.start + i] = qbg

    def core_transition(self, F, q, dt: float) -> None:
        """The error transition of the core block (15, 15) over ``dt`` (s) at the
        present inputs and state, into ``F`` (a memoryview of a (15, 15) array
        whose off-model entries stay as ``transition_static`` writes them) and
        its diagonal process noise into ``q`` (15,): the transition this filter
        applies to its own covariance (eq 6.17 in this convention), for a
        covariance carried beside it (``coiltrack.firmware.actuate.accuracy``)."""
        self._build_F(F, q, dt)

    def _accel(self):
        """``R f - f_ref`` (``f_ref = -g``): the acceleration in the source frame."""
        f = self.f
        ax, ay, az = to_nav(self._Rv, float(f[0]), float(f[1]), float(f[2]))
        r = self._fref
        return ax - r[0], ay - r[1], az - r[2]

    def _orthonormalize(self) -> None:
        """One Newton step of the polar decomposition, ``R (3 I - R^T R) / 2``."""
        R = self.R
        np.matmul(R.T, R, out=self._R2)
        np.negative(self._R2, out=self._R2)
        for i in range(3):
            self._R2[i, i] += 3.0
        np.multiply(self._R2, self._half, out=self._R2)
        np.matmul(R, self._R2, out=self._dR)
        R[:] = self._dR

    # -------------------------------------------------------- prediction
    def predict_pose(self, horizon_us: int, out_P6, out_p, steps: int = 8) -> None:
        """Pose covariance (6x6 over ``(dp, ori)``) and position predicted
        ``horizon_us`` ahead with the last inertial inputs held, without
        changing the filter (for the when/which decisions)."""
        T = max(int(horizon_us), 0) * 1e-6
        n = max(1, int(steps))
        dt = T / n
        Pc = self._Pc
        Pc[:] = self.P[CORE, CORE]
        if dt > 0.0:
            Fc = self._Fc
            self._build_F(self._Fcv, self._qc, dt)
            for _ in range(n):
                np.matmul(Fc, Pc, out=self._Tc)
                np.matmul(self._Tc, self._Fct, out=Pc)
                self._Pc_diag += self._qc
        out_P6[POSE_POS, POSE_POS] = Pc[POS, POS]
        out_P6[POSE_POS, POSE_ORI] = Pc[POS, ORI]
        out_P6[POSE_ORI, POSE_POS] = Pc[ORI, POS]
        out_P6[POSE_ORI, POSE_ORI] = Pc[ORI, ORI]
        a = self._accel()
        p, v = self._pv, self._vv
        for i in range(3):
            out_p[i] = p[i] + (v[i] + 0.5 * T * a[i]) * T

    def pose_variances(self, out6) -> None:
        for i in range(3):
            out6[POSE_POS.start + i] = self.P[POS.start + i, POS.start + i]
            out6[POSE_ORI.start + i] = self.P[ORI.start + i, ORI.start + i]

    # ------------------------------------------------------------ update
    def update_single_coil(self, k: int, y, var_amp, coil: int, current: float,
                           model: SingleCoilModel, rel_model: float = 0.0,
                           r_scale: float = 1.0, gate: bool = True) -> int:
        """Correct the state with the amplitude ``y`` (3,) (T, sensor frame)
        of one pulse of ``coil`` carrying ``current`` (A), measured at the
        time of clone ``k`` (``k = -1``: the current state).

        Measurement covariance: ``var_amp`` (3,), the amplitude variances
        (T^2), plus ``(rel_model |h|)^2`` for the field model, plus the
        linearisation error of Schepers sec. 3.2: for a field falling as
        ``r^-3`` the second-order term of ``h(p + dp)`` is about
        ``6 (dp/r)^2 |h|``, which the first-order model misses (the paper
        shows it grows near the source and with the uncertainty and "can
        cause the filter to diverge"); ``(6 sigma_p^2 / r^2 |h|)^2`` is added
        with ``sigma_p`` the largest prior position std and ``r`` the
        distance to the coil. Negligible once tracking (``sigma_p/r`` ~ 1 %:
        6e-4 of the field), it damps the first updates after an acquisition.
        The whole covariance is multiplied by ``r_scale`` (the NIS monitor's
        inflation).

        Iterated update (``iterations`` > 1): the measurement is
        relinearised at the corrected clone pose, ``dx_{i+1} = K_i (y -
        h(x_i) + H_i dx_i)`` (Gauss-Newton on the eq-4 cost), each pass through
        the shared ``KalmanUpdate`` from the prior covariance; the last pass
        gives the covariance. A second pass is made only when the first
        correction changes ``h`` through its second-order term by more than a
        tenth of the amplitude noise (after an acquisition, not while
        tracking). The gate and the NIS are those of the first pass (the
        plain EKF innovation).

        ``gate=False`` skips the chi-square gate (the caller has already
        judged the pulses inconsistent and inflated ``R``: gating them too
        would reject every pulse while the innovations grow, leaving the state
        to the IMU alone).

        Returns the ``ekf.EKF_*`` flags; ``nis_nominal`` is the first-pass
        NIS with ``r_scale = 1`` (for the monitor), ``nis`` the one gated.
        """
        if not self.initialized:
            return EKF_NO_STATE
        if k >= 0:
            if not self.clone_taken[k]:
                # the IMU stream has not reached the measurement time: measure now
                self._take_clone(k)
            p, R = self.clone_p[k], self.clone_R[k]
            cp, co = self._cp[k], self._co[k]
        else:
            p, R = self.p, self.R
            cp, co = POS, ORI
        upd = self.upd
        H = upd.H
        Rm = upd.R
        # measurement covariance, from the prior
        model.evaluate(p, R)
        cur = self._k0
        cur[()] = current
        np.multiply(model.h[coil], cur, out=self.y_pred)
        yp = self.y_pred
        hn2 = float(yp[0] * yp[0] + yp[1] * yp[1] + yp[2] * yp[2])
        b = cp.start
        sp2 = max(float(self.P[b, b]), float(self.P[b + 1, b + 1]), float(self.P[b + 2, b + 2]))
        c = model.cs.centers[coil]
        ddx, ddy, ddz = float(p[0] - c[0]), float(p[1] - c[1]), float(p[2] - c[2])
        r2 = max(ddx * ddx + ddy * ddy + ddz * ddz, 1e-6)
        lin = _LIN_K * sp2 / r2
        extra = (rel_model * rel_model + lin * lin) * hn2
        Rm.fill(0.0)
        for i in range(3):
            Rm[i, i] = float(var_amp[i]) + extra
        self._P0[:] = self.P
        dx = self._dx
        dx.fill(0.0)
        pi, Ri = self._pi, self._Ri
        pi[:] = p
        Ri[:] = R
        flags = 0
        for it in range(self.iterations):
            if it:
                model.evaluate(pi, Ri)
                np.multiply(model.h[coil], cur, out=self.y_pred)
            Hu = model.H[coil]
            H.fill(0.0)
            np.multiply(Hu[:, 0:3], cur, out=H[:, cp])
            np.multiply(Hu[:, 3:6], cur, out=H[:, co])
            # pseudo-innovation y - h(x_i) + H_i dx_i
            np.subtract(y, self.y_pred, out=upd.y)
            if it:
                np.matmul(H, dx, out=self._Hdx)
                upd.y += self._Hdx
            else:
                # first pass: the nominal NIS (the monitor's input), with the unscaled R
                np.matmul(self.P, upd._Ht, out=self._PHt)
                np.matmul(H, self._PHt, out=self._S)
                self._S += Rm
                self.nis_nominal = _nis3(self._S, upd.y)
                if r_scale != 1.0:
                    for i in range(3):
                        Rm[i, i] *= r_scale
            else_gate = upd.gate
            if it or not gate:
                upd.gate = math.inf          # the gate belongs to the first pass
            if it:
                self.P[:] = self._P0
            f = upd.update(self.P)
            upd.gate = else_gate
            if it == 0:
                flags = f
                self.nis = upd.nis
                if f & (EKF_GATED | EKF_NOT_PD | EKF_NONFINITE):
                    self.rejected += 1
                    return f
            elif f & (EKF_NOT_PD | EKF_NONFINITE):
                # keep the previous pass
                self.P[:] = self._Pprev
                break
            b = cp.start
            step = max(abs(float(upd.dx[b + i]) - float(dx[b + i])) for i in range(3))
            dx[:] = upd.dx
            if it == 0:
                # relinearise only if the correction moves h by more than a fraction of the
                # noise through the second-order term (~ 6 (dp/r)^2 |h|, Schepers sec. 3.2)
                b = cp.start
                dp2 = float(dx[b] * dx[b] + dx[b + 1] * dx[b + 1] + dx[b + 2] * dx[b + 2])
                so = 6.0 * dp2 / r2
                noise2 = float(var_amp[0] + var_amp[1] + var_amp[2]) / 3.0
                if so * so * hn2 < 0.01 * noise2:
                    break
            if it + 1 < self.iterations:
                self._Pprev[:] = self.P
                # next linearisation point: the corrected clone pose
                np.add(p, dx[cp], out=pi)
                o = co.start
                exp_rotvec(float(dx[o]), float(dx[o + 1]), float(dx[o + 2]), self._dR)
                np.matmul(R, self._dR, out=Ri)
                if step < 1e-6:
                    break
        self._inject(dx)
        self.updates += 1
        return flags

    def _inject(self, dx) -> None:
        """Apply the error estimate to the nominal state (error reset)."""
        self.p += dx[POS]
        self.v += dx[VEL]
        self.ba += dx[ACC]
        self.bg += dx[GYR]
        o = ORI.start
        self._sd.rotate(self.R, float(dx[o]), float(dx[o + 1]), float(dx[o + 2]))
        for k in range(self.n_clones):
            if self.clone_taken[k]:
                self.clone_p[k] += dx[self._cp[k]]
                c = self._co[k].start
                self._sd.rotate(self.clone_R[k], float(dx[c]), float(dx[c + 1]), float(dx[c + 2]))


def _nis3(S, r) -> float:
    """``r^T S^-1 r`` for a symmetric 3x3 ``S`` (inf if not positive definite)."""
    inv = inv3_sym(float(S[0, 0]), float(S[0, 1]), float(S[0, 2]),
                   float(S[1, 1]), float(S[1, 2]), float(S[2, 2]))
    if inv is None:
        return math.inf
    return quad3_sym(inv, float(r[0]), float(r[1]), float(r[2]))
