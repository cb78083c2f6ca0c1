"""Orientation filter: gyroscope, accelerometer and magnetometer (thesis ch. 2).

Roetenberg thesis (``002_cd7f1fdb7fc67471.txt``) ch. 2: a complementary
Kalman filter that integrates the gyroscope (strapdown, eq 2.27) and
estimates the orientation error, the gyroscope offset error and the magnetic
disturbance error (state eq 2.15, table ``layout.ORIENTATION_LAYOUT``) from
two measurements: the inclination seen by the accelerometer against the one
predicted by the gyroscope (eqs 2.20, 2.23, 2.29), and the earth magnetic
field seen by the magnetometer against the one predicted by the gyroscope
(eqs 2.21, 2.24, 2.30). The estimated errors are fed back into the
orientation, offset and disturbance after every update (Fig. 2.2), so the
a-priori error estimate is zero at every step.

Frames and conventions
    ``R`` (attribute ``R``) maps sensor-frame vectors to the global frame
    ``G`` (z up, x along the horizontal component of the earth field, thesis
    eq 2.1: the rows of ``R`` are the global axes in the sensor frame).
    Errors are ``true = estimate + error`` with the orientation error
    ``theta`` in the sensor frame, ``R_true = R exp([theta]x)`` (the thesis
    defines it with the opposite sign, eq 2.25; the Kalman gain is the same).
    Gravity is ``-g e_z``; the accelerometer measures ``y_A = a - g``
    (eq 2.4), i.e. ``g Z`` at rest with ``Z = R^T e_z`` the "inclination".
    The magnetometer is used normalised by the earth-field magnitude
    learned at initialisation (eq 2.8: ``|m| = 1`` undisturbed).

Model (per IMU sample, step ``T``)
    * gyroscope ``y_G = w + b + v_G`` (eq 2.2), offset random walk (eq 2.3);
    * strapdown ``R <- R exp([(y_G - b) T]x)`` (first order: eq 2.27);
    * acceleration ``a_t = c_a a_{t-1} + w_a`` (eq 2.5), predicted in the
      sensor frame as ``c_a a+``, with ``a+ = y_A - g Z+`` after each update;
    * disturbance ``d_t = c_d d_{t-1} + w_d`` (eq 2.7), its driving noise
      raised when the field norm or dip angle change (eq 2.12).

Error propagation (eq 2.28 and its offset / disturbance rows)::

    theta_t = Gamma theta_{t-1} - T b_{t-1}      Gamma = exp(-[w T]x)
    b_t     = b_{t-1}
    d_t     = c_d d_{t-1}

``P = A P A^T + Q`` with ``Q = diag(T^2 Q_vG, Q_wb, Q_wd)``. Eq 2.34 is this
with the cross-covariances of orientation and offset dropped (``A = 0``
bookkeeping of the thesis); the full form is kept here because it is what
makes the offset observable from the inclination and heading updates. The
nominal state is integrated at every sample; the covariance is carried over
all samples since the previous update in one step (:meth:`propagate`), so
updates can run at a fraction of the IMU rate (``ori_update_every``).

Measurements (eqs 2.31-2.33, in this sign convention)::

    z_incl = Z_A - Z_G = [Z x] theta + v_incl         Z_A = (y_A - a-)/|y_A - a-|
    z_mag  = H_M - H_G = [H x] theta + d + v_mag      H_M = y_M/|m| - d-

with ``Z_G = R^T e_z`` and ``H_G = R^T h_G``; the noise variances are
eq 2.35 without the gyroscope term (which enters through ``Q``):
``(c_a^2 Q_a + Q_wa + Q_vA) / g^2`` and ``Q_vM / |m|^2``.

Adaptive motion variance (``body.acc_adapt_gain`` ``k``, default 0:
off). One ``Q_wa`` cannot suit a still sensor and a walking trunk (1-3
m/s^2 at 0.9-1.8 Hz, read as 6-17 deg of tilt). As eq 2.12 raises the
disturbance's driving noise with the measured change of the field, the
motion term here is raised with the measured motion:
``Q_wa + k var(y_A - g Z-)``, the variance about the running mean over
``acc_adapt_tau_s`` (first-order averages at the update rate; a tilt error
``g theta`` is slow and goes into the mean, so it does not weight down the
very updates that remove it). At rest the variance is the accelerometer
noise and the filter is the thesis's; under body motion the
inclination is weighted down in proportion to the acceleration that would
be read as tilt, and the gyroscope carries the orientation through it. The
``-a x theta / g`` term of the first row of eq 2.32 is dropped: the
acceleration is predicted in the sensor frame (eq 2.5) and does not depend on
the current orientation error; it is below 1 % of ``Z`` for human motion.

Both updates go through ``ekf.KalmanUpdate`` (innovation, variance, gate,
gain, Joseph form, health flags), each in a class of its own
(``orientation_updates.Inclination``, ``orientation_updates.Compass``, which
also learns ``|m|`` and the dip and adapts the disturbance noise); the filter
keeps the state, its prediction and the corrections. Nothing here allocates after
``__init__``.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import EKF_OK, CovariancePredict
from coiltrack.firmware.estimate.layout import BIAS, DIST, ORIENTATION_LAYOUT, THETA
from coiltrack.firmware.estimate.orientation_updates import Compass, Inclination
from coiltrack.firmware.estimate.strapdown import Strapdown
from coiltrack.firmware.linalg import rotvec_from_matrix

N = ORIENTATION_LAYOUT.n

# orientation-filter health flags (bit field, beside the ekf flags)
ORI_NOT_INITIALISED = 64
ORI_FREEFALL = 128          # accelerometer norm far from g: inclination update skipped
ORI_LEARNING = 256          # compass sample used to learn |m| and the dip, not as a compass

#: the prediction's sums since the last covariance propagation (``OrientationFilter.sums``): the
#: time, the sum of the squared steps, the disturbance's correlation and driving noise composed
#: (``propagate``), the acceleration's last correlation ``c_a`` (eq 2.5) and the time since the
#: last inclination update (``Inclination.observe``); the compiled core keeps them in the same
#: array (``core/include/ct_fusimu.h`` ``CT_OA_*``)
SUM_DT, SUM_DT2, SUM_CD, SUM_QD, SUM_CA, SUM_INCL_DT = range(6)

#: what one sample on the compiled core did (``core/src/fusimu.c ct_ori_sample``, ``CT_OS_*``): a
#: prediction step; an update round; the inclination's Kalman update (its ekf flags at bit 8) or free
#: fall; the compass's update (its flags at bit 12); the covariance propagations (their number at bit 16)
OS_PREDICTED, OS_ROUND, OS_ACC, OS_FREEFALL, OS_MAG = 1, 2, 4, 8, 16

#: ``OrientationFilter.state`` (int64): initialised (0/1), the time (us), the prediction steps, the
#: last inclination and compass flags; the compiled one-call IMU sample updates them in place
#: (``core/include/ct_fusimu.h`` ``CT_OF_*``)
OF_INIT, OF_T, OF_STEPS, OF_ACCF, OF_MAGF, OF_N = range(6)


def _state_int(i: int):
    """A property reading and writing entry ``i`` of ``self._stv`` (an int64 state array's view)."""
    def fset(self, v) -> None:
        self._stv[i] = v
    return property(lambda self: self._stv[i], fset)


def _state_bool(i: int):
    """A bool property kept as 0/1 in entry ``i`` of ``self._stv``."""
    def fset(self, v) -> None:
        self._stv[i] = 1 if v else 0
    return property(lambda self: self._stv[i] != 0, fset)


class OrientationParams:
    """Noise and model parameters of the ch. 2 filter (SI units, per sample
    unless stated), with no defaults of their own: :meth:`from_config`."""

    @classmethod
    def from_config(cls, cfg=None, **overrides) -> "OrientationParams":
        """The parameters of ``cfg`` (default ``FirmwareConfig()``), with ``overrides``."""
        if cfg is None:
            from coiltrack.firmware.config import FirmwareConfig
            cfg = FirmwareConfig()
        kw = dict(
            gyro_noise=cfg.imu.imu_gyro_sigma, gyro_bias_rw=cfg.imu.imu_gyro_bias_rw,
            gyro_bias_sigma=cfg.imu.imu_gyro_bias_sigma, acc_noise=cfg.imu.imu_acc_sigma,
            acc_motion_sigma=cfg.orientation.acc_motion_sigma, acc_corr_time_s=cfg.orientation.acc_corr_time_s,
            mag_noise=cfg.pulse.mag_sigma_t / cfg.orientation.earth_field_t, dist_corr=cfg.orientation.dist_corr, dist_sigma=cfg.orientation.dist_sigma,
            dist_norm_gain=cfg.orientation.dist_norm_gain, dist_dip_gain=cfg.orientation.dist_dip_gain, dist_smoothing=cfg.orientation.dist_smoothing,
            gravity=math.sqrt(sum(v * v for v in cfg.imu.gravity_mps2)), gate_probability=cfg.fusion.fusion_gate_probability,
            theta0_sigma=cfg.orientation.theta0_sigma, freefall_tolerance=cfg.orientation.freefall_tolerance,
            mag_learn_samples=cfg.orientation.mag_learn_samples, acc_adapt_gain=cfg.body.acc_adapt_gain,
            acc_adapt_tau_s=cfg.body.acc_adapt_tau_s, compass_heading_only=cfg.body.compass_heading_only)
        kw.update(overrides)
        return cls(**kw)

    def __init__(self, *, gyro_noise, gyro_bias_rw, gyro_bias_sigma, acc_noise, acc_motion_sigma, acc_corr_time_s,
                 mag_noise, dist_corr, dist_sigma, dist_norm_gain, dist_dip_gain, dist_smoothing, gravity,
                 gate_probability, theta0_sigma, freefall_tolerance, mag_learn_samples, acc_adapt_gain=0.0,
                 acc_adapt_tau_s=1.0, compass_heading_only=False):
        self.gyro_noise = float(gyro_noise)            # rad/s rms per sample (Q_vG)
        self.gyro_bias_rw = float(gyro_bias_rw)        # rad/s/sqrt(s) (Q_wb)
        self.gyro_bias_sigma = float(gyro_bias_sigma)  # rad/s, initial offset uncertainty
        self.acc_noise = float(acc_noise)              # m/s^2 rms per sample (Q_vA)
        self.acc_motion_sigma = float(acc_motion_sigma)  # m/s^2, driving noise of eq 2.5 (Q_wa)
        self.acc_corr_time_s = float(acc_corr_time_s)  # c_a = exp(-T / tau_a)
        self.mag_noise = float(mag_noise)              # rms per sample, in units of |earth field| (Q_vM)
        self.dist_corr = float(dist_corr)              # c_d, per sample (eq 2.7)
        self.dist_sigma = float(dist_sigma)            # floor of sigma_d (eq 2.12)
        self.dist_norm_gain = float(dist_norm_gain)    # sigma_m of eq 2.12
        self.dist_dip_gain = float(dist_dip_gain)      # sigma_phi of eq 2.12 (per rad)
        self.dist_smoothing = float(dist_smoothing)    # low-pass weight of norm and dip before eq 2.12
        self.gravity = float(gravity)
        self.gate_probability = float(gate_probability)
        self.theta0_sigma = float(theta0_sigma)        # rad, initial orientation uncertainty
        self.freefall_tolerance = float(freefall_tolerance)  # relative |y_A| deviation from g
        self.mag_learn_samples = int(mag_learn_samples)    # compass samples averaged for |m| and dip
        self.acc_adapt_gain = float(acc_adapt_gain)    # k of the motion variance k <|y_A - g Z|^2> (0: off)
        self.acc_adapt_tau_s = float(acc_adapt_tau_s)  # s, averaging time of <|y_A - g Z|^2>
        self.compass_heading_only = bool(compass_heading_only)  # the compass corrects the heading only


def _triad(ax, ay, az, mx, my, mz):
    """TRIAD (eq 2.1): the rows ``X`` (magnetic north, horizontal), ``Y = Z x m`` (west) and ``Z``
    (up, from the specific force) of the sensor-to-global rotation, sensor frame, and ``|m|``;
    ``(xx, xy, xz, yx, yy, yz, zx, zy, zz, |m|)``, or None when the samples give no frame (a zero
    or non-finite sample, or the field along gravity)."""
    an = math.sqrt(ax * ax + ay * ay + az * az)
    mn = math.sqrt(mx * mx + my * my + mz * mz)
    if not (an > 0.0 and mn > 0.0 and math.isfinite(an) and math.isfinite(mn)):
        return None
    zx, zy, zz = ax / an, ay / an, az / an
    yx, yy, yz = zy * mz - zz * my, zz * mx - zx * mz, zx * my - zy * mx
    yn = math.sqrt(yx * yx + yy * yy + yz * yz)
    if not yn > 1e-6 * mn:
        return None                            # field along gravity: no heading
    yx, yy, yz = yx / yn, yy / yn, yz / yn
    xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
    return xx, xy, xz, yx, yy, yz, zx, zy, zz, mn


class _OriState:
    """:class:`OrientationFilter`'s per-sample state as attributes, kept in its ``state`` array."""

    initialized = _state_bool(OF_INIT)
    t_us = _state_int(OF_T)                 # the time of the last sample (us)
    steps = _state_int(OF_STEPS)            # prediction steps (every 64th orthonormalises R)
    last_acc_flags = _state_int(OF_ACCF)
    last_mag_flags = _state_int(OF_MAGF)
    state_view = property(lambda self: self._stv)     # ``state`` as a memoryview (the tracker's tests read it)


class OrientationFilter(_OriState):
    """Complementary orientation Kalman filter of thesis ch. 2 (see module); ``core``: the
    numeric core (``coiltrack.firmware.core.Core``), chosen at composition."""

    def __init__(self, params: OrientationParams, core=_DEFAULT_CORE):
        self.prm = params
        self.P = np.zeros((N, N))
        self.pred = CovariancePredict(N, core)
        self.incl = Inclination(params, core)   # the inclination update (eqs 2.20, 2.23)
        self.compass = Compass(params, core)    # the compass update and its learning (eqs 2.8-2.12, 2.21, 2.24)
        # nominal state
        self.R = np.eye(3)
        self.bias = np.zeros(3)          # gyroscope offset, rad/s, sensor frame
        self.dist = np.zeros(3)          # magnetic disturbance, normalised, sensor frame
        self.acc = np.zeros(3)           # acceleration a+ (eq 2.5), sensor frame
        self._Rv = memoryview(self.R)
        self.bias_v = memoryview(self.bias)   # the gyroscope bias as Python floats (the tracker reads it)
        self._dv = memoryview(self.dist)
        self._av = memoryview(self.acc)
        self._sd = Strapdown(core)       # the attitude step (estimate.strapdown)
        self._T = np.zeros((3, 3))
        self._O = np.zeros((3, 3))       # orthonormalisation scratch
        self._Rc = np.eye(3)             # orientation when the covariance was last propagated
        self._Rcv = memoryview(self._Rc)
        self.sums = np.zeros(6)          # the prediction's sums (SUM_*)
        self._s = memoryview(self.sums)
        self._s[SUM_CD] = 1.0
        self._Av = memoryview(self.pred.A)
        self._Qv = memoryview(self.pred.Q)
        # the per-sample state (OF_*: initialised, time, steps, the last updates' flags) in one int64
        # array a compiled kernel bound once updates in place; read and written through the properties
        self.state = np.zeros(OF_N, dtype=np.int64)
        self._stv = memoryview(self.state)
        self.reacquired = 0              # orientations found again after a break (reacquire)
        self._Pv = memoryview(self.P)
        self._Tv = memoryview(self._T)
        # the numeric core of propagate, bound once here (coiltrack.firmware.core:
        # core/src/orientation.c, the same blocks and the compiled covariance prediction)
        self._ck = None
        ext = core.ext
        if ext is not None and self.pred.core == "compiled":
            self._ck = ext.OriProp(N, THETA.start, BIAS.start, DIST.start, self.R, self._Rc, self.pred.A,
                                   self.pred.Q, self.P, self.pred._T)
            self.propagate = self._propagate_compiled
            # core/src/fusimu.c ct_ori_predict: predict's state step and sums
            assert (SUM_DT, SUM_DT2, SUM_CD, SUM_QD, SUM_CA, SUM_INCL_DT, 6) == (0, 1, 2, 3, 4, 5, ext.FUS_OA_N)
            self._ckp = ext.OriPred(self.R, self.bias, self.dist, self.acc, self.sums, params.dist_corr,
                                    params.acc_corr_time_s)
            self.predict = self._predict_compiled
            self._bind_updates(ext, params)

    def _bind_updates(self, ext, p: OrientationParams) -> None:
        """The compiled measurement parts of the two updates (``core/src/fusimu.c``
        ``ct_ori_incl_begin``, ``ct_ori_compass_fill``, ``ct_ori_apply``, ``ct_ori_post_acc``), bound
        once to the filter's and its updates' buffers; the Kalman update between them stays
        ``ekf.KalmanUpdate`` (compiled too)."""
        iu, cu, c = self.incl.upd, self.compass.upd, self.compass
        self._cku = ext.OriUpd(N, THETA.start, BIAS.start, DIST.start, self.R, self._Rc, self.bias, self.dist,
                               self.acc, self.sums, iu.y, iu.H, iu.R, iu.dx, cu.y, cu.H, cu.R, cu.dx, c.h_g, c.state,
                               p.gravity, p.freefall_tolerance, p.acc_noise, p.acc_motion_sigma, p.acc_adapt_gain,
                               p.mag_noise, p.dist_sigma, p.dist_norm_gain, p.dist_dip_gain, p.dist_smoothing,
                               p.compass_heading_only)
        self.update_acc = self._update_acc_compiled
        self.update_mag = self._update_mag_compiled

    # ------------------------------------------------------------ init
    def initialize(self, t_us: int, ax, ay, az, mx, my, mz) -> bool:
        """TRIAD from one accelerometer and one magnetometer sample (sensor
        frame): ``Z`` (up) from the specific force, ``Y = Z x m`` (west),
        ``X = Y x Z`` (magnetic north, horizontal); eq 2.1 puts them in the
        rows of ``R``. The field magnitude and dip learned here define
        ``|m| = 1`` and ``h_G`` (eqs 2.8-2.10)."""
        fr = _triad(ax, ay, az, mx, my, mz)
        if fr is None:
            return False
        xx, xy, xz, yx, yy, yz, zx, zy, zz, mn = fr
        self._set_R(fr)
        # field in the global frame: (north, 0, up) components
        hn = (xx * mx + xy * my + xz * mz) / mn
        hu = (zx * mx + zy * my + zz * mz) / mn
        self.compass.start(hn, hu, mn)
        self.bias.fill(0.0)
        self.dist.fill(0.0)
        self.acc.fill(0.0)
        self.incl.reset()
        p = self.prm
        self.P.fill(0.0)
        Pv = self._Pv
        for i in range(3):
            Pv[THETA.start + i, THETA.start + i] = p.theta0_sigma ** 2
            Pv[BIAS.start + i, BIAS.start + i] = p.gyro_bias_sigma ** 2
            Pv[DIST.start + i, DIST.start + i] = p.dist_sigma ** 2
        self.t_us = t_us
        np.copyto(self._Rc, self.R)
        self._restart_sums()
        self._s[SUM_INCL_DT] = 0.0       # (the inclination restarts: Inclination.reset)
        self.initialized = True
        return True

    def _restart_sums(self) -> None:
        """No prediction since the covariance was last propagated."""
        s = self._s
        s[SUM_DT] = s[SUM_DT2] = s[SUM_QD] = 0.0
        s[SUM_CD] = 1.0

    def _set_R(self, fr) -> None:
        """Write the rows ``X, Y, Z`` of a :func:`_triad` frame into ``R`` (eq 2.1)."""
        R = self._Rv
        R[0, 0], R[0, 1], R[0, 2] = fr[0], fr[1], fr[2]
        R[1, 0], R[1, 1], R[1, 2] = fr[3], fr[4], fr[5]
        R[2, 0], R[2, 1], R[2, 2] = fr[6], fr[7], fr[8]

    def reacquire(self, t_us: int, ax, ay, az, mx, my, mz) -> bool:
        """After a break in the IMU stream (the sensor turned while nothing
        was integrated): the orientation again by TRIAD from one accelerometer
        and one magnetometer sample, as :meth:`initialize`, in the frame the
        filter already has (``h_G``, ``|m|`` learned, eqs 2.8-2.10, kept). The
        gyroscope offset (eq 2.3) is kept with its variance grown by the random
        walk over the break (``sigma_wb^2 dt``, at most its initial variance);
        ``theta`` restarts with ``theta0_sigma``, its cross-covariances zero.
        Returns False (nothing changed) when the samples give no frame."""
        fr = _triad(ax, ay, az, mx, my, mz)
        if fr is None:
            return False
        self.propagate()
        self._set_R(fr)
        p = self.prm
        dt = max(0, t_us - self.t_us) * 1e-6
        Pv = self._Pv
        t0, b0 = THETA.start, BIAS.start
        grow = p.gyro_bias_rw * p.gyro_bias_rw * dt
        cap = p.gyro_bias_sigma ** 2
        for i in range(N):
            for j in range(3):
                Pv[t0 + j, i] = 0.0
                Pv[i, t0 + j] = 0.0
        for i in range(3):
            Pv[t0 + i, t0 + i] = p.theta0_sigma ** 2
            v = Pv[b0 + i, b0 + i] + grow
            Pv[b0 + i, b0 + i] = v if v < cap else cap
        self.dist.fill(0.0)
        self.acc.fill(0.0)
        self.t_us = t_us
        np.copyto(self._Rc, self.R)
        self._restart_sums()
        self.initialized = True
        self.reacquired += 1
        return True

    def lose(self) -> None:
        """The IMU stream broke off: what the gyroscopes missed cannot be integrated; the
        orientation is to be found again (:meth:`reacquire`)."""
        self.initialized = False

    @property
    def learning(self) -> bool:
        """The compass samples are still learning ``|m|`` and the dip (eqs 2.8-2.10)."""
        return self.compass.learning

    # the parts' state (read)
    upd_acc = property(lambda self: self.incl.upd)
    upd_mag = property(lambda self: self.compass.upd)
    acc_motion_ms = property(lambda self: self.incl.motion_ms)    # variance of y_A - g Z-, m^2/s^4
    h_g = property(lambda self: self.compass.h_g)                 # earth field direction, global frame
    m_ref = property(lambda self: self.compass.m_ref)             # |earth field|, T

    def set_bias(self, bx, by, bz) -> None:
        self.bias[0], self.bias[1], self.bias[2] = bx, by, bz

    # --------------------------------------------------------- predict
    def predict(self, t_us: int, wx, wy, wz) -> None:
        """Strapdown step to ``t_us`` with the gyroscope sample (rad/s, sensor
        frame): the nominal orientation, offset and disturbance now; the
        covariance when the next update needs it (:meth:`propagate`), over all
        the steps since the previous one at once."""
        dt = (t_us - self.t_us) * 1e-6
        self.t_us = t_us
        if not dt > 0.0:
            return
        p = self.prm
        b = self.bias_v
        self._sd.rotate(self.R, (wx - b[0]) * dt, (wy - b[1]) * dt, (wz - b[2]) * dt)    # eq 2.27
        self.steps += 1
        if self.steps & 63 == 0:
            self._orthonormalize()
        cd = p.dist_corr
        d = self._dv
        d[0] *= cd
        d[1] *= cd
        d[2] *= cd
        # eq 2.5: a- = c_a a+ (c_a = 0: the acceleration is white, a- = 0)
        ca = math.exp(-dt / p.acc_corr_time_s) if p.acc_corr_time_s > 0.0 else 0.0
        a = self._av
        a[0] *= ca
        a[1] *= ca
        a[2] *= ca
        s = self._s
        s[SUM_CA] = ca
        s[SUM_DT] += dt
        s[SUM_INCL_DT] += dt
        s[SUM_DT2] += dt * dt
        s[SUM_CD] *= cd
        s[SUM_QD] = s[SUM_QD] * cd * cd + self.compass.qwd

    def _predict_compiled(self, t_us: int, wx, wy, wz) -> None:
        """:meth:`predict` on the compiled core (``ct_ori_predict``: the attitude step, the decays and
        the sums in one call; the periodic orthonormalisation here, on ``R`` alone)."""
        dt = (t_us - self.t_us) * 1e-6
        self.t_us = t_us
        if not dt > 0.0:
            return
        self._ckp.predict(dt, wx, wy, wz, self.compass.qwd)
        self.steps += 1
        if self.steps & 63 == 0:
            self._orthonormalize()

    def sample_done(self, t_us: int, r: int) -> None:
        """The bookkeeping of a sample the compiled core ran (``ct_ori_sample``, or its halves; the ``OS_*``
        bits ``r``): time, steps (the orthonormalisation of :meth:`predict`), counts, flags (in ``state``)."""
        s = self._stv
        s[OF_T] = t_us
        s[OF_STEPS] += r & OS_PREDICTED
        if r & OS_PREDICTED and s[OF_STEPS] & 63 == 0:
            self._orthonormalize()       # (after ct_ori_sample_begin: its caller finishes the sample)
        if r & OS_ROUND:
            if r & (OS_FREEFALL | OS_ACC):
                s[OF_ACCF] = ORI_FREEFALL if r & OS_FREEFALL else self.incl.upd.counted((r >> 8) & 15)
            self.pred.set_count(self.pred.count + (r >> 16))
            if r & OS_MAG:
                s[OF_MAGF] = self.compass.upd.counted((r >> 12) & 15)

    def propagate(self) -> None:
        """Covariance over the steps since the last call (eq 2.28 and the
        offset / disturbance rows, composed):

        ``theta_N = Gamma theta_0 - T_N (I + Gamma) / 2 b``, ``Gamma = R_N^T R_0``
        (the sensor-frame error turned with the sensor; trapezoidal mean of
        the turn over the interval for the offset term), ``d_N = c_d^N d_0``;
        ``Q`` the sums of the per-step noises (``sum (sigma_G T)^2``,
        ``sigma_wb^2 T_N``, ``sum c_d^2k Q_wd``)."""
        s = self._s
        if s[SUM_DT] <= 0.0:
            return
        p = self.prm
        R = self._Rv
        Rc = self._Rcv
        A = self._Av
        t0 = THETA.start
        b0 = BIAS.start
        h = -0.5 * s[SUM_DT]
        for i in range(3):
            for j in range(3):
                g = R[0, i] * Rc[0, j] + R[1, i] * Rc[1, j] + R[2, i] * Rc[2, j]
                A[t0 + i, t0 + j] = g
                A[t0 + i, b0 + j] = h * g + (h if i == j else 0.0)
            A[DIST.start + i, DIST.start + i] = s[SUM_CD]
        Q = self._Qv
        qt = p.gyro_noise * p.gyro_noise * s[SUM_DT2]
        qb = p.gyro_bias_rw * p.gyro_bias_rw * s[SUM_DT]
        qd = s[SUM_QD]
        for i in range(3):
            Q[t0 + i, t0 + i] = qt
            Q[b0 + i, b0 + i] = qb
            Q[DIST.start + i, DIST.start + i] = qd
        self.pred.predict(self.P)
        np.copyto(self._Rc, self.R)
        self._restart_sums()

    def _propagate_compiled(self) -> None:
        """:meth:`propagate` on the compiled core (``ct_orientation_propagate``)."""
        s = self._s
        if s[SUM_DT] <= 0.0:
            return
        p = self.prm
        self._ck.propagate(s[SUM_DT], s[SUM_DT2], s[SUM_CD], s[SUM_QD], p.gyro_noise, p.gyro_bias_rw)
        self.pred.after_predict(self.P)
        self._restart_sums()

    def _orthonormalize(self) -> None:
        """``R <- R (3 I - R^T R) / 2`` (one Newton step of the polar factor)."""
        R = self._Rv
        Tv = self._Tv
        for i in range(3):
            for j in range(3):
                rtr = R[0, i] * R[0, j] + R[1, i] * R[1, j] + R[2, i] * R[2, j]
                Tv[i, j] = (1.5 if i == j else 0.0) - 0.5 * rtr
        np.matmul(self.R, self._T, out=self._O)
        np.copyto(self.R, self._O)

    # --------------------------------------------------------- updates
    def _apply(self, dx) -> None:
        self._sd.rotate(self.R, dx[THETA.start], dx[THETA.start + 1], dx[THETA.start + 2])
        np.copyto(self._Rc, self.R)      # the error is reset at the corrected orientation
        b = self.bias_v
        d = self._dv
        for i in range(3):
            b[i] += dx[BIAS.start + i]
            d[i] += dx[DIST.start + i]

    def update_acc(self, ax, ay, az) -> int:
        """Inclination update (eqs 2.20, 2.23) with an accelerometer sample
        (m/s^2, sensor frame; :class:`orientation_updates.Inclination`). Returns ekf health
        flags (``ORI_FREEFALL`` when ``|y_A|`` is far from ``g``: no inclination information)."""
        p = self.prm
        a = self._av
        g = p.gravity
        s = self._s
        self.incl.observe(self._Rv, ax, ay, az, s[SUM_INCL_DT])
        s[SUM_INCL_DT] = 0.0
        vx, vy, vz = ax - a[0], ay - a[1], az - a[2]
        vn = math.sqrt(vx * vx + vy * vy + vz * vz)
        if not (abs(vn - g) <= p.freefall_tolerance * g):
            self.last_acc_flags = ORI_FREEFALL
            self._post_acc(ax, ay, az)
            return ORI_FREEFALL
        self.propagate()
        flags = self.incl.update(self._Rv, self.P, vx, vy, vz, vn, s[SUM_CA])
        if flags == EKF_OK:
            self._apply(self.incl.upd._dxv)
        self._post_acc(ax, ay, az)
        self.last_acc_flags = flags
        return flags

    def _update_acc_compiled(self, ax, ay, az) -> int:
        """:meth:`update_acc` on the compiled core (``OriUpd``: the free-fall test with the
        inclination's measurement, and after the update the correction and ``a+``)."""
        s = self._s
        self.incl.observe(self._Rv, ax, ay, az, s[SUM_INCL_DT])
        s[SUM_INCL_DT] = 0.0
        if not self._cku.acc_begin(ax, ay, az, self.incl.motion_ms):
            self.last_acc_flags = ORI_FREEFALL
            return ORI_FREEFALL
        self.propagate()                 # (the measurement does not depend on P)
        flags = self.incl.upd.update(self.P)
        self._cku.acc_end(flags == EKF_OK)
        self.last_acc_flags = flags
        return flags

    def _post_acc(self, ax, ay, az) -> None:
        R = self._Rv
        g = self.prm.gravity
        a = self._av
        a[0] = ax - g * R[2, 0]
        a[1] = ay - g * R[2, 1]
        a[2] = az - g * R[2, 2]

    def update_mag(self, mx, my, mz) -> int:
        """Compass update (eqs 2.21, 2.24) with a magnetometer sample (T,
        sensor frame) taken outside any coil pulse (:class:`orientation_updates.Compass`:
        first the learning of ``|m|`` and the dip; the disturbance driving noise adapted from
        the change of norm and dip, eq 2.12)."""
        c = self.compass
        if c.learn(self._Rv, mx, my, mz):
            self.last_mag_flags = ORI_LEARNING
            return ORI_LEARNING
        self.propagate()
        flags = c.update(self._Rv, self._dv, self.P, mx, my, mz)
        if flags == EKF_OK:
            self._apply(c.upd._dxv)
        self.last_mag_flags = flags
        return flags

    def _update_mag_compiled(self, mx, my, mz) -> int:
        """:meth:`update_mag` on the compiled core (``OriUpd``: the compass's measurement, and after
        the update its correction)."""
        c = self.compass
        if c.learn(self._Rv, mx, my, mz):
            self.last_mag_flags = ORI_LEARNING
            return ORI_LEARNING
        self._cku.mag_fill(mx, my, mz)   # (the measurement does not depend on P)
        self.propagate()
        flags = c.upd.update(self.P)
        if flags == EKF_OK:
            self._cku.mag_apply()
        self.last_mag_flags = flags
        return flags

    # ----------------------------------------------------------- output
    def theta_covariance_global(self, out) -> None:
        """Covariance of the orientation error expressed in the global frame,
        ``R P[THETA, THETA] R^T`` (``R_true = exp([R theta]x) R``), into ``out`` (3x3)."""
        self.propagate()
        R = self._Rv
        P = self._Pv
        t0 = THETA.start
        for i in range(3):
            for j in range(3):
                acc = 0.0
                for k in range(3):
                    rik = R[i, k]
                    for m in range(3):
                        acc += rik * P[t0 + k, t0 + m] * R[j, m]
                out[i, j] = acc

    def inclination_error(self, R_true) -> float:
        """Angle between the estimated and a true orientation (rad), for tests."""
        R = self.R
        M = R_true.T @ R
        x, y, z = rotvec_from_matrix(*M.reshape(9))
        return math.sqrt(x * x + y * y + z * z)
