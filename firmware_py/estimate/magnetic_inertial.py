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

Bounded update (the delayed-horizon idea of PX4's EKF2). The update and its
replay need not run in one tick: :meth:`begin_magnetic_update` restores the
snapshot into a second preallocated state (the *shadow*), updates it and
returns; :meth:`step` then replays at most a given number of IMU steps on the
shadow per call. Meanwhile :meth:`push_imu` keeps propagating the *live*
state and queueing fused poses from it, so no output waits for the replay.
When the shadow has caught up with the newest IMU sample it is copied into
the live state (and its replayed pose history into the live history), and
the live state carries the update from then on. While a replay runs, the
snapshot of the next burst is taken by the shadow (the corrected state) and
the recorder (smoother) follows the shadow. :meth:`magnetic_update` is
``begin_magnetic_update`` and ``step`` until done, the same result in one
call. Cost per :meth:`step` call: at most ``budget + 1`` strapdown and
covariance steps (:func:`max_replay_steps_per_step`; the last IMU sample of a
call may be split in two at a snapshot time), plus, on the call that
finishes, one copy of the state and of the pose history.

Recovery (docs/faults.md). The filter restarts from a magnetic solution
(:meth:`_initialize`) when ``reinit_after`` solutions in a row fail the gate
(``RECOVER_DISAGREE``), when the last accepted update is older than
``dead_reckon_limit_us`` (``RECOVER_GAP``: the inertial state alone is not
vouched for that long) or after the IMU stream broke off (``RECOVER_STREAM``).
The offsets ``b_a``, ``b_g`` and their covariance block survive a restart
while credible (:meth:`_keep_biases`, :meth:`_restore_biases`: decayed and
with the random-walk variance of eqs 6.13-6.14 added for the time between).
Outputs older than ``dead_reckon_after_us`` since the last accepted update
carry ``OUT_DEAD_RECKONING``, older than ``dead_reckon_limit_us`` ``OUT_LOST``.

All buffers are created in ``__init__``; a step allocates no numpy array.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import EKF_OK, CovariancePredict, KalmanUpdate
from coiltrack.firmware.estimate.layout import (ACC, GYR, ORI, POS, POSE_ORI, POSE_POS, PSI, QM, VEL, XI,
                                               fusion_layout, fusion_measurement_layout)
from coiltrack.firmware.estimate.strapdown import Strapdown, integrate_pv, to_nav, transition_nav, transition_static
from coiltrack.firmware.linalg import exp_rotvec, rotvec_from_matrix
from coiltrack.firmware.ring import Ring, field_slices
from coiltrack.firmware.rotation import quat_from_elements

# fusion health flags (bit field, beside the ekf flags)
FUS_NOT_INITIALISED = 64
FUS_NO_SNAPSHOT = 128       # the IMU stream has not reached t_ref (or it left the ring)
FUS_REINITIALISED = 256     # too many consecutive rejections: restarted from the magnetic pose
FUS_INITIALISED = 512       # this update initialised the filter
FUS_BUSY = 2048             # begin_magnetic_update refused: the previous replay is still running
FUS_REPLAY_LOST = 4096      # the IMU ring dropped samples the replay needed: the update is lost
FUS_PREPARED = 8192         # prepare_magnetic_update: the measurement is ready for apply_magnetic_update
FUS_GAP_REINIT = 16384      # the last update was longer ago than the filter can bridge: restarted

#: why the filter restarted from a magnetic solution (``FusionFilter.recovery_reason``)
RECOVER_DISAGREE = 1        # ``reinit_after`` rejected updates in a row (innovations beyond the gate)
RECOVER_GAP = 2             # no accepted update for longer than ``dead_reckon_limit_us``
RECOVER_STREAM = 3          # the IMU stream broke off (``max_gap_us``)

#: named rows of an IMU ring entry: specific force, rate (sensor frame), the
#: source's specific force in G, the source orientation Phi (row-major)
IMU_FIELDS = (("F", 3), ("W", 3), ("FSRC", 3), ("PHI", 9))
#: named rows of a pose-history entry: p_M, R_MS (row-major), source frame
HIST_FIELDS = (("P", 3), ("R", 9))
#: named rows of an output entry (the POSE message): p_M, quaternion (w, x, y, z),
#: position variances (source frame), orientation variances (sensor frame), status bits
OUT_FIELDS = (("P", 3), ("Q", 4), ("VAR_P", 3), ("VAR_O", 3), ("STATUS", 1))
_I, _H, _O = field_slices(IMU_FIELDS), field_slices(HIST_FIELDS), field_slices(OUT_FIELDS)
IMU_F, IMU_W, IMU_FSRC, IMU_PHI = _I["F"].start, _I["W"].start, _I["FSRC"].start, _I["PHI"].start
HIST_P, HIST_R = _H["P"].start, _H["R"].start
OUT_P, OUT_Q, OUT_VAR_P, OUT_VAR_O, OUT_STATUS = (_O["P"].start, _O["Q"].start, _O["VAR_P"].start,
                                                  _O["VAR_O"].start, _O["STATUS"].start)
#: status bits of ``OUT_STATUS``
OUT_STALE = 1               # no magnetic update for ``stale_us``
OUT_INCONSISTENT = 2        # the last update was not accepted cleanly
OUT_DEAD_RECKONING = 4      # no accepted magnetic update for ``dead_reckon_after_us``: inertial only
OUT_LOST = 8                # ... for ``dead_reckon_limit_us``: not a valid pose
OUT_RECOVERED = 16          # restarted from a magnetic solution, no update accepted since
#: strapdown + covariance steps one replayed IMU sample can cost (split at a snapshot)
MAX_STEPS_PER_SAMPLE = 2


def max_replay_steps_per_step(budget: int) -> int:
    """Most strapdown and covariance steps one ``FusionFilter.step(budget)`` runs."""
    return max(int(budget), 1) - 1 + MAX_STEPS_PER_SAMPLE


class FusionParams:
    """Parameters of the ch. 6 filter (SI units; per-sample noise figures).

    They have no defaults of their own: :meth:`from_config` takes them from a
    ``FirmwareConfig`` (whose defaults are the one set)."""

    @classmethod
    def from_config(cls, cfg=None, source_imu: bool = False, **overrides) -> "FusionParams":
        """The parameters of ``cfg`` (default ``FirmwareConfig()``), with ``overrides``."""
        if cfg is None:
            from coiltrack.firmware.config import FirmwareConfig
            cfg = FirmwareConfig()
        kw = dict(
            measurement_model=cfg.measurement_model, acc_noise=cfg.imu_acc_sigma, gyro_noise=cfg.imu_gyro_sigma,
            source_acc_noise=(cfg.source_acc_sigma or cfg.imu_acc_sigma) if source_imu else 0.0,
            acc_bias_sigma=cfg.imu_acc_bias_sigma, gyro_bias_sigma=cfg.imu_gyro_bias_sigma,
            acc_bias_rw=cfg.imu_acc_bias_rw, gyro_bias_rw=cfg.imu_gyro_bias_rw,
            acc_bias_tau_s=cfg.bias_tau_s, gyro_bias_tau_s=cfg.bias_tau_s,
            velocity0_sigma=cfg.init_sigma_vel, gate_probability=cfg.fusion_gate_probability,
            reinit_after=cfg.fusion_reinit_after, xi_var_scale=cfg.xi_var_scale, xi_sigma_floor=cfg.xi_sigma_floor,
            xi_heading_sigma_floor=cfg.xi_heading_sigma_floor, mag_var_scale=cfg.mag_var_scale,
            qm_sigma=cfg.qm_sigma, psi_sigma=cfg.psi_sigma, meas_sigma=cfg.meas_sigma,
            max_gap_us=max(cfg.imu_timeout_us, int(3e6 / cfg.imu_rate_hz)), stale_us=cfg.stale_us,
            dead_reckon_after_us=cfg.dead_reckon_after_us, dead_reckon_limit_us=cfg.dead_reckon_limit_us,
            keep_biases=cfg.recovery_keep_biases, bias_gate_sigmas=cfg.recovery_bias_gate_sigmas)
        kw.update(overrides)
        return cls(**kw)

    def __init__(self, *, measurement_model, acc_noise, gyro_noise, source_acc_noise, acc_bias_sigma,
                 gyro_bias_sigma, acc_bias_rw, gyro_bias_rw, acc_bias_tau_s, gyro_bias_tau_s, velocity0_sigma,
                 gate_probability, reinit_after, xi_var_scale, xi_sigma_floor, xi_heading_sigma_floor,
                 mag_var_scale, qm_sigma, psi_sigma, meas_sigma, max_gap_us, stale_us,
                 dead_reckon_after_us=1_000_000, dead_reckon_limit_us=2_000_000, keep_biases=True,
                 bias_gate_sigmas=4.0):
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
        # recovery: how long the inertial state alone is vouched for, and whether the
        # offsets survive a restart (when within ``bias_gate_sigmas`` of their prior)
        self.dead_reckon_after_us = int(dead_reckon_after_us)
        self.dead_reckon_limit_us = int(dead_reckon_limit_us)
        self.keep_biases = bool(keep_biases)
        self.bias_gate_sigmas = float(bias_gate_sigmas)


class InsState:
    """One copy of the inertial state: nominal position ``p``, velocity ``v``,
    orientation ``Th`` (Theta), offsets ``ba``, ``bg`` at ``t_us``, the error
    covariance ``P``, and its propagation workspace (``pred``: ``A``, ``Q`` of
    eq 6.17, written for the step ``dt_last``; ``white``: the rows of the white
    states, zero in ``A``). The filter holds three: the live state, the shadow
    (a replay in progress) and the snapshot at t_ref, which is only copied
    (``white=None``: no workspace)."""

    def __init__(self, n: int, white: tuple[slice, ...] | None, white_q: tuple[float, ...] = (),
                 core=_DEFAULT_CORE):
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.Th = np.eye(3)
        self.ba = np.zeros(3)
        self.bg = np.zeros(3)
        self.P = np.zeros((n, n))
        self.t_us = 0
        self._pv = memoryview(self.p)
        self._vv = memoryview(self.v)
        self._Thv = memoryview(self.Th)
        self._bav = memoryview(self.ba)
        self._bgv = memoryview(self.bg)
        self._Pv = memoryview(self.P)
        self.dt_last = -1.0
        self.ka = self.kg = 1.0
        #: the compiled strapdown and covariance step bound to this state's buffers, or None
        #: (``coiltrack.firmware.core``; ``FusionFilter._step_compiled``)
        self.ck = None
        if white is None:
            self.pred = None
            return
        self.pred = CovariancePredict(n, core)
        self._Av = memoryview(self.pred.A)
        self._Qf = memoryview(self.pred.Q.reshape(-1))     # flat: element (i, j) at i n + j
        ext = core.ext
        if ext is not None and self.pred.core == "compiled":
            assert (POS.start, VEL.start, ORI.start, ACC.start, GYR.start) == (ext.POS, ext.VEL, ext.ORI,
                                                                             ext.ACC, ext.GYR)
            self.ck = ext.InsStep(n, self.p, self.v, self.Th, self.ba, self.bg, self.pred.A, self.P,
                                  self.pred.Q, self.pred._T)
        # the white states: no transition, their noise (``white_q``, one variance per block) has no
        # step in it, so it is written once here
        for s, q in zip(white, white_q, strict=True):
            for i in range(s.start, s.stop):
                self._Av[i, i] = 0.0
                self.pred.Q[i, i] = q

    def copy_from(self, other: "InsState") -> None:
        """Take ``other``'s nominal state, covariance and time (not its workspace)."""
        np.copyto(self.p, other.p)
        np.copyto(self.v, other.v)
        np.copyto(self.Th, other.Th)
        np.copyto(self.ba, other.ba)
        np.copyto(self.bg, other.bg)
        np.copyto(self.P, other.P)
        self.t_us = other.t_us


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
    core : coiltrack.firmware.core.Core
        The numeric core, chosen at composition.

    The nominal state and covariance of the live state are ``p``, ``v``,
    ``Th``, ``ba``, ``bg``, ``P`` (arrays, fixed for the filter's life),
    ``t_us``; ``pred`` is its ``CovariancePredict``.
    """

    def __init__(self, params: FusionParams, xi_filter=None, imu_capacity: int = 128,
                 history_capacity: int = 128, output_capacity: int = 16, core=_DEFAULT_CORE):
        self.prm = params
        prm = params
        # the step's constants of _set_dt, as it computes them (the same values to the bit)
        self._dtk = (prm.acc_bias_tau_s, prm.gyro_bias_tau_s, prm.acc_noise ** 2 + prm.source_acc_noise ** 2,
                     prm.gyro_noise, prm.acc_bias_rw * prm.acc_bias_rw, prm.gyro_bias_rw * prm.gyro_bias_rw)
        self.layout = fusion_layout(params.measurement_model)
        n = self.layout.n
        self.n = n
        # flat indices of the diagonals of Q that _set_dt rewrites with the step
        self._q_diag = tuple(tuple((b.start + i) * (n + 1) for i in range(3)) for b in (VEL, ORI, ACC, GYR))
        self.model = params.measurement_model
        if self.model != 1 and xi_filter is None:
            raise ValueError("measurement models 2 and 3 need the orientation filter Xi")
        self.xi = xi_filter
        white = (QM, PSI) + ((XI,) if n > 21 else ())
        white_q = (prm.qm_sigma ** 2, prm.psi_sigma ** 2) + ((prm.psi_sigma ** 2,) if n > 21 else ())
        self.st = InsState(n, white, white_q, core)        # live
        self.sh = InsState(n, white, white_q, core)        # shadow: the replay of a delayed update
        self.sn = InsState(n, None, core=core)         # snapshot at t_ref
        self._auth = self.st                # the state that takes snapshots and is recorded
        self.sd = Strapdown(core)
        # the numeric body of each IMU step, chosen once (coiltrack.firmware.core)
        self._ins_step = self._step_compiled if self.st.ck is not None else self._step_python
        zl = fusion_measurement_layout(self.model)
        self.zlayout = zl
        m = zl.n
        self.m = m
        self._zp = zl.ZP.start
        self._zpsi = zl.ZPSI.start if "ZPSI" in zl.names() else -1
        self._zxi = zl.ZXI.start if "ZXI" in zl.names() else -1
        self.upd = KalmanUpdate(n, m, params.gate_probability, core)
        self._Hv = memoryview(self.upd.H)
        self._Rmv = memoryview(self.upd.R)
        self._yv = self.upd._yv
        # the measurement matrix C is constant (eqs 6.18, 6.20, 6.21)
        H = self._Hv
        for i in range(3):
            H[self._zp + i, POS.start + i] = 1.0
            H[self._zp + i, QM.start + i] = 1.0
            for row, white in ((self._zpsi, PSI), (self._zxi, XI)):
                if row >= 0:
                    H[row + i, ORI.start + i] = 1.0
                    H[row + i, white.start + i] = 1.0
        r = params.meas_sigma ** 2
        for i in range(m):
            self._Rmv[i, i] = r
        #: the source is fixed (Phi = I): history and output skip the frame change
        self.source_fixed = False
        # scratch
        self._E = np.zeros((3, 3))
        self._Ev = memoryview(self._E)
        self._T = np.zeros((3, 3))
        # snapshot at t_ref: the source orientation and Xi beside the state
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
        # rings: IMU samples (replay), pose history (motion compensation) and its
        # shadow (the replayed history), fused poses waiting to be sent
        self.imu = Ring(imu_capacity, IMU_FIELDS)
        self.hist = Ring(history_capacity, HIST_FIELDS)
        self._shist = Ring(history_capacity, HIST_FIELDS)
        self.out = Ring(output_capacity, OUT_FIELDS)
        self.imu_t, self.imu_d = self.imu.t, self.imu.d
        self._itv, self._idv, self._icap = self.imu.tv, self.imu.dv, self.imu.capacity
        self._otv, self._odv = self.out.tv, self.out.dv
        self.out_dropped = 0
        self.prepared = 0                # magnetic updates prepared (snapshot restored, measurement evaluated)
        # bookkeeping
        self.initialized = False
        self.replaying = False          # a replay runs on the shadow
        self._pending = None            # a prepared magnetic update: (t_ref, q, R_ms, C, final)
        self.last_step_units = 0        # strapdown steps of the last ``step`` call
        self.rejects_in_row = 0
        self.accepted_in_row = 0
        self.last_update_t = 0
        self.last_flags = 0
        self.last_nis = 0.0
        self.updates = 0
        self.rejected = 0
        self.reinits = 0
        self.replays_lost = 0
        self.steps = 0
        # recovery: offsets kept across a restart (ACC, GYR and their covariance block)
        self._kb = np.zeros(6)
        self._kP = np.zeros((6, 6))
        self._kbv = memoryview(self._kb)
        self._kPv = memoryview(self._kP)
        self.kept = False
        self.kept_t = 0
        self.ever_initialised = False
        self.recovering = False         # restarted, no update accepted since (OUT_RECOVERED)
        self.recovery_reason = 0        # RECOVER_* of the pending or last restart
        self.recoveries = 0             # restarts after the first initialisation
        self.biases_kept = 0            # ... of which kept the offsets
        self.recorder = None       # optional offline hook (smoother); None on the board

    # ------------------------------------------------------------ the live state
    p = property(lambda self: self.st.p)
    v = property(lambda self: self.st.v)
    Th = property(lambda self: self.st.Th)
    ba = property(lambda self: self.st.ba)
    bg = property(lambda self: self.st.bg)
    P = property(lambda self: self.st.P)
    t_us = property(lambda self: self.st.t_us)
    pred = property(lambda self: self.st.pred)

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
        k = self.imu.push(t_us)          # kept for replay
        d = self._idv
        d[k, IMU_F], d[k, IMU_F + 1], d[k, IMU_F + 2] = fx, fy, fz
        d[k, IMU_W], d[k, IMU_W + 1], d[k, IMU_W + 2] = wx, wy, wz
        d[k, IMU_FSRC], d[k, IMU_FSRC + 1], d[k, IMU_FSRC + 2] = rx, ry, rz
        if not self.source_fixed:          # a fixed source keeps Phi = I (columns unused)
            for i in range(3):
                for j in range(3):
                    d[k, IMU_PHI + 3 * i + j] = Phi[i, j]
        st = self.st
        if not self.initialized:
            if self.snap_pending and t_us >= self.snap_t and not self.replaying:
                self._snapshot_aux(k, False)
            return False
        if t_us <= st.t_us:
            return False
        if t_us - st.t_us > self.prm.max_gap_us:
            # the stream broke off: the inertial state is not worth keeping (its offsets may be)
            self._keep_biases(st)
            self.recovery_reason = RECOVER_STREAM
            self.initialized = False
            self.snap_valid = False
            self._end_replay()
            return False
        self._advance(st, self.hist, k)
        self._output(t_us)
        return True

    def _advance(self, st: InsState, hist: Ring, k: int) -> int:
        """Propagate ``st`` to IMU slot ``k``'s time, splitting the step at a
        pending snapshot (taken if ``st`` is the authoritative state); append
        the poses to ``hist``. Returns the number of steps run (1 or 2)."""
        t = self._itv[k]
        t0 = st.t_us
        if self.snap_pending and t0 < self.snap_t <= t:
            ts = self.snap_t
            n = 0
            if ts > t0:
                self._propagate(st, k, t0, ts)
                st.t_us = ts
                self._history(st, hist, k)
                n = 1
            if st is self._auth:
                self._snapshot(st, k)
            if t > ts:
                self._propagate(st, k, ts, t)
                n += 1
        else:
            self._propagate(st, k, t0, t)
            n = 1
        st.t_us = t
        self._history(st, hist, k)
        return n

    # ------------------------------------------------------------ model
    def _step(self, k: int, t0: int, t1: int) -> None:
        """One step of the live state (``tools.commands.perf`` times it)."""
        self._propagate(self.st, k, t0, t1)

    def _propagate(self, st: InsState, k: int, t0: int, t1: int) -> None:
        """Strapdown and covariance step of ``st`` over ``[t0, t1]`` with the IMU
        samples of ring slots ``k - 1`` and ``k`` (trapezoidal in the rate
        and in the global-frame specific force: the samples are instantaneous
        values; inputs at ``t0`` / ``t1`` interpolated linearly between the
        two entries). Strapdown and error transition: ``estimate.strapdown``
        (eqs 6.1-6.4, 6.8, 6.17)."""
        dt = (t1 - t0) * 1e-6
        d = self._idv
        tv = self._itv
        tk = tv[k]
        kp = k - 1 if k > 0 else self._icap - 1
        tp = tv[kp]
        # interpolation weights of entry k at t0 and t1 (1: entry k alone)
        if len(self.imu) > 1 and tp < tk:
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
        ba = st._bav
        bg = st._bgv
        F, W, S = IMU_F, IMU_W, IMU_FSRC
        # the two entries, each element read once
        pfx, pfy, pfz, pwx, pwy, pwz = d[kp, F], d[kp, F + 1], d[kp, F + 2], d[kp, W], d[kp, W + 1], d[kp, W + 2]
        kfx, kfy, kfz, kwx, kwy, kwz = d[k, F], d[k, F + 1], d[k, F + 2], d[k, W], d[k, W + 1], d[k, W + 2]
        psx, psy, psz, ksx, ksy, ksz = d[kp, S], d[kp, S + 1], d[kp, S + 2], d[k, S], d[k, S + 1], d[k, S + 2]
        bax, bay, baz = ba[0], ba[1], ba[2]
        # inputs at t0 and t1 (offsets removed), the rate at mid-step
        f0x = b0 * pfx + a0 * kfx - bax
        f0y = b0 * pfy + a0 * kfy - bay
        f0z = b0 * pfz + a0 * kfz - baz
        f1x = b1 * pfx + a1 * kfx - bax
        f1y = b1 * pfy + a1 * kfy - bay
        f1z = b1 * pfz + a1 * kfz - baz
        am = 0.5 * (a0 + a1)
        bm = 1.0 - am
        wx = bm * pwx + am * kwx - bg[0]
        wy = bm * pwy + am * kwy - bg[1]
        wz = bm * pwz + am * kwz - bg[2]
        r0x, r0y, r0z = b0 * psx + a0 * ksx, b0 * psy + a0 * ksy, b0 * psz + a0 * ksz
        r1x, r1y, r1z = b1 * psx + a1 * ksx, b1 * psy + a1 * ksy, b1 * psz + a1 * ksz
        self._ins_step(st, k, t1, dt, f0x, f0y, f0z, f1x, f1y, f1z, wx, wy, wz, r0x, r0y, r0z, r1x, r1y, r1z)

    def _step_python(self, st: InsState, k: int, t1: int, dt: float, f0x, f0y, f0z, f1x, f1y, f1z,
                     wx, wy, wz, r0x, r0y, r0z, r1x, r1y, r1z) -> None:
        """The numeric body of :meth:`_propagate` (the reference of ``core/src/strapdown.c``
        ``ct_ins_propagate``): attitude, position and velocity, offset decay, eq 6.17's blocks
        and the covariance prediction."""
        ba = st._bav
        bg = st._bgv
        Th = st._Thv
        # specific force in G at t0 with the attitude at t0, at t1 with the attitude at t1
        g0x, g0y, g0z = to_nav(Th, f0x, f0y, f0z)
        self.sd.rotate(st.Th, wx * dt, wy * dt, wz * dt)
        g1x, g1y, g1z = to_nav(Th, f1x, f1y, f1z)
        integrate_pv(st._pv, st._vv, dt, g0x - r0x, g0y - r0y, g0z - r0z, g1x - r1x, g1y - r1y, g1z - r1z)
        if dt != st.dt_last:
            self._set_dt(st, dt)
        ka = st.ka
        kg = st.kg
        ba[0] *= ka
        ba[1] *= ka
        ba[2] *= ka
        bg[0] *= kg
        bg[1] *= kg
        bg[2] *= kg
        transition_nav(st._Av, dt, Th, 0.5 * (g0x + g1x), 0.5 * (g0y + g1y), 0.5 * (g0z + g1z))
        st.pred.predict(st.P)
        self.steps += 1
        if self.recorder is not None and st is self._auth:
            self.recorder.on_step(self, st, k, t1)

    def _step_compiled(self, st: InsState, k: int, t1: int, dt: float, f0x, f0y, f0z, f1x, f1y, f1z,
                       wx, wy, wz, r0x, r0y, r0z, r1x, r1y, r1z) -> None:
        """:meth:`_step_python` on the compiled core (``InsState.ck``, bound at start-up): the
        step's static blocks written first (they depend on ``dt`` alone, not on the step's
        results), then one call does the rest."""
        if dt != st.dt_last:
            self._set_dt(st, dt)
        st.ck.propagate(dt, f0x, f0y, f0z, f1x, f1y, f1z, wx, wy, wz, r0x, r0y, r0z, r1x, r1y, r1z,
                        st.ka, st.kg)
        st.pred.after_predict(st.P)
        self.steps += 1
        if self.recorder is not None and st is self._auth:
            self.recorder.on_step(self, st, k, t1)

    def _set_dt(self, st: InsState, dt: float) -> None:
        """The parts of ``A`` and ``Q`` that depend on the step alone
        (eqs 6.10, 6.13-6.14), rewritten only when the step changes (the white
        magnetic states' noise has no step in it: :class:`InsState` writes it)."""
        k = self._dtk
        st.dt_last = dt
        ka = math.exp(-dt / k[0]) if k[0] > 0.0 else 1.0
        kg = math.exp(-dt / k[1]) if k[1] > 0.0 else 1.0
        st.ka = ka
        st.kg = kg
        transition_static(st._Av, dt, ka, kg)
        Q = st._Qf
        qv = k[2] * dt * dt
        qo = (k[3] * dt) ** 2
        qa = k[4] * dt
        qg = k[5] * dt
        v, o, a, g = self._q_diag
        Q[v[0]] = Q[v[1]] = Q[v[2]] = qv
        Q[o[0]] = Q[o[1]] = Q[o[2]] = qo
        Q[a[0]] = Q[a[1]] = Q[a[2]] = qa
        Q[g[0]] = Q[g[1]] = Q[g[2]] = qg

    def _history(self, st: InsState, hist: Ring, k: int) -> None:
        """Append ``st``'s pose in the source frame to ``hist``: ``p_M = Phi^T p``,
        ``R_MS = Phi^T Theta`` (Phi of IMU slot ``k``)."""
        d = self._idv
        h = hist.push(st.t_us)
        hd = hist.dv
        p = st._pv
        Th = st._Thv
        P0, R0 = HIST_P, HIST_R
        if self.source_fixed:
            hd[h, P0], hd[h, P0 + 1], hd[h, P0 + 2] = p[0], p[1], p[2]
            for i in range(3):
                hd[h, R0 + 3 * i], hd[h, R0 + 3 * i + 1], hd[h, R0 + 3 * i + 2] = Th[i, 0], Th[i, 1], Th[i, 2]
        else:
            F = IMU_PHI
            for i in range(3):
                f0, f1, f2 = d[k, F + i], d[k, F + 3 + i], d[k, F + 6 + i]     # column i of Phi
                hd[h, P0 + i] = f0 * p[0] + f1 * p[1] + f2 * p[2]
                for j in range(3):
                    hd[h, R0 + 3 * i + j] = f0 * Th[0, j] + f1 * Th[1, j] + f2 * Th[2, j]

    def _output(self, t_us: int) -> None:
        """Queue the fused pose (source frame) with its variances: position
        ``diag(Phi^T P_pp Phi)``, orientation in the sensor frame
        ``diag(R^T P_oo R)`` with ``R = Theta`` (as the POSE message defines)."""
        out = self.out
        if out.full:
            self.out_dropped += 1
            return
        slot = out.push(t_us)
        od = self._odv
        hist = self.hist
        h = hist.peek(0)
        hd = hist.dv
        od[slot, OUT_P], od[slot, OUT_P + 1], od[slot, OUT_P + 2] = hd[h, HIST_P], hd[h, HIST_P + 1], hd[h, HIST_P + 2]
        _quat_into(hd, h, od, slot)
        k = self.imu.peek(0)
        d = self._idv
        st = self.st
        P = st._Pv
        Th = st._Thv
        p0 = POS.start
        o0 = ORI.start
        # orientation: diag(Theta^T P_oo Theta) = sum_i Theta[i, c] (P_oo Theta)[i, c]
        o00, o01, o02 = P[o0, o0], P[o0, o0 + 1], P[o0, o0 + 2]
        o11, o12, o22 = P[o0 + 1, o0 + 1], P[o0 + 1, o0 + 2], P[o0 + 2, o0 + 2]
        for c in range(3):
            x, y, z = Th[0, c], Th[1, c], Th[2, c]
            od[slot, OUT_VAR_O + c] = (x * (o00 * x + o01 * y + o02 * z) + y * (o01 * x + o11 * y + o12 * z)
                                       + z * (o02 * x + o12 * y + o22 * z))
        if self.source_fixed:
            od[slot, OUT_VAR_P], od[slot, OUT_VAR_P + 1], od[slot, OUT_VAR_P + 2] = (
                P[p0, p0], P[p0 + 1, p0 + 1], P[p0 + 2, p0 + 2])
        else:
            q00, q01, q02 = P[p0, p0], P[p0, p0 + 1], P[p0, p0 + 2]
            q11, q12, q22 = P[p0 + 1, p0 + 1], P[p0 + 1, p0 + 2], P[p0 + 2, p0 + 2]
            F = IMU_PHI
            for c in range(3):
                x, y, z = d[k, F + c], d[k, F + 3 + c], d[k, F + 6 + c]      # column c of Phi
                od[slot, OUT_VAR_P + c] = (x * (q00 * x + q01 * y + q02 * z) + y * (q01 * x + q11 * y + q12 * z)
                                           + z * (q02 * x + q12 * y + q22 * z))
        status = 0
        age = t_us - self.last_update_t
        if age > self.prm.stale_us:
            status |= OUT_STALE
        if age > self.prm.dead_reckon_after_us:
            status |= OUT_DEAD_RECKONING
            if age > self.prm.dead_reckon_limit_us:
                status |= OUT_LOST
        if self.recovering:
            status |= OUT_RECOVERED
        if self.last_flags & ~(FUS_INITIALISED | FUS_GAP_REINIT):
            status |= OUT_INCONSISTENT
        od[slot, OUT_STATUS] = status

    def pop_output(self) -> int:
        """Slot of the oldest queued pose in ``out_t`` / ``out_d`` (rows
        ``OUT_*``), or -1; call :meth:`release_output` when sent."""
        return self.out.slot(0) if len(self.out) else -1

    def release_output(self) -> None:
        self.out.pop()

    @property
    def out_t(self):
        return self.out.t

    @property
    def out_d(self):
        return self.out.d

    # ------------------------------------------------------------ snapshot
    def _snapshot_aux(self, k: int, full: bool) -> None:
        """Source orientation and Xi at t_ref (all that initialisation needs);
        ``full``: the inertial state was kept with them."""
        d = self._idv
        S = self._sPhiv
        for i in range(3):
            for j in range(3):
                S[i, j] = (1.0 if i == j else 0.0) if self.source_fixed else d[k, IMU_PHI + 3 * i + j]
        if self.xi is not None and self.xi.initialized:
            np.copyto(self._sXi, self.xi.R)
            self.xi.theta_covariance_global(self._sXiPv)
            np.copyto(self._sXiB, self.xi.bias)
            self.snap_xi = True
        else:
            self.snap_xi = False
        self.snap_pending = False
        self.snap_valid = True
        self.snap_initialized = full

    def _snapshot(self, st: InsState, k: int) -> None:
        self.sn.copy_from(st)
        self._snapshot_aux(k, True)

    def _ring_covers(self, t_us: int) -> bool:
        imu = self.imu
        return len(imu) > 0 and imu.tv[imu.slot(0)] <= t_us

    # ------------------------------------------------------------ update
    def magnetic_update(self, t_ref_us: int, q, R_ms, C, final: bool = True) -> int:
        """:meth:`begin_magnetic_update` and the whole replay in one call (a
        replay still running is finished first). Returns the health flags."""
        self.finish()
        flags = self.begin_magnetic_update(t_ref_us, q, R_ms, C, final)
        self.finish()
        return flags

    def finish(self) -> None:
        """Run the replay in progress (if any) to its end."""
        while not self.step(2 * self._icap):
            pass

    def begin_magnetic_update(self, t_ref_us: int, q, R_ms, C, final: bool = True) -> int:
        """Fuse one magnetic solution referring to ``t_ref_us``: position
        ``q`` (3, source frame), orientation ``R_ms`` (3x3, sensor to source)
        and their covariance ``C`` (6x6, ``(p, dtheta)`` as ``solver``, rows
        ``layout.POSE_POS``, ``POSE_ORI``). :meth:`prepare_magnetic_update`
        and :meth:`apply_magnetic_update` in one call (a tick may do them in
        two). Initialises the filter when needed. The update is applied to the
        shadow state at ``t_ref``; the replay to the newest IMU sample is left
        to :meth:`step` (none is needed when the state did not change: a
        rejected solution). Returns health flags (ekf flags, ``FUS_*``); never
        raises. With ``final=False`` a rejected solution leaves the snapshot
        in place (and counts nothing), so the caller can offer another
        solution of the same burst. ``FUS_BUSY``: the previous replay is still
        running (nothing done; call again once :meth:`step` has returned True)."""
        flags = self.prepare_magnetic_update(t_ref_us, q, R_ms, C, final)
        if flags != FUS_PREPARED:
            return flags
        return self.apply_magnetic_update()

    def prepare_magnetic_update(self, t_ref_us: int, q, R_ms, C, final: bool = True) -> int:
        """The first half of :meth:`begin_magnetic_update`: restore the
        snapshot at ``t_ref`` into the shadow state and evaluate the
        measurement model (``q``, ``R_ms``, ``C`` are read now). Returns
        ``FUS_PREPARED`` (then call :meth:`apply_magnetic_update`), or the
        final flags when it is already decided (busy, no snapshot,
        initialisation)."""
        if self.replaying:
            return FUS_BUSY
        if not (self.snap_valid and self.snap_t == t_ref_us and self._ring_covers(t_ref_us)):
            self.last_flags = FUS_NO_SNAPSHOT
            return FUS_NO_SNAPSHOT
        self.snap_valid = False
        sh = self.sh
        running = self.initialized and self.snap_initialized
        gap = running and t_ref_us - self.last_update_t > self.prm.dead_reckon_limit_us
        if not running or gap:
            if self.model != 1 and not self.snap_xi:
                self.last_flags = FUS_NOT_INITIALISED
                return FUS_NOT_INITIALISED
            flags = FUS_INITIALISED
            if gap:                     # too long to bridge: restart from the magnetic solution
                self._keep_biases(self.sn)
                self.recovery_reason = RECOVER_GAP
                flags |= FUS_GAP_REINIT
            self._initialize(sh, t_ref_us, q, R_ms, C)
            self.last_flags = flags
            self.last_update_t = t_ref_us
            self._start_replay()
            return flags
        sh.copy_from(self.sn)
        self._shist.copy_from(self.hist)
        self._shist.drop_newer_than(t_ref_us)
        self._measurement(sh, q, R_ms, C)
        self._pending = (t_ref_us, q, R_ms, C, final)
        self.prepared += 1
        return FUS_PREPARED

    def apply_magnetic_update(self) -> int:
        """The second half of :meth:`begin_magnetic_update`: gate, gain and
        Joseph update of the prepared measurement, the correction of the
        shadow state and the start of its replay. Returns the health flags."""
        t_ref_us, q, R_ms, C, final = self._pending
        self._pending = None
        sh = self.sh
        if self.recorder is not None:
            self.recorder.on_prior(self, sh)
        flags = self.upd.update(sh.P)
        self.last_nis = self.upd.nis
        self.last_flags = flags
        if flags == EKF_OK:
            self._correct(sh, self.upd._dxv)
            self.rejects_in_row = 0
            self.accepted_in_row += 1
            self.updates += 1
            self.recovering = False
            self.last_update_t = t_ref_us
            if self.recorder is not None:
                self.recorder.on_update(self, sh, self.upd.dx)
        elif not final:
            self.snap_valid = True
            return flags
        else:
            self.rejected += 1
            self.rejects_in_row += 1
            self.accepted_in_row = 0
            if not (self.rejects_in_row >= self.prm.reinit_after and (self.model == 1 or self.snap_xi)):
                return flags            # the state is unchanged: nothing to replay
            if self.recorder is not None:
                self.recorder.on_rewind(self, t_ref_us)
            self._keep_biases(sh)       # sh: the prior at t_ref
            self.recovery_reason = RECOVER_DISAGREE
            self._initialize(sh, t_ref_us, q, R_ms, C)
            self.reinits += 1
            self.rejects_in_row = 0
            flags |= FUS_REINITIALISED
            self.last_update_t = t_ref_us
            self.last_flags = flags
        self._start_replay()
        return flags

    def _start_replay(self) -> None:
        self.replaying = True
        self._auth = self.sh
        if self.recorder is not None:
            self.recorder.on_rewind(self, self.sh.t_us)

    def _end_replay(self) -> None:
        self.replaying = False
        self._auth = self.st

    def step(self, budget_replay_steps: int) -> bool:
        """Replay IMU samples on the shadow state, at most
        ``max_replay_steps_per_step(budget)`` strapdown and covariance steps;
        when the shadow reaches the newest IMU sample it becomes the live
        state. Returns True when no replay is left (also when none was
        running)."""
        self.last_step_units = 0
        if not self.replaying:
            return True
        sh = self.sh
        imu = self.imu
        units = 0
        while True:
            i = imu.index_at_or_after(sh.t_us + 1)
            if i >= len(imu):
                self._swap()
                self.last_step_units = units
                return True
            if units >= budget_replay_steps:
                self.last_step_units = units
                return False
            if i == 0:
                # the sample before the next one left the ring: the replay cannot go on
                self._end_replay()
                self.replays_lost += 1
                self.last_flags |= FUS_REPLAY_LOST
                self.last_step_units = units
                return True
            units += self._advance(sh, self._shist, imu.slot(i))

    def _swap(self) -> None:
        """The shadow has caught up: it becomes the live state."""
        self.st.copy_from(self.sh)
        self.hist.copy_from(self._shist)
        self.initialized = True
        self._end_replay()

    def _measurement(self, st: InsState, q, R_ms, C) -> None:
        """Innovation (eqs 6.18-6.21) at ``st`` and the white blocks of its ``P``."""
        y = self._yv
        Phi = self._sPhiv
        p = st._pv
        Th = st._Thv
        P = st._Pv
        s = self.prm.mag_var_scale
        # position: Phi q - p
        z0 = self._zp
        for i in range(3):
            y[z0 + i] = Phi[i, 0] * q[0] + Phi[i, 1] * q[1] + Phi[i, 2] * q[2] - p[i]
        # Psi = Phi R_ms
        psi = self._E
        np.matmul(self._sPhi, R_ms, out=psi)
        Psi = self._Ev
        # white-state covariances: Phi C_pp Phi^T, Psi C_tt Psi^T, Phi C_pt Psi^T
        q0, s0 = QM.start, PSI.start
        cp, co = POSE_POS.start, POSE_ORI.start
        for i in range(3):
            for j in range(3):
                cpp = cpt = ctt = 0.0
                for a in range(3):
                    fa = Phi[i, a]
                    pa = Psi[i, a]
                    for b in range(3):
                        cpp += fa * C[cp + a, cp + b] * Phi[j, b]
                        cpt += fa * C[cp + a, co + b] * Psi[j, b]
                        ctt += pa * C[co + a, co + b] * Psi[j, b]
                P[q0 + i, q0 + j] = cpp * s
                P[q0 + i, s0 + j] = cpt * s
                P[s0 + j, q0 + i] = cpt * s
                P[s0 + i, s0 + j] = ctt * s
        if self._zpsi >= 0:
            _log_diff(Psi, Th, y, self._zpsi)
        if self._zxi >= 0:
            _log_diff(self._sXiv, Th, y, self._zxi)
            x0 = XI.start
            xs = self.prm.xi_var_scale
            fl = self.prm.xi_sigma_floor ** 2
            fh = self.prm.xi_heading_sigma_floor ** 2
            XP = self._sXiPv
            for i in range(3):
                for j in range(3):
                    P[x0 + i, x0 + j] = XP[i, j] * xs
                P[x0 + i, x0 + i] += fh if i == 2 else fl
        if self._zpsi < 0:
            # the magnetic orientation is not used: keep its white block inert
            for i in range(3):
                for j in range(3):
                    P[s0 + i, s0 + j] = (self.prm.psi_sigma ** 2) if i == j else 0.0
                    P[q0 + i, s0 + j] = 0.0
                    P[s0 + j, q0 + i] = 0.0

    def _correct(self, st: InsState, dx) -> None:
        p = st._pv
        v = st._vv
        ba = st._bav
        bg = st._bgv
        for i in range(3):
            p[i] += dx[POS.start + i]
            v[i] += dx[VEL.start + i]
            ba[i] += dx[ACC.start + i]
            bg[i] += dx[GYR.start + i]
        o = ORI.start
        exp_rotvec(dx[o], dx[o + 1], dx[o + 2], self._Ev)
        np.matmul(self._E, st.Th, out=self._T)
        np.copyto(st.Th, self._T)

    def _initialize(self, st: InsState, t_ref_us: int, q, R_ms, C) -> None:
        """``st`` at ``t_ref``: position from the magnetic solution, velocity
        zero, orientation from Xi (models 2, 3) or the magnetic one (model 1),
        gyroscope offset from the ch. 2 filter; its pose history starts anew."""
        prm = self.prm
        Phi = self._sPhiv
        p = st._pv
        for i in range(3):
            p[i] = Phi[i, 0] * q[0] + Phi[i, 1] * q[1] + Phi[i, 2] * q[2]
        st.v.fill(0.0)
        st.ba.fill(0.0)
        st.P.fill(0.0)
        P = st._Pv
        use_xi = self.model != 1 and self.snap_xi
        if use_xi:
            np.copyto(st.Th, self._sXi)
            np.copyto(st.bg, self._sXiB)
        else:
            np.matmul(self._sPhi, R_ms, out=st.Th)
            st.bg.fill(0.0)
        Th = st._Thv
        p0, o0 = POS.start, ORI.start
        cp, co = POSE_POS.start, POSE_ORI.start
        for i in range(3):
            for j in range(3):
                cpp = 0.0
                coo = 0.0
                for a in range(3):
                    for b in range(3):
                        cpp += Phi[i, a] * C[cp + a, cp + b] * Phi[j, b]
                        coo += Th[i, a] * C[co + a, co + b] * Th[j, b]
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
        if self.ever_initialised:
            self.recoveries += 1
            self.recovering = True
            if self.kept and self._restore_biases(st, t_ref_us):
                self.biases_kept += 1
        self.kept = False
        self.ever_initialised = True
        st.t_us = t_ref_us
        self.rejects_in_row = 0
        self.accepted_in_row = 0
        self._shist.clear()
        if self.recorder is not None:
            self.recorder.on_init(self, st)

    def _keep_biases(self, st: InsState) -> None:
        """Remember ``st``'s offsets and their covariance block (rows ``ACC``,
        ``GYR``) for the next restart, when credible: every offset within
        ``bias_gate_sigmas`` of its prior (a diverged state has run them off)."""
        prm = self.prm
        self.kept = False
        if not prm.keep_biases:
            return
        ga = prm.bias_gate_sigmas * prm.acc_bias_sigma
        gg = prm.bias_gate_sigmas * prm.gyro_bias_sigma
        ba, bg = st._bav, st._bgv
        for i in range(3):
            if not (abs(ba[i]) <= ga and abs(bg[i]) <= gg):
                return
        kb, kP, P = self._kbv, self._kPv, st._Pv
        a0, g0 = ACC.start, GYR.start
        for i in range(3):
            kb[i] = ba[i]
            kb[3 + i] = bg[i]
        for i in range(6):
            ri = a0 + i if i < 3 else g0 + i - 3
            for j in range(6):
                kP[i, j] = P[ri, a0 + j if j < 3 else g0 + j - 3]
        self.kept = True
        self.kept_t = st.t_us

    def _restore_biases(self, st: InsState, t_us: int) -> bool:
        """The kept offsets into ``st`` (just initialised at ``t_us``): the
        nominal values decayed by eqs 6.13-6.14 over the time since they were
        kept, the variances grown by the random walk (``sigma_rw^2 dt``); not
        used (False) when a grown variance is no smaller than the prior's."""
        prm = self.prm
        dt = max(0, t_us - self.kept_t) * 1e-6
        qa = prm.acc_bias_rw * prm.acc_bias_rw * dt
        qg = prm.gyro_bias_rw * prm.gyro_bias_rw * dt
        kP = self._kPv
        for i in range(3):
            if kP[i, i] + qa >= prm.acc_bias_sigma ** 2 or kP[3 + i, 3 + i] + qg >= prm.gyro_bias_sigma ** 2:
                return False
        ka = math.exp(-dt / prm.acc_bias_tau_s) if prm.acc_bias_tau_s > 0.0 else 1.0
        kg = math.exp(-dt / prm.gyro_bias_tau_s) if prm.gyro_bias_tau_s > 0.0 else 1.0
        kb, P = self._kbv, st._Pv
        ba, bg = st._bav, st._bgv
        a0, g0 = ACC.start, GYR.start
        for i in range(3):
            ba[i] = ka * kb[i]
            bg[i] = kg * kb[3 + i]
        for i in range(6):
            ri = a0 + i if i < 3 else g0 + i - 3
            si = ka if i < 3 else kg
            for j in range(6):
                sj = ka if j < 3 else kg
                P[ri, a0 + j if j < 3 else g0 + j - 3] = si * sj * kP[i, j]
            P[ri, ri] += qa if i < 3 else qg
        return True

    # ------------------------------------------------------------ queries
    def pose_at(self, t_us: int, out_p, out_R) -> bool:
        """Inertial pose in the source frame at ``t_us`` (linear
        interpolation of the live history; ``out_R`` is not re-orthonormalised,
        which is second order in the step rotation). False when ``t_us`` is
        outside the history."""
        hist = self.hist
        n = len(hist)
        if n < 2:
            return False
        i = hist.index_at_or_after(t_us)
        if i >= n:
            return False
        ht = hist.tv
        if i == 0:
            if ht[hist.slot(0)] != t_us:
                return False
            i = 1
        prev = hist.slot(i - 1)
        k = hist.slot(i)
        t0 = ht[prev]
        tk = ht[k]
        a = (t_us - t0) / (tk - t0) if tk > t0 else 1.0
        b = 1.0 - a
        hd = hist.dv
        for c in range(3):
            out_p[c] = b * hd[prev, HIST_P + c] + a * hd[k, HIST_P + c]
        for i2 in range(3):
            for j in range(3):
                c = HIST_R + 3 * i2 + j
                out_R[i2, j] = b * hd[prev, c] + a * hd[k, c]
        return True

    def velocity_sigma(self) -> float:
        """rms velocity uncertainty per axis, m/s."""
        P = self.st._Pv
        v0 = VEL.start
        return math.sqrt(max(P[v0, v0] + P[v0 + 1, v0 + 1] + P[v0 + 2, v0 + 2], 0.0) / 3.0)

    def speed_squared(self) -> float:
        v = self.st._vv
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
    ``h`` into the output row ``slot``."""
    r = HIST_R
    w, x, y, z = quat_from_elements(hd[h, r], hd[h, r + 1], hd[h, r + 2], hd[h, r + 3], hd[h, r + 4],
                                    hd[h, r + 5], hd[h, r + 6], hd[h, r + 7], hd[h, r + 8])
    o = OUT_Q
    od[slot, o], od[slot, o + 1], od[slot, o + 2], od[slot, o + 3] = w, x, y, z
