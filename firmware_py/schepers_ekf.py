"""Error-state EKF for single-coil magnetic updates with inertial propagation.

Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``) sec. 2.1: "a
fusion filter that predicts the change of position and orientation by
integration of acceleration and angular velocity measured by inertial
sensors"; a magnetic update takes the pulse of ONE source coil,
``y = R^T B_c(p) + v`` (eq 5, field eqs 6-8), linearised with eqs 9-11, and
corrects the error state with eq 4. The error-state structure and the
strapdown error model follow the thesis' complementary filter
(``seeds/002_cd7f1fdb7fc67471.txt`` ch. 6, eqs 6.10-6.17) with the gyroscope
and accelerometer offsets as random walks.

State layout (``LAYOUT``: name, index, size; code indexes the covariance
with the named slices, never with bare numbers)::

    pos   0  3   sensor position in the source frame, m
    vel   3  3   velocity in the source frame, m/s
    att   6  3   orientation error, sensor frame, rad
    bacc  9  3   accelerometer offset, sensor frame, m/s^2
    bgyr 12  3   gyroscope offset, sensor frame, rad/s
    clone k: 15 + 6 k, 6   (pos, att) copied at the time pulse k is measured

Error convention: ``x_true = x_est + dx`` for vectors and
``R_true = R_est exp([dtheta]x)`` (as ``firmware_py.solve``), so the
measurement Jacobian's orientation block is ``+[h]x`` (Schepers eq 11 with
their opposite error sign, eq 2) and the correction is ``x += K (y - h)``.

Inertial propagation (one IMU sample ``(f, w)``, specific force and angular
rate in the sensor frame, offsets removed)::

    p += v dt + (R f + g) dt^2 / 2,   v += (R f + g) dt,   R = R exp([w dt]x)

and the error transition (first order in dt, plus the dt^2 terms of the
position)::

    d(dp)/dt     = dv
    d(dv)/dt     = -R [f]x dtheta - R dbacc - R n_a
    d(dtheta)/dt = -[w]x dtheta - dbgyr - n_g
    d(dbacc)/dt  = n_ba,   d(dbgyr)/dt = n_bg

A pulse is measured over tens of milliseconds and its window closes one
baseline later, so the update arrives ~0.1 s after the instant it describes.
The filter clones the pose error at that instant (stochastic cloning: the
clone rows/columns of ``P`` are copied from ``pos``/``att`` and propagate
with an identity transition), evaluates ``h`` and ``H`` at the cloned nominal
pose and corrects the whole state through the cross-covariance when the
amplitude is in.

The update has the one shape all estimator updates use: innovation,
innovation covariance, chi-square gate, gain, Joseph-form covariance update,
health flags returned (never raised). Every array is allocated in
``__init__``.
"""
from __future__ import annotations

import math

import numpy as np

from .adaptive import SingleCoilModel
from .solve import so3_exp

__all__ = ["LAYOUT", "POS", "VEL", "ATT", "BACC", "BGYR", "N_CORE", "CLONE_SIZE",
           "clone_pos", "clone_att", "SchepersEKF",
           "UPD_OK", "UPD_GATED", "UPD_NOT_PD", "UPD_NONFINITE", "UPD_NO_STATE", "UPD_DISTORTED",
           "measurement_update", "UpdateWork"]

LAYOUT = (("pos", 0, 3), ("vel", 3, 3), ("att", 6, 3), ("bacc", 9, 3), ("bgyr", 12, 3))
_IDX = {name: slice(i, i + n) for name, i, n in LAYOUT}
POS = _IDX["pos"]
VEL = _IDX["vel"]
ATT = _IDX["att"]
BACC = _IDX["bacc"]
BGYR = _IDX["bgyr"]
N_CORE = 15
CLONE_SIZE = 6


def clone_pos(k: int) -> slice:
    b = N_CORE + CLONE_SIZE * k
    return slice(b, b + 3)


def clone_att(k: int) -> slice:
    b = N_CORE + CLONE_SIZE * k + 3
    return slice(b, b + 3)


# health flags of an update (bit field)
UPD_OK = 0
UPD_GATED = 1          # NIS above the gate: state and covariance unchanged
UPD_NOT_PD = 2         # innovation covariance not positive definite: unchanged
UPD_NONFINITE = 4      # non-finite input or result: unchanged
UPD_NO_STATE = 8       # filter not initialised / clone missing
UPD_DISTORTED = 16     # made with an inflated measurement covariance (NIS monitor)

_GRAVITY = (0.0, 0.0, -9.81)


class UpdateWork:
    """Buffers of a 3-dimensional measurement update on an ``nx`` state."""

    def __init__(self, nx: int, m: int = 3):
        self.nx = nx
        self.m = m
        self.PHt = np.zeros((nx, m))
        self.S = np.zeros((m, m))
        self.Sinv = np.zeros((m, m))
        self.K = np.zeros((nx, m))
        self.KR = np.zeros((nx, m))
        self.IKH = np.zeros((nx, nx))
        self.T = np.zeros((nx, nx))
        self.T2 = np.zeros((nx, nx))
        self.dx = np.zeros(nx)
        self.Sr = np.zeros(m)
        self.IKH_diag = self.IKH.reshape(-1)[::nx + 1]   # writable strided view
        self.nis = 0.0
        self.nis_nominal = 0.0


def _inv3_into(S, out) -> bool:
    """Inverse of a symmetric positive-definite 3x3 ``S`` into ``out``."""
    a00, a01, a02 = float(S[0, 0]), float(S[0, 1]), float(S[0, 2])
    a11, a12, a22 = float(S[1, 1]), float(S[1, 2]), float(S[2, 2])
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    if not (det > 0.0 and a00 > 0.0 and a00 * a11 - a01 * a01 > 0.0) or not math.isfinite(det):
        return False
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[0, 1] = out[1, 0] = c01 * inv
    out[0, 2] = out[2, 0] = c02 * inv
    out[1, 1] = (a00 * a22 - a02 * a02) * inv
    out[1, 2] = out[2, 1] = (a01 * a02 - a00 * a12) * inv
    out[2, 2] = (a00 * a11 - a01 * a01) * inv
    return True


def measurement_update(P, H, r, Rv, gate: float, w: UpdateWork, r_scale: float = 1.0) -> int:
    """One 3-dimensional Kalman update in the shared shape (Schepers eq 4).

    innovation ``r`` (given), innovation covariance
    ``S = H P H^T + r_scale Rv``, chi-square gate on ``NIS = r^T S^-1 r``,
    gain ``K = P H^T S^-1``, correction ``dx = K r`` (in ``w.dx``) and the
    Joseph form ``P = (I - K H) P (I - K H)^T + K (r_scale Rv) K^T``, which
    stays symmetric positive semi-definite with a suboptimal gain.
    ``w.nis_nominal`` is the NIS with ``r_scale = 1`` (for the monitor),
    ``w.nis`` the one gated. Returns ``UPD_*`` flags; on any flag but
    ``UPD_DISTORTED`` the state and ``P`` are unchanged and ``w.dx`` is 0.
    """
    w.dx[:] = 0.0
    if not (math.isfinite(float(np.dot(r, r))) and math.isfinite(float(H.sum()))):
        return UPD_NONFINITE
    np.matmul(P, H.T, out=w.PHt)
    np.matmul(H, w.PHt, out=w.S)
    w.S += Rv
    # nominal NIS
    if not _inv3_into(w.S, w.Sinv):
        return UPD_NOT_PD
    np.matmul(w.Sinv, r, out=w.Sr)
    w.nis_nominal = float(np.dot(r, w.Sr))
    flags = UPD_OK
    if r_scale != 1.0:
        w.S += (r_scale - 1.0) * Rv
        if not _inv3_into(w.S, w.Sinv):
            return UPD_NOT_PD
        np.matmul(w.Sinv, r, out=w.Sr)
        flags |= UPD_DISTORTED
    w.nis = float(np.dot(r, w.Sr))
    if not math.isfinite(w.nis):
        return UPD_NONFINITE
    if w.nis > gate:
        return flags | UPD_GATED
    np.matmul(w.PHt, w.Sinv, out=w.K)
    np.matmul(w.K, r, out=w.dx)
    # Joseph form
    np.matmul(w.K, H, out=w.IKH)
    np.negative(w.IKH, out=w.IKH)
    w.IKH_diag += 1.0
    np.matmul(w.IKH, P, out=w.T)
    np.matmul(w.T, w.IKH.T, out=w.T2)
    np.matmul(w.K, Rv, out=w.KR)
    if r_scale != 1.0:
        w.KR *= r_scale
    np.matmul(w.KR, w.K.T, out=w.T)
    np.add(w.T2, w.T, out=w.T2)
    if not math.isfinite(float(w.T2.sum())):
        w.dx[:] = 0.0
        return UPD_NONFINITE
    # symmetrise
    np.add(w.T2, w.T2.T, out=P)
    P *= 0.5
    return flags


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
        White-noise densities, m/s^2/sqrt(Hz) and rad/s/sqrt(Hz).
    acc_bias_rw, gyr_bias_rw : float
        Offset random-walk densities, m/s^3/sqrt(Hz) and rad/s^2/sqrt(Hz).
    pos_noise : float
        Extra position process noise, m/sqrt(s) (unmodelled motion during
        a pulse, timing).
    """

    def __init__(self, n_clones: int = 2, gravity=_GRAVITY, acc_noise: float = 2e-3,
                 gyr_noise: float = 1e-3, acc_bias_rw: float = 1e-4, gyr_bias_rw: float = 1e-5,
                 pos_noise: float = 0.0):
        self.n_clones = int(n_clones)
        nx = N_CORE + CLONE_SIZE * self.n_clones
        self.nx = nx
        self.g = np.array(gravity, dtype=float).reshape(3)
        self.acc_noise = float(acc_noise)
        self.gyr_noise = float(gyr_noise)
        self.acc_bias_rw = float(acc_bias_rw)
        self.gyr_bias_rw = float(gyr_bias_rw)
        self.pos_noise = float(pos_noise)
        # nominal state
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.R = np.eye(3)
        self.ba = np.zeros(3)
        self.bg = np.zeros(3)
        self.P = np.zeros((nx, nx))
        self._P_diag = self.P.reshape(-1)[::nx + 1]
        self.initialized = False
        self.t_us: int | None = None
        self.updates = 0
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
        self._T = np.zeros((nx, nx))
        self._q = np.zeros(nx)
        self._a = np.zeros(3)
        self._tmp3 = np.zeros(3)
        self._dR = np.eye(3)
        self._R2 = np.eye(3)
        self._fx = np.zeros((3, 3))
        self._Rfx = np.zeros((3, 3))
        self._steps = 0
        # prediction-ahead buffers (core block only)
        self._Fc = np.eye(N_CORE)
        self._Pc = np.zeros((N_CORE, N_CORE))
        self._Pc_diag = self._Pc.reshape(-1)[::N_CORE + 1]
        self._Tc = np.zeros((N_CORE, N_CORE))
        self._qc = np.zeros(N_CORE)
        # update buffers
        self.work = UpdateWork(nx)
        self.H = np.zeros((3, nx))
        self.r = np.zeros(3)
        self.Rv = np.zeros((3, 3))
        self.y_pred = np.zeros(3)

    # ------------------------------------------------------------ set-up
    def initialize(self, p, R, P6, t_us: int, sigma_vel: float, sigma_bacc: float,
                   sigma_bgyr: float) -> None:
        """Start from a pose (e.g. a full-cycle solution) and its 6x6
        covariance ``P6`` over ``(dp, dtheta)``; velocity 0 and offsets 0
        with the given standard deviations."""
        self.p[:] = p
        self.R[:] = R
        self.v[:] = 0.0
        self.ba[:] = 0.0
        self.bg[:] = 0.0
        self.P[:] = 0.0
        self.P[POS, POS] = P6[0:3, 0:3]
        self.P[POS, ATT] = P6[0:3, 3:6]
        self.P[ATT, POS] = P6[3:6, 0:3]
        self.P[ATT, ATT] = P6[3:6, 3:6]
        for s, sig in ((VEL, sigma_vel), (BACC, sigma_bacc), (BGYR, sigma_bgyr)):
            for i in range(s.start, s.stop):
                self.P[i, i] = sig * sig
        self.clone_due[:] = False
        self.clone_taken[:] = False
        self.initialized = True
        if self.t_us is None:
            self.t_us = int(t_us)

    def reset(self) -> None:
        self.initialized = False
        self.P[:] = 0.0
        self.clone_due[:] = False
        self.clone_taken[:] = False

    # ------------------------------------------------------------ clones
    def schedule_clone(self, k: int, t_us: int) -> None:
        """Clone the pose at ``t_us`` (the mid time of pulse k's used samples)."""
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
        cp, ca = clone_pos(k), clone_att(k)
        P = self.P
        P[cp, :] = P[POS, :]
        P[ca, :] = P[ATT, :]
        P[:, cp] = P[:, POS]
        P[:, ca] = P[:, ATT]

    def release_clone(self, k: int) -> None:
        cp, ca = clone_pos(k), clone_att(k)
        self.P[cp, :] = 0.0
        self.P[ca, :] = 0.0
        self.P[:, cp] = 0.0
        self.P[:, ca] = 0.0
        self.clone_due[k] = False
        self.clone_taken[k] = False

    # ------------------------------------------------------- propagation
    def propagate(self, t_us: int, acc, gyr) -> None:
        """Advance to the IMU sample at ``t_us`` (raw specific force ``acc``
        m/s^2 and angular rate ``gyr`` rad/s, sensor frame). The interval
        since the previous sample uses the mean of the two samples; a clone
        scheduled inside it is taken at its own time."""
        t_us = int(t_us)
        if self.t_us is None or not self._have_prev:
            self.t_us = t_us
            self._acc_prev[:] = acc
            self._gyr_prev[:] = gyr
            self._have_prev = True
            return
        if t_us <= self.t_us:
            return
        # mean inputs over the interval, offsets removed
        np.add(self._acc_prev, acc, out=self.f)
        self.f *= 0.5
        self.f -= self.ba
        np.add(self._gyr_prev, gyr, out=self.w)
        self.w *= 0.5
        self.w -= self.bg
        self._acc_prev[:] = acc
        self._gyr_prev[:] = gyr
        t = self.t_us
        while True:
            # next clone time inside (t, t_us]
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
        # a clone whose time passed while no sample came is taken now
        for k in range(self.n_clones):
            if self.clone_due[k] and self.clone_t[k] <= t_us:
                self._take_clone(k)
        self.t_us = t_us

    def _step(self, dt: float) -> None:
        """Nominal strapdown step and covariance propagation over dt (s).

        The specific force is rotated with the orientation at the middle of
        the interval, ``R exp([w dt/2]x)``: with the start orientation a
        rotation rate ``w`` would tilt gravity by ``w dt / 2`` on average
        (0.25 m/s^2 at 0.5 rad/s and 100 Hz), a bias the error model does
        not know."""
        R = self.R
        f = self.f
        # half-step rotation: R_mid = R exp([w dt/2]x)
        self._tmp3[:] = self.w
        self._tmp3 *= 0.5 * dt
        so3_exp(self._tmp3, out=self._dR)
        np.matmul(R, self._dR, out=self._R2)
        R[:] = self._R2
        # a = R_mid f + g
        np.matmul(R, f, out=self._a)
        self._a += self.g
        # p += v dt + a dt^2/2 ; v += a dt
        self._tmp3[:] = self.v
        self._tmp3 *= dt
        self.p += self._tmp3
        self._tmp3[:] = self._a
        self._tmp3 *= 0.5 * dt * dt
        self.p += self._tmp3
        self._tmp3[:] = self._a
        self._tmp3 *= dt
        self.v += self._tmp3
        if self.initialized:
            self._build_F(self.F, self._q, dt)
            np.matmul(self.F, self.P, out=self._T)
            np.matmul(self._T, self.F.T, out=self.P)
            self._P_diag += self._q
        # second half step: R = R_mid exp([w dt/2]x)
        np.matmul(R, self._dR, out=self._R2)
        R[:] = self._R2
        self._steps += 1
        if self._steps % 64 == 0:
            self._orthonormalize()

    def _build_F(self, F, q, dt: float) -> None:
        """Discrete error transition (core block of ``F``) and diagonal
        process noise ``q`` over ``dt`` (thesis eq 6.17 with offsets as
        random walks; error dynamics in the module docstring)."""
        R = self.R
        fx = self._fx
        fx[0, 0] = fx[1, 1] = fx[2, 2] = 0.0
        fx[0, 1] = -self.f[2]
        fx[0, 2] = self.f[1]
        fx[1, 0] = self.f[2]
        fx[1, 2] = -self.f[0]
        fx[2, 0] = -self.f[1]
        fx[2, 1] = self.f[0]
        np.matmul(R, fx, out=self._Rfx)            # R [f]x
        h2 = 0.5 * dt * dt
        # pos row
        F[POS, VEL] = 0.0
        for i in range(3):
            F[POS.start + i, VEL.start + i] = dt
        np.multiply(self._Rfx, -h2, out=F[POS, ATT])
        np.multiply(R, -h2, out=F[POS, BACC])
        # vel row
        np.multiply(self._Rfx, -dt, out=F[VEL, ATT])
        np.multiply(R, -dt, out=F[VEL, BACC])
        # att row: exp(-[w]x dt), -I dt
        self._tmp3[:] = self.w
        self._tmp3 *= -dt
        so3_exp(self._tmp3, out=F[ATT, ATT])
        F[ATT, BGYR] = 0.0
        for i in range(3):
            F[ATT.start + i, BGYR.start + i] = -dt
        qa = self.acc_noise * self.acc_noise
        qg = self.gyr_noise * self.gyr_noise
        q[POS] = qa * dt * dt * dt / 3.0 + self.pos_noise * self.pos_noise * dt
        q[VEL] = qa * dt
        q[ATT] = qg * dt
        q[BACC] = self.acc_bias_rw * self.acc_bias_rw * dt
        q[BGYR] = self.gyr_bias_rw * self.gyr_bias_rw * dt

    def _orthonormalize(self) -> None:
        """One Newton step of the polar decomposition, ``R (3 I - R^T R) / 2``."""
        R = self.R
        np.matmul(R.T, R, out=self._R2)
        np.negative(self._R2, out=self._R2)
        for i in range(3):
            self._R2[i, i] += 3.0
        self._R2 *= 0.5
        np.matmul(R, self._R2, out=self._dR)
        R[:] = self._dR

    # -------------------------------------------------------- prediction
    def predict_pose(self, horizon_us: int, out_P6, out_p, steps: int = 8) -> None:
        """Pose covariance (6x6 over ``(dp, dtheta)``) and position predicted
        ``horizon_us`` ahead with the last inertial inputs held, without
        changing the filter (for the when/which decisions)."""
        dt_total = max(horizon_us, 0) * 1e-6
        n = max(1, int(steps))
        dt = dt_total / n
        Pc = self._Pc
        Pc[:] = self.P[:N_CORE, :N_CORE]
        if dt > 0.0:
            Fc = self._Fc
            self._build_F(Fc, self._qc, dt)
            for _ in range(n):
                np.matmul(Fc, Pc, out=self._Tc)
                np.matmul(self._Tc, Fc.T, out=Pc)
                self._Pc_diag += self._qc
        out_P6[0:3, 0:3] = Pc[POS, POS]
        out_P6[0:3, 3:6] = Pc[POS, ATT]
        out_P6[3:6, 0:3] = Pc[ATT, POS]
        out_P6[3:6, 3:6] = Pc[ATT, ATT]
        # p + v T + a T^2 / 2
        np.matmul(self.R, self.f, out=self._a)
        self._a += self.g
        out_p[:] = self._a
        out_p *= 0.5 * dt_total
        out_p += self.v
        out_p *= dt_total
        out_p += self.p

    def pose_variances(self, out6) -> None:
        for i in range(3):
            out6[i] = self.P[POS.start + i, POS.start + i]
            out6[3 + i] = self.P[ATT.start + i, ATT.start + i]

    # ------------------------------------------------------------ update
    def update_single_coil(self, k: int, y, var_amp, coil: int, current: float,
                           model: SingleCoilModel, rel_model: float, gate: float,
                           r_scale: float = 1.0) -> int:
        """Correct the state with the amplitude ``y`` (3,) (T, sensor frame)
        of one pulse of ``coil`` carrying ``current`` (A), measured at the
        time of clone ``k`` (``k = -1``: the current state).

        ``var_amp`` (3,) are the amplitude variances (T^2); the measurement
        covariance adds ``(rel_model |h|)^2`` for the field model. Returns
        ``UPD_*`` flags; ``self.work.nis`` / ``nis_nominal`` hold the NIS.
        """
        if not self.initialized:
            return UPD_NO_STATE
        if k >= 0:
            if not self.clone_taken[k]:
                # the filter has not reached the measurement time (no IMU):
                # measure the current state instead
                self._take_clone(k)
            p, R = self.clone_p[k], self.clone_R[k]
            cp, ca = clone_pos(k), clone_att(k)
        else:
            p, R = self.p, self.R
            cp, ca = POS, ATT
        model.evaluate(p, R)
        Hu = model.H[coil]
        hu = model.h[coil]
        H = self.H
        H[:] = 0.0
        np.multiply(Hu[:, 0:3], current, out=H[:, cp])
        np.multiply(Hu[:, 3:6], current, out=H[:, ca])
        np.multiply(hu, current, out=self.y_pred)
        np.subtract(y, self.y_pred, out=self.r)
        hn2 = float(np.dot(self.y_pred, self.y_pred))
        Rv = self.Rv
        Rv[:] = 0.0
        extra = rel_model * rel_model * hn2
        for i in range(3):
            Rv[i, i] = float(var_amp[i]) + extra
        flags = measurement_update(self.P, H, self.r, Rv, gate, self.work, r_scale)
        if flags & (UPD_GATED | UPD_NOT_PD | UPD_NONFINITE):
            return flags
        self._inject(self.work.dx)
        self.updates += 1
        return flags

    def _inject(self, dx) -> None:
        """Apply the error estimate to the nominal state (error reset)."""
        self.p += dx[POS]
        self.v += dx[VEL]
        self.ba += dx[BACC]
        self.bg += dx[BGYR]
        so3_exp(dx[ATT], out=self._dR)
        np.matmul(self.R, self._dR, out=self._R2)
        self.R[:] = self._R2
        for k in range(self.n_clones):
            if self.clone_taken[k]:
                self.clone_p[k] += dx[clone_pos(k)]
                so3_exp(dx[clone_att(k)], out=self._dR)
                np.matmul(self.clone_R[k], self._dR, out=self._R2)
                self.clone_R[k] = self._R2
