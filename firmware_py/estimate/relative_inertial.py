"""Relative inertial EKF: the sensor's pose relative to a moving source, in the source frame.

The magnetic system measures the sensor relative to the source: position
``q`` (source frame) and orientation ``R = Phi^T Theta`` (sensor to source).
The thesis (``002_cd7f1fdb7fc67471.txt``) integrates ``a_net = a_sensor -
a_source`` (eq 6.8) in the global frame, ``a_net = Theta f_sensor - Phi
f_source``, so both orientations ``Theta`` and ``Phi`` must be known in the
global frame, and a tilt error of either leaks ``g sin(err)`` into
``a_net`` (sec 6.5: "the acceleration of the source is now related to
orientation errors of the source Phi"). Written in the source frame,

    Phi^T a_net = Phi^T Theta f_sensor - f_source = R f_sensor - f_source,

gravity cancels: only the relative orientation ``R`` enters, the one the
magnetic measurements observe. This is eq 6.8 with the source orientation
"incorporated in the fusion scheme" (sec 6.5): ``Phi`` is not needed at all.

Kinematics (``w_s`` the source's rate, source frame; ``d`` the position of
the source's IMU on the source, source frame: its accelerometer measures the
specific force there; ``r = q - d`` the sensor relative to that point;
``v = Phi^T d(Phi r)/dt`` the relative world velocity in source axes)::

    r' = v - w_s x r
    v' = R f - f_source - w_s x v               (eq 6.8 in the source frame)
    R' = R [w]x - [w_s]x R

One IMU interval ``dt`` (both IMUs' samples averaged over the interval, offsets
removed) is integrated exactly for constant rates: the specific forces are
taken at the interval's middle, ``R_mid = exp(-[w_s dt/2]x) R exp([w dt/2]x)``,
the relative acceleration ``a = R_mid f - f_source`` is brought to the
interval's first source frame (``exp([w_s dt/2]x) a``), ``r`` and ``v``
integrated there (an inertial frame over the interval) and turned into the
last frame, ``r <- exp(-[w_s dt]x) r``.

State layout ``relative_layout(n)`` (``coiltrack.firmware.estimate.layout``):
``POS, VEL, ORI, ACC, GYR`` as in the single-coil EKF
(``coiltrack.firmware.estimate.single_coil``, whose clones, measurement
update and error injection are used unchanged), plus ``SACC`` and ``SGYR``,
the source IMU's offsets (source frame, random walks). Error convention
``x_true = x_est + dx``, ``R_true = R exp([ori]x)``; first-order error
dynamics (``E = exp(-[w_s dt]x)`` premultiplies the ``POS`` and ``VEL``
rows: the frame change)::

    d(dp)/dt  = dv - [r]x dsgyr                  (+ the frame rotation)
    d(dv)/dt  = -R [f]x ori - R acc + dsacc - [v]x dsgyr
    d(ori)/dt = -[w]x ori - gyr + R^T dsgyr

A fixed source (no source IMU) is ``f_source = -g`` (source frame), ``w_s = 0``
and the source offsets frozen at zero: then this is the single-coil EKF.

The measurement of each pulse window is the one signal model's ``h = I R^T
B_k(p)`` with ``H`` its Jacobian (Schepers & Veltink 2010, eqs 5, 9-11;
``SingleCoilModel``), through the one update shape
(``coiltrack.firmware.estimate.ekf.KalmanUpdate``, Joseph form), at the
clone of the pulse's own measurement time: ``SchepersEKF.update_single_coil``.

Quiet field (relative heading). Between pulses the sensor's magnetometer reads
the earth field alone, in the sensor frame, ``b = R^T e`` with ``e`` the earth
field in the source frame, which the source module's magnetometer reads
between pulses. :meth:`RelativeInertialEKF.update_quiet_field` takes that
pair as a 3-dof measurement of the relative orientation (the two axes across
the field; the rotation about it stays with the pulses)::

    h = R^T e,   H_ORI = [h]x                (R_true^T e = exp(-[ori]x) R^T e)

through the same update shape, with ``R = var I``. A better ``R`` is what
makes ``R f - f_source`` cancel gravity between bursts: 1 deg of ``R``
leaks 0.17 m/s^2 into the relative acceleration.

All arrays are allocated in ``__init__``; propagation allocates nothing.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NONFINITE, EKF_NOT_PD
from coiltrack.firmware.estimate.layout import ORI, POS, VEL, relative_layout
from coiltrack.firmware.estimate.single_coil import EKF_NO_STATE, SchepersEKF
from coiltrack.firmware.estimate.strapdown import integrate_pv, transition_sensor, transition_static
from coiltrack.firmware.linalg import exp_rotvec

_SACC = relative_layout(0).SACC
_SGYR = relative_layout(0).SGYR
#: columns of the inertial core and the source offsets (the rows the frame change turns)
_NC = _SGYR.stop


class RelativeInertialEKF(SchepersEKF):
    """Inertial error-state EKF of the sensor relative to a moving source.

    Extra parameters (besides :class:`SchepersEKF`'s):

    src_position : (3,)
        Position of the source's IMU on the source, source frame, m.
    src_acc_noise, src_gyr_noise : float
        White-noise densities of the source IMU (m/s^2/sqrt(Hz), rad/s/sqrt(Hz)).
    src_acc_bias_rw, src_gyr_bias_rw : float
        Random-walk densities of the source offsets (0 with ``src_bias_sigma`` 0: frozen).
    src_acc_bias_sigma, src_gyr_bias_sigma : float
        Initial standard deviations of the source offsets (m/s^2, rad/s).
    extra_acc_noise : float
        Acceleration noise density beyond the IMUs' (m/s^2/sqrt(Hz)).
    """

    @staticmethod
    def _make_layout(n_clones: int):
        return relative_layout(n_clones)

    @classmethod
    def from_config(cls, cfg=None, n_clones: int = 3, source_imu: bool = True, **overrides):
        """The filter of ``cfg`` with one clone per pulse of the burst; ``source_imu``
        False: a fixed source (``f_source = -g``, ``w_s = 0``, source offsets frozen)."""
        if cfg is None:
            from coiltrack.firmware.config import FirmwareConfig
            cfg = FirmwareConfig()
        root = math.sqrt(cfg.imu.imu_rate_hz)
        states = source_imu and cfg.tight.tight_source_bias_states
        kw = dict(n_clones=n_clones, src_position=cfg.tight.tight_source_imu_position_m,
                  src_acc_noise=(cfg.imu.imu_acc_sigma / root) if source_imu else 0.0,
                  src_gyr_noise=(cfg.imu.imu_gyro_sigma / root) if source_imu else 0.0,
                  src_acc_bias_rw=cfg.imu.imu_acc_bias_rw if states else 0.0,
                  src_gyr_bias_rw=cfg.imu.imu_gyro_bias_rw if states else 0.0,
                  src_acc_bias_sigma=cfg.imu.imu_acc_bias_sigma if states else 0.0,
                  src_gyr_bias_sigma=cfg.imu.imu_gyro_bias_sigma if states else 0.0,
                  extra_acc_noise=cfg.tight.tight_acc_noise)
        kw.update(overrides)
        return super().from_config(cfg, **kw)

    def __init__(self, *, src_position=(0.0, 0.0, 0.0), src_acc_noise: float = 0.0, src_gyr_noise: float = 0.0,
                 src_acc_bias_rw: float = 0.0, src_gyr_bias_rw: float = 0.0, src_acc_bias_sigma: float = 0.0,
                 src_gyr_bias_sigma: float = 0.0, extra_acc_noise: float = 0.0, **kw):
        super().__init__(**kw)
        self.d = np.array(src_position, dtype=float).reshape(3)
        self.src_acc_noise = float(src_acc_noise)
        self.src_gyr_noise = float(src_gyr_noise)
        self.src_acc_bias_rw = float(src_acc_bias_rw)
        self.src_gyr_bias_rw = float(src_gyr_bias_rw)
        self.src_acc_bias_sigma = float(src_acc_bias_sigma)
        self.src_gyr_bias_sigma = float(src_gyr_bias_sigma)
        self.extra_acc_noise = float(extra_acc_noise)
        self.bsa = np.zeros(3)              # source accelerometer offset estimate, source frame
        self.bsg = np.zeros(3)              # source gyroscope offset estimate
        self.fs = np.array([-float(v) for v in self.g])   # source specific force (interval mean), offset removed
        self.ws = np.zeros(3)               # source rate (interval mean), offset removed
        self._fs_prev = self.fs.copy()
        self._ws_prev = np.zeros(3)
        self._src_have_prev = False
        self._fsv = memoryview(self.fs)
        self._fref = self._fsv        # SchepersEKF._accel: R f - f_ref, here the source's specific force
        self._wsv = memoryview(self.ws)
        self._fspv = memoryview(self._fs_prev)
        self._wspv = memoryview(self._ws_prev)
        self._bsav = memoryview(self.bsa)
        self._bsgv = memoryview(self.bsg)
        self._dv = memoryview(self.d)
        self._Eh = np.eye(3)                # exp(-[w_s dt/2]x)
        self._E = np.eye(3)                 # exp(-[w_s dt]x)
        self._Ehv = memoryview(self._Eh)
        self._Ev = memoryview(self._E)
        self._R3 = np.zeros((3, 3))
        self._R1 = np.zeros((3, 3))
        self._R1v = memoryview(self._R1)
        self._Eht = self._Eh.T
        self._r6 = np.zeros((3, _NC))
        self.quiet_pred = np.zeros(3)       # the last quiet-field update's h = R^T e (T)
        self._qpv = memoryview(self.quiet_pred)
        self.quiet_nis = 0.0

    # ------------------------------------------------------------ set-up
    def initialize(self, p, R, P6, t_us: int, sigma_vel: float, sigma_acc: float, sigma_gyr: float) -> None:
        """:meth:`SchepersEKF.initialize`, plus the source offsets' variances (their estimates kept)."""
        super().initialize(p, R, P6, t_us, sigma_vel, sigma_acc, sigma_gyr)
        P = self.P
        for s, sig in ((_SACC, self.src_acc_bias_sigma), (_SGYR, self.src_gyr_bias_sigma)):
            for i in range(s.start, s.stop):
                P[i, i] = sig * sig

    def restart_inputs(self) -> None:
        super().restart_inputs()
        self._src_have_prev = False

    # ------------------------------------------------------- propagation
    def propagate_relative(self, t_us: int, acc, gyr, src_acc, src_gyr) -> None:
        """Advance to the sample pair at ``t_us``: the sensor's raw specific force ``acc``
        (m/s^2) and rate ``gyr`` (rad/s), sensor frame, and the source's ``src_acc``,
        ``src_gyr`` at the same instant (source frame; for a fixed source ``-g`` and 0)."""
        fp, wp, fs, ws = self._fspv, self._wspv, self._fsv, self._wsv
        ba, bg = self._bsav, self._bsgv
        if self._src_have_prev and self._have_prev and self.t_us is not None and int(t_us) > self.t_us:
            for i in range(3):
                fs[i] = 0.5 * (fp[i] + src_acc[i]) - ba[i]
                ws[i] = 0.5 * (wp[i] + src_gyr[i]) - bg[i]
        for i in range(3):
            fp[i] = src_acc[i]
            wp[i] = src_gyr[i]
        self._src_have_prev = True
        self.propagate(t_us, acc, gyr)

    def _left(self, R, E) -> None:
        """``R <- E R``."""
        np.matmul(E, R, out=self._R3)
        np.copyto(R, self._R3)

    def _step(self, dt: float) -> None:
        """Nominal relative step over ``dt`` (s, module docstring) and the covariance."""
        R = self.R
        h = 0.5 * dt
        w = self.w
        ws, d = self._wsv, self._dv
        wx, wy, wz = float(w[0]) * h, float(w[1]) * h, float(w[2]) * h
        sx, sy, sz = ws[0], ws[1], ws[2]
        sd = self._sd
        exp_rotvec(-sx * h, -sy * h, -sz * h, self._Ehv)
        exp_rotvec(-sx * dt, -sy * dt, -sz * dt, self._Ev)
        sd.rotate(R, wx, wy, wz)
        self._left(R, self._Eh)                           # R_mid
        # a = R_mid f - f_source (mid frame), brought to the first frame: Eh^T a
        mx, my, mz = self._accel()
        Eh = self._Ehv
        ax = Eh[0, 0] * mx + Eh[1, 0] * my + Eh[2, 0] * mz
        ay = Eh[0, 1] * mx + Eh[1, 1] * my + Eh[2, 1] * mz
        az = Eh[0, 2] * mx + Eh[1, 2] * my + Eh[2, 2] * mz
        p, v = self._pv, self._vv
        # r = p - d in the first frame
        for i in range(3):
            p[i] = p[i] - d[i]
        integrate_pv(p, v, dt, ax, ay, az, ax, ay, az)
        E = self._Ev
        rx, ry, rz = p[0], p[1], p[2]
        vx, vy, vz = v[0], v[1], v[2]
        for i in range(3):
            p[i] = E[i, 0] * rx + E[i, 1] * ry + E[i, 2] * rz + d[i]
            v[i] = E[i, 0] * vx + E[i, 1] * vy + E[i, 2] * vz
        if self.initialized:
            self._build_relative_F(dt, rx, ry, rz, vx, vy, vz)
            np.matmul(self.F, self.P, out=self._T)
            np.matmul(self._T, self._Ft, out=self.P)
            self._P_diag += self._q
        sd.rotate(R, wx, wy, wz)
        self._left(R, self._Eh)
        self._steps += 1
        if self._steps % 64 == 0:
            self._orthonormalize()

    def _build_relative_F(self, dt: float, rx: float, ry: float, rz: float, vx: float, vy: float,
                          vz: float) -> None:
        """Error transition over ``dt`` into ``F`` (``R`` at the interval's middle; ``r``, ``v``
        the relative position from the source IMU and the velocity, first frame) and its
        diagonal process noise into ``_q`` (module docstring)."""
        F = self._Fv
        f, w = self.f, self.w
        Fa = self.F
        P0, V0, O0 = POS.start, VEL.start, ORI.start
        for r0 in (P0, V0):                # the rows the frame change turned last time
            Fa[r0:r0 + 3, 0:_NC].fill(0.0)
            for i in range(3):
                F[r0 + i, r0 + i] = 1.0
        transition_static(F, dt, 1.0, 1.0)
        # the specific force's error enters in the first frame: R_1 = exp([w_s dt/2]x) R_mid
        np.matmul(self._Eht, self.R, out=self._R1)
        transition_sensor(F, dt, self._R1v, float(f[0]), float(f[1]), float(f[2]),
                          float(w[0]), float(w[1]), float(w[2]), self._sd)
        sa, sg = _SACC.start, _SGYR.start
        h2 = 0.5 * dt * dt
        R = self._Rv
        for i in range(3):
            F[P0 + i, sa + i] = h2
            F[V0 + i, sa + i] = dt
            F[sa + i, sa + i] = 1.0
            F[sg + i, sg + i] = 1.0
            for j in range(3):
                F[O0 + i, sg + j] = dt * R[j, i]          # + dt R^T
        # -dt [r]x and -dt [v]x on SGYR
        F[P0, sg], F[P0, sg + 1], F[P0, sg + 2] = 0.0, dt * rz, -dt * ry
        F[P0 + 1, sg], F[P0 + 1, sg + 1], F[P0 + 1, sg + 2] = -dt * rz, 0.0, dt * rx
        F[P0 + 2, sg], F[P0 + 2, sg + 1], F[P0 + 2, sg + 2] = dt * ry, -dt * rx, 0.0
        F[V0, sg], F[V0, sg + 1], F[V0, sg + 2] = 0.0, dt * vz, -dt * vy
        F[V0 + 1, sg], F[V0 + 1, sg + 1], F[V0 + 1, sg + 2] = -dt * vz, 0.0, dt * vx
        F[V0 + 2, sg], F[V0 + 2, sg + 1], F[V0 + 2, sg + 2] = dt * vy, -dt * vx, 0.0
        # the frame change: POS and VEL rows premultiplied by E = exp(-[w_s dt]x)
        rows = self._r6
        for r0 in (P0, V0):
            np.matmul(self._E, Fa[r0:r0 + 3, 0:_NC], out=rows)
            np.copyto(Fa[r0:r0 + 3, 0:_NC], rows)
        # process noise (diagonal; the isotropic noises are not changed by the frame change)
        qa = (self.acc_noise * self.acc_noise + self.src_acc_noise * self.src_acc_noise
              + self.extra_acc_noise * self.extra_acc_noise)
        gs2 = self.src_gyr_noise * self.src_gyr_noise
        qa += gs2 * (vx * vx + vy * vy + vz * vz)
        q = self._q
        self._fill_q(q, dt, qa, self.pos_noise * self.pos_noise + gs2 * (rx * rx + ry * ry + rz * rz),
                     self.gyr_noise * self.gyr_noise + gs2)
        qsa = self.src_acc_bias_rw * self.src_acc_bias_rw * dt
        qsg = self.src_gyr_bias_rw * self.src_gyr_bias_rw * dt
        for i in range(3):
            q[sa + i] = qsa
            q[sg + i] = qsg

    # ------------------------------------------------------------ quiet field
    def update_quiet_field(self, b, e, var: float, gate: bool = True) -> int:
        """Correct the state with the sensor's quiet field ``b`` (3,) (T, sensor frame) and the
        earth field ``e`` (3,) (T, source frame), both at the filter's time: ``h = R^T e``,
        ``H_ORI = [h]x``, ``R = var I`` (T^2; module docstring). Returns the ``ekf.EKF_*``
        flags; ``quiet_nis`` is the update's NIS."""
        if not self.initialized:
            return EKF_NO_STATE
        R = self._Rv
        ex, ey, ez = float(e[0]), float(e[1]), float(e[2])
        hx = R[0, 0] * ex + R[1, 0] * ey + R[2, 0] * ez
        hy = R[0, 1] * ex + R[1, 1] * ey + R[2, 1] * ez
        hz = R[0, 2] * ex + R[1, 2] * ey + R[2, 2] * ez
        q = self._qpv
        q[0], q[1], q[2] = hx, hy, hz
        upd = self.upd
        H = upd.H
        H.fill(0.0)
        o = ORI.start
        # [h]x
        H[0, o + 1], H[0, o + 2] = -hz, hy
        H[1, o], H[1, o + 2] = hz, -hx
        H[2, o], H[2, o + 1] = -hy, hx
        Rm = upd.R
        Rm.fill(0.0)
        y = upd.y
        for i in range(3):
            Rm[i, i] = var
            y[i] = float(b[i]) - q[i]
        f = upd.update(self.P, None if gate else math.inf)
        self.quiet_nis = upd.nis
        if not f & (EKF_GATED | EKF_NOT_PD | EKF_NONFINITE):
            self._inject(upd.dx)
        return f

    def _inject(self, dx) -> None:
        """:meth:`SchepersEKF._inject` and the source offsets."""
        super()._inject(dx)
        self.bsa += dx[_SACC]
        self.bsg += dx[_SGYR]


SACC = _SACC
SGYR = _SGYR
