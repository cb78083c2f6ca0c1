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
    GAIN 27  n_coils  1   :class:`CoilGainEKF` only: each coil's gain error, a constant

Coil gains (:class:`CoilGainEKF`, ``[adaptive] coil_gain_sigma`` > 0). The pulse model becomes
``y = (1 + g_c) I R^T B_c(p)`` (eq 5 with the coil's true current ``(1 + g_c) I``): a driver whose
current sense carries a static gain error (invisible in the current it reports) or a coil whose
field differs from the model by a constant factor. The field-model term of ``R`` is white, so it
averages away over repeated pulses of one coil, which a constant error does not: a policy that
leans on one coil takes its bias into the pose. The nominal gains scale the current the update
predicts with, the error column of ``H`` for ``g_c`` is ``I h_c`` (the derivative of eq 5), the
gains are constant (identity transition, no process noise) and kept through a restart of the pose
(their prior variance restored); ``single_coil_update.CoilGains``.

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

The compiled core (``coiltrack.firmware.core``, chosen once at construction by the ``core``
argument): ``core/src/single_coil.c`` follows :meth:`SchepersEKF._advance` (with ``_step``,
``_build_F``, ``_orthonormalize``), ``_predict_ahead``, ``_take_clone_now``, ``_back_clone_now``,
``release_clone``, ``core_transition``, ``pose_values`` and ``_inject`` operation by operation; the products
the Python hands to BLAS (``F P F^T``) are summed there in index order with ``F``'s structural
zeros skipped, equal to rounding. A subclass that changes the dynamics (overrides ``_step``,
``_build_F``, ``_accel``, ``_advance`` or ``_fill_q``) runs them in Python.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NONFINITE, EKF_NOT_PD
from coiltrack.firmware.estimate.layout import (ACC, GYR, ORI, POS, POSE_ORI, POSE_POS, SCHEPERS_CORE as CORE,
                                               SCHEPERS_LAYOUT, VEL, schepers_layout)
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.strapdown import Strapdown, integrate_pv, to_nav, transition_sensor, transition_static
from coiltrack.firmware.estimate.clones import PoseClones
from coiltrack.firmware.estimate.single_coil_update import CoilGains, CoilMeasurement, SingleCoilUpdate
from coiltrack.firmware.rotation import quat_tuple

__all__ = ["SCHEPERS_LAYOUT", "SchepersEKF", "CoilGainEKF", "EKF_NO_STATE", "filter_class"]

#: the methods whose compiled form is bound only where a subclass keeps them all
_DYNAMICS = ("_step", "_build_F", "_accel", "_advance", "_fill_q", "_predict_ahead")

#: the filter is not initialised (no pose yet): nothing done
EKF_NO_STATE = 1024

_GRAVITY = (0.0, 0.0, -9.81)


N_CORE = CORE.stop


class _UpdateCounts:
    """The last update's nominal and used NIS and the updates rejected and applied of a
    :class:`SchepersEKF`, in arrays (``ust``, ``ucnt``) a compiled window update bound once writes in
    place (``track.single_coil_window.window_update``), read and written through properties under
    the attributes' names."""

    def _alloc_counts(self) -> None:
        self.ust = np.zeros(2)
        self.ucnt = np.zeros(2, dtype=np.int64)
        self._ustv = memoryview(self.ust)
        self._ucntv = memoryview(self.ucnt)

    def _set_nis_nominal(self, v: float) -> None:
        self._ustv[0] = v

    def _set_nis(self, v: float) -> None:
        self._ustv[1] = v

    def _set_rejected(self, v: int) -> None:
        self._ucntv[0] = v

    def _set_updates(self, v: int) -> None:
        self._ucntv[1] = v

    #: the last update's first-pass NIS with ``r_scale = 1`` (for the monitor)
    nis_nominal = property(lambda self: self._ustv[0], _set_nis_nominal)
    #: the last update's NIS, the one gated
    nis = property(lambda self: self._ustv[1], _set_nis)
    #: updates rejected (gated or failed)
    rejected = property(lambda self: self._ucntv[0], _set_rejected)
    #: updates applied
    updates = property(lambda self: self._ucntv[1], _set_updates)


class SchepersEKF(_UpdateCounts):
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
        root = math.sqrt(cfg.imu.imu_rate_hz)
        kw = dict(n_clones=2, gravity=cfg.imu.gravity_mps2, acc_noise=cfg.imu.imu_acc_sigma / root,
                  gyr_noise=cfg.imu.imu_gyro_sigma / root, acc_bias_rw=cfg.imu.imu_acc_bias_rw,
                  gyr_bias_rw=cfg.imu.imu_gyro_bias_rw, pos_noise=cfg.adaptive.adaptive_pos_noise,
                  gate_probability=cfg.adaptive.nis_gate_probability, iterations=cfg.adaptive.single_coil_iterations)
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
        self.g = np.array(gravity, dtype=float).reshape(3)
        self.acc_noise = float(acc_noise)
        self.gyr_noise = float(gyr_noise)
        self.acc_bias_rw = float(acc_bias_rw)
        self.gyr_bias_rw = float(gyr_bias_rw)
        self.pos_noise = float(pos_noise)
        self.iterations = max(1, int(iterations))
        self._alloc_state(nx)
        self._alloc_propagation(nx, core)
        # update: the shared shape (``single_coil_update``), plus the nominal NIS for the monitor
        self._coil_update = SingleCoilUpdate(nx, gate_probability, self.iterations, core)
        self.upd = self._coil_update.upd
        self._meas = CoilMeasurement()
        self._run_update = self._coil_update.run      # CoilGainEKF: with its gains
        self.nis = self.nis_nominal = 0.0
        self.kernels = "python"        # where its own dynamics run (its update reports its own core)
        if core.ext is not None:
            self._bind_compiled(core.ext)

    def _bind_compiled(self, ext) -> None:
        """Bind the compiled kernels (``core/src/single_coil.c``) in place of the reference
        methods of the same contract, once; the dynamics only where this class's are run."""
        cls = type(self)
        if all(getattr(cls, name) is getattr(SchepersEKF, name) for name in _DYNAMICS):
            ck = _compiled(self, ext)
            self._ck = ck
            self._advance, self._take_clone_now, self.release_clone = ck.propagate, ck.take_clone, ck.release_clone
            self._back_clone_now = ck.back_clone
            self._predict_ahead, self.core_transition, self.pose_values = ck.predict_pose, ck.build_F, ck.pose_values
            if cls._inject is SchepersEKF._inject:
                self._inject = ck.inject
            self.kernels = "compiled"

    def _alloc_state(self, nx: int) -> None:
        """The nominal state, the covariance, the last inputs and the clones."""
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
        self._alloc_counts()
        # last inputs (offsets removed), for prediction ahead
        self.f = np.zeros(3)
        self.w = np.zeros(3)
        self._acc_prev = np.zeros(3)
        self._gyr_prev = np.zeros(3)
        self._have_prev = False
        # clones (``clones.PoseClones``; their arrays read here under the old names)
        self.clones = PoseClones(self.layout, self.n_clones)
        self.clone_p, self.clone_R, self.clone_t = self.clones.p, self.clones.R, self.clones.t
        self.clone_due, self.clone_taken = self.clones.due, self.clones.taken

    def _alloc_propagation(self, nx: int, core) -> None:
        """The buffers of the propagation and of the prediction ahead."""
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
        self._fref_a = np.array(self._fref)
        self._steps = 0
        # 0-d operands (a Python float in a ufunc would become a new 0-d array)
        self._k0 = np.zeros(())
        self._half = np.full((), 0.5)
        # prediction-ahead buffers (core block only)
        self._Fc = np.eye(N_CORE)
        self._Fct = self._Fc.T
        self._Fcv = memoryview(self._Fc)
        self._Pc = np.zeros((N_CORE, N_CORE))
        self._Pc_diag = self._Pc.reshape(-1)[::N_CORE + 1]
        self._Tc = np.zeros((N_CORE, N_CORE))
        self._qc = np.zeros(N_CORE)
        self._TPb, self._TPTb = np.zeros((6, nx)), np.zeros((6, 6))      # the compiled back_clone's scratch

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
        self.clones.clear()
        self.initialized = True
        if self.t_us is None:
            self.t_us = int(t_us)

    def reset(self) -> None:
        """Forget the pose (keep the inertial integration running)."""
        self.initialized = False
        self.P.fill(0.0)
        self.clones.clear()

    # ------------------------------------------------------------ clones
    def schedule_clone(self, k: int, t_us: int) -> None:
        """Clone the pose at ``t_us`` (the mid time of pulse slot k's used samples)."""
        self.clones.schedule(k, t_us)
        if self.t_us is not None and self.t_us >= t_us:
            self._take_clone(k)

    def _take_clone(self, k: int) -> None:
        self._take_clone_now(k, self.initialized)

    def _take_clone_now(self, k: int, initialized: bool) -> None:
        self.clones.take(k, self.P, self.p, self.R, initialized)

    def back_clone(self, k: int, dt: float, G) -> None:
        """Clone k as the pose ``dt`` seconds before the filter's time, predicted backwards
        from the current state (``clones.PoseClones.back``; ``G`` = ``R_now^T R_then`` from
        the gyroscope). For an amplitude measured before the filter was started (the
        acquisition burst): the update then corrects the present state, velocity included."""
        self._back_clone_now(k, dt, G, self.initialized)

    def _back_clone_now(self, k: int, dt: float, G, initialized: bool) -> None:
        self.clones.back(k, dt, G, self.P, self.p, self.v, self.R, initialized)

    def release_clone(self, k: int) -> None:
        self.clones.release(k, self.P)

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
        self._advance(self.t_us, t_us, acc, gyr, self.initialized)
        self.t_us = t_us

    def _advance(self, t0: int, t_us: int, acc, gyr, initialized: bool) -> None:
        """From the filter's time ``t0`` to ``t_us`` > ``t0``: the interval's mean inputs, the
        steps split at the clones due inside it (``initialized``: the covariance is propagated)."""
        np.add(self._acc_prev, acc, out=self.f)
        np.multiply(self.f, self._half, out=self.f)
        self.f -= self.ba
        np.add(self._gyr_prev, gyr, out=self.w)
        np.multiply(self.w, self._half, out=self.w)
        self.w -= self.bg
        self._acc_prev[:] = acc
        self._gyr_prev[:] = gyr
        t = t0
        while True:
            kk = self.clones.next_due(t, t_us)
            nxt = int(self.clone_t[kk]) if kk >= 0 else t_us
            if nxt > t:
                self._step((nxt - t) * 1e-6)
                t = nxt
            if kk >= 0:
                self._take_clone_now(kk, initialized)
                continue
            if t >= t_us:
                break
        for k in range(self.n_clones):
            if self.clone_due[k] and self.clone_t[k] <= t_us:
                self._take_clone_now(k, initialized)

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
        """The core block's error transition over ``dt`` (s) into ``F`` ((15, 15), its off-model
        entries as ``transition_static`` writes them) and its diagonal noise into ``q`` (15,): what
        this filter applies (eq 6.17), for a covariance beside it (``actuate.accuracy``)."""
        self._build_F(F, q, dt)

    def _accel(self):
        """``R f - f_ref`` (``f_ref = -g``): the acceleration in the source frame."""
        f = self.f
        ax, ay, az = to_nav(self._Rv, float(f[0]), float(f[1]), float(f[2]))
        r = self._fref
        return ax - r[0], ay - r[1], az - r[2]

    def _orthonormalize(self) -> None:
        _orthonormalize(self.R, self._R2, self._dR, self._half)

    # -------------------------------------------------------- prediction
    def predict_pose(self, horizon_us: int, out_P6, out_p, steps: int = 8) -> None:
        """Pose covariance (6x6 over ``(dp, ori)``) and position predicted
        ``horizon_us`` ahead with the last inertial inputs held, without
        changing the filter (for the when/which decisions)."""
        self._predict_ahead(max(int(horizon_us), 0) * 1e-6, max(1, int(steps)), out_P6, out_p)

    def _predict_ahead(self, T: float, n: int, out_P6, out_p) -> None:
        """:meth:`predict_pose` over ``T`` seconds in ``n`` steps."""
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

    def pose_values(self, out) -> None:
        """A POSE's values into ``out`` (14): the position, the quaternion w, x, y, z
        (``rotation.quat_tuple``), the variances of ``POS`` and ``ORI``, and ``POS``'s trace."""
        p, P, b, o = self.p, self.P, POS.start, ORI.start
        out[0], out[1], out[2] = float(p[0]), float(p[1]), float(p[2])
        out[3], out[4], out[5], out[6] = quat_tuple(self.R)
        for i in range(3):
            out[7 + i] = float(P[b + i, b + i])
            out[10 + i] = float(P[o + i, o + i])
        out[13] = float(P[b, b]) + float(P[b + 1, b + 1]) + float(P[b + 2, b + 2])

    # ------------------------------------------------------------ update
    def update_pulse(self, k: int, m: CoilMeasurement, model: SingleCoilModel) -> int:
        """Correct the state with one pulse's amplitude ``m`` (:class:`CoilMeasurement`),
        measured at the time of clone ``k`` (``k = -1``: the current state), through the
        iterated update of ``single_coil_update.SingleCoilUpdate``.

        Measurement covariance: the amplitude variances, plus ``(rel_model |h|)^2`` for the
        field model and the current, plus the linearisation error of Schepers sec. 3.2 (for a
        field falling as ``r^-3`` the second-order term of ``h(p + dp)`` is about ``6 (dp/r)^2
        |h|``; ``(2 sigma_p^2 / r^2 |h|)^2`` is kept with ``sigma_p`` the largest prior
        position std), the whole multiplied by ``r_scale``. Returns the ``ekf.EKF_*`` flags;
        ``nis_nominal`` is the first-pass NIS with ``r_scale = 1`` (for the monitor), ``nis``
        the one gated."""
        if not self.initialized:
            return EKF_NO_STATE
        if k >= 0:
            if not self.clone_taken[k]:
                # the IMU stream has not reached the measurement time: measure now
                self._take_clone(k)
            p, R = self.clone_p[k], self.clone_R[k]
            cp, co = self.clones.cp[k], self.clones.co[k]
        else:
            p, R = self.p, self.R
            cp, co = POS, ORI
        u = self._coil_update
        flags = self._run_update(self.P, p, R, cp, co, m, model)
        self.nis_nominal = u.nis_nominal
        self.nis = u.nis
        if flags & (EKF_GATED | EKF_NOT_PD | EKF_NONFINITE):
            self.rejected += 1
            return flags
        self._inject(u.dx)
        self.updates += 1
        return flags

    def update_single_coil(self, k: int, y, var_amp, coil: int, current: float,
                           model: SingleCoilModel, rel_model: float = 0.0,
                           r_scale: float = 1.0, gate: bool = True) -> int:
        """:meth:`update_pulse` with the measurement's fields given one by one (for the
        trackers that fuse pulse windows of a burst)."""
        return self.update_pulse(k, self._meas.set(y, var_amp, coil, current, rel_model, r_scale, gate), model)

    def _inject(self, dx) -> None:
        """Apply the error estimate to the nominal state (error reset)."""
        self.p += dx[POS]
        self.v += dx[VEL]
        self.ba += dx[ACC]
        self.bg += dx[GYR]
        o = ORI.start
        self._sd.rotate(self.R, float(dx[o]), float(dx[o + 1]), float(dx[o + 2]))
        self.clones.inject(dx, self._sd.rotate)



class CoilGainEKF(SchepersEKF):
    """:class:`SchepersEKF` with each coil's gain error as a state (module docstring, "Coil gains";
    ``[adaptive] coil_gain_sigma``): ``coil_gains`` coils, prior std ``gain_sigma``. The dynamics and
    their compiled kernels are the base class's; the gains' rows come after the clones
    (``layout.schepers_layout``), so the propagation carries them with the identity."""

    @classmethod
    def from_config(cls, cfg=None, **overrides) -> "CoilGainEKF":
        """:meth:`SchepersEKF.from_config` with a gain per coil of ``cfg``, prior ``coil_gain_sigma``."""
        if cfg is None:
            from coiltrack.firmware.config import FirmwareConfig
            cfg = FirmwareConfig()
        kw = dict(coil_gains=len(cfg.source.coils), gain_sigma=cfg.adaptive.coil_gain_sigma)
        kw.update(overrides)
        return super().from_config(cfg, **kw)

    def __init__(self, *, coil_gains: int, gain_sigma: float, **kw):
        if int(coil_gains) < 1 or not (math.isfinite(gain_sigma) and gain_sigma > 0.0):
            raise ValueError(f"coil_gains must be >= 1 and gain_sigma > 0, got {coil_gains!r}, {gain_sigma!r}")
        self._n_gains = int(coil_gains)          # read by _make_layout during the base's set-up
        super().__init__(**kw)
        self.gains = CoilGains(self.layout.GAIN, gain_sigma, self._coil_update)
        self._run_update = self.gains.run

    def _make_layout(self, n_clones: int):
        return schepers_layout(n_clones, self._n_gains)

    def initialize(self, p, R, P6, t_us: int, sigma_vel: float, sigma_acc: float, sigma_gyr: float) -> None:
        """:meth:`SchepersEKF.initialize`; the gains' estimates kept, their variances the prior's."""
        super().initialize(p, R, P6, t_us, sigma_vel, sigma_acc, sigma_gyr)
        self.gains.restore_prior(self.P)

    def update_pulse(self, k: int, m: CoilMeasurement, model: SingleCoilModel) -> int:
        """:meth:`SchepersEKF.update_pulse`, and the gains' correction where it was applied."""
        flags = super().update_pulse(k, m, model)
        if not flags & (EKF_GATED | EKF_NOT_PD | EKF_NONFINITE | EKF_NO_STATE):
            self.gains.inject()
        return flags


def filter_class(cfg) -> type:
    """The single-coil filter of ``cfg``: :class:`CoilGainEKF` with ``coil_gain_sigma`` > 0."""
    return CoilGainEKF if cfg.adaptive.coil_gain_sigma > 0.0 else SchepersEKF


def _orthonormalize(R, R2, dR, half) -> None:
    """One Newton step of the polar decomposition, ``R <- R (3 I - R^T R) / 2`` (``R2``, ``dR``:
    (3, 3) scratch, ``half`` a 0-d 0.5)."""
    np.matmul(R.T, R, out=R2)
    np.negative(R2, out=R2)
    for i in range(3):
        R2[i, i] += 3.0
    np.multiply(R2, half, out=R2)
    np.matmul(R, R2, out=dR)
    R[:] = dR


def _compiled(ekf: SchepersEKF, ext):
    """The compiled kernels (``ext.SchepersCore``) bound to the arrays of ``ekf``."""
    arrays = (ekf.p, ekf.v, ekf.R, ekf.ba, ekf.bg, ekf.f, ekf.w, ekf._acc_prev, ekf._gyr_prev, ekf.P, ekf.F,
              ekf._T, ekf._q, ekf._Fc, ekf._Pc, ekf._Tc, ekf._qc, ekf._sd.E, ekf._R2, ekf._dR, ekf._fref_a,
              ekf.clone_p, ekf.clone_R, ekf._TPb, ekf._TPTb)
    cl = ekf.clones
    return ext.SchepersCore(ekf.nx, ekf.n_clones, arrays, cl.t, cl.due, cl.taken,
                            tuple(c.start for c in cl.cp), tuple(c.start for c in cl.co),
                            ekf.acc_noise * ekf.acc_noise, ekf.pos_noise * ekf.pos_noise,
                            ekf.gyr_noise * ekf.gyr_noise, ekf.acc_bias_rw * ekf.acc_bias_rw,
                            ekf.gyr_bias_rw * ekf.gyr_bias_rw)
