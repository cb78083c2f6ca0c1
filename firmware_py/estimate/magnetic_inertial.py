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
while credible (``fusion_recovery.Recovery.keep_biases``, ``restore_biases``: decayed and
with the random-walk variance of eqs 6.13-6.14 added for the time between).
Outputs older than ``dead_reckon_after_us`` since the last accepted update
carry ``OUT_DEAD_RECKONING``, older than ``dead_reckon_limit_us`` ``OUT_LOST``.

Composition. :class:`FusionFilter` holds the live and shadow states and runs
the delayed update and its replay; it is built, once, from components of one
job each: the prediction (``fusion_prediction.InertialPrediction``: IMU ring,
strapdown and covariance step), the source frame (``fusion_state.MovingSource``
or ``FixedSource``), the snapshot at t_ref (``fusion_snapshot.Snapshot``), the
measurement model (``fusion_measurement``: model 1, or models 2 and 3 with
``Xi``), the (re)start and kept offsets (``fusion_recovery.Recovery``) and the
outputs (``fusion_output.PoseHistory``, ``PoseOutput``). Every update goes
through the one update shape, ``ekf.KalmanUpdate``.

All buffers are created in ``__init__``; a step allocates no numpy array.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import EKF_OK, SYMMETRIZE_EVERY, KalmanUpdate
from coiltrack.firmware.estimate.fusion_measurement import make_measurement_model
from coiltrack.firmware.estimate.fusion_output import (OUT_DEAD_RECKONING, OUT_FIELDS, OUT_INCONSISTENT,  # noqa: F401
                                                      OUT_LOST, OUT_P, OUT_Q, OUT_RECOVERED, OUT_STALE,
                                                      OUT_STATUS, OUT_VAR_O, OUT_VAR_P, PoseHistory, PoseOutput)
from coiltrack.firmware.estimate.fusion_prediction import InertialPrediction
from coiltrack.firmware.estimate.fusion_recovery import Recovery
from coiltrack.firmware.estimate.fusion_replay import CompiledReplay, CompiledUpdate
from coiltrack.firmware.estimate.fusion_snapshot import Snapshot
from coiltrack.firmware.estimate.fusion_state import (HIST_FIELDS, HIST_P, HIST_R, IMU_F, IMU_FIELDS,  # noqa: F401
                                                     IMU_FSRC, IMU_PHI, IMU_W, FixedSource, InsState,
                                                     MovingSource)

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

#: strapdown + covariance steps one replayed IMU sample can cost (split at a snapshot)
MAX_STEPS_PER_SAMPLE = 2

#: ``FusionFilter.fs`` (int64): initialised (0/1), the last update's time (us) and flags, a recorder
#: attached (0/1), a replay running on the shadow (0/1): the per-sample state the compiled one-call
#: IMU sample reads in place (``core/include/ct_fusimu.h`` ``CT_FF_*``)
FS_INIT, FS_UPDATE_T, FS_FLAGS, FS_RECORDER, FS_REPLAYING, FS_N = range(6)


def _fs_int(i: int, as_bool: bool = False):
    """A property over entry ``i`` of ``self._fsv`` (0/1 for a bool)."""
    def fset(self, v) -> None:
        self._fsv[i] = (1 if v else 0) if as_bool else v
    if as_bool:
        return property(lambda self: self._fsv[i] != 0, fset)
    return property(lambda self: self._fsv[i], fset)


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
            measurement_model=cfg.fusion.measurement_model, acc_noise=cfg.imu.imu_acc_sigma, gyro_noise=cfg.imu.imu_gyro_sigma,
            source_acc_noise=(cfg.body.source_acc_sigma or cfg.imu.imu_acc_sigma) if source_imu else 0.0,
            acc_bias_sigma=cfg.imu.imu_acc_bias_sigma, gyro_bias_sigma=cfg.imu.imu_gyro_bias_sigma,
            acc_bias_rw=cfg.imu.imu_acc_bias_rw, gyro_bias_rw=cfg.imu.imu_gyro_bias_rw,
            acc_bias_tau_s=cfg.fusion.bias_tau_s, gyro_bias_tau_s=cfg.fusion.bias_tau_s,
            velocity0_sigma=cfg.adaptive.init_sigma_vel, gate_probability=cfg.fusion.fusion_gate_probability,
            reinit_after=cfg.fusion.fusion_reinit_after, xi_var_scale=cfg.fusion.xi_var_scale, xi_sigma_floor=cfg.fusion.xi_sigma_floor,
            xi_heading_sigma_floor=cfg.fusion.xi_heading_sigma_floor, mag_var_scale=cfg.fusion.mag_var_scale,
            qm_sigma=cfg.fusion.qm_sigma, psi_sigma=cfg.fusion.psi_sigma, meas_sigma=cfg.fusion.meas_sigma,
            max_gap_us=max(cfg.imu.imu_timeout_us, int(3e6 / cfg.imu.imu_rate_hz)), stale_us=cfg.link.stale_us,
            dead_reckon_after_us=cfg.recovery.dead_reckon_after_us, dead_reckon_limit_us=cfg.recovery.dead_reckon_limit_us,
            keep_biases=cfg.recovery.recovery_keep_biases, bias_gate_sigmas=cfg.recovery.recovery_bias_gate_sigmas)
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


class FilterView:
    """The reads of a :class:`FusionFilter`: its live state, its parts and the queries on them
    (each delegates to the part that owns the value)."""

    # ------------------------------------------------------------ the live state, the parts
    p = property(lambda self: self.st.p)
    v = property(lambda self: self.st.v)
    Th = property(lambda self: self.st.Th)
    ba = property(lambda self: self.st.ba)
    bg = property(lambda self: self.st.bg)
    P = property(lambda self: self.st.P)
    t_us = property(lambda self: self.st.t_us)
    pred = property(lambda self: self.st.pred)
    sn = property(lambda self: self.snap.st)
    hist = property(lambda self: self.history.live)
    source_fixed = property(lambda self: self.frame.fixed)
    steps = property(lambda self: self.prediction.steps)
    imu_t = property(lambda self: self.imu.t)
    imu_d = property(lambda self: self.imu.d)
    out_t = property(lambda self: self.output.out.t)
    out_d = property(lambda self: self.output.out.d)
    out_tv = property(lambda self: self.output.out.tv)
    out_dv = property(lambda self: self.output.out.dv)
    out_dropped = property(lambda self: self.output.dropped)
    recoveries = property(lambda self: self.recovery.recoveries)
    biases_kept = property(lambda self: self.recovery.biases_kept)
    recovery_reason = property(lambda self: self.recovery.recovery_reason)
    initialized = _fs_int(FS_INIT, True)
    last_update_t = _fs_int(FS_UPDATE_T)      # the last accepted update's time (us)
    last_flags = _fs_int(FS_FLAGS)            # the last update's FUS_* flags
    replaying = _fs_int(FS_REPLAYING, True)   # a replay runs on the shadow (the live state takes no snapshot)

    # ------------------------------------------------------------ queries
    def pose_at(self, t_us: int, out_p, out_R) -> bool:
        """Inertial pose in the source frame at ``t_us`` (``PoseHistory.pose_at``)."""
        return self.history.pose_at(t_us, out_p, out_R)

    def velocity_sigma(self) -> float:
        """rms velocity uncertainty per axis of the live state, m/s."""
        return self.st.velocity_sigma()

    def speed_squared(self) -> float:
        return self.st.speed_squared()

    def nees(self, p_true_g, R_true_g, v_true_g=None) -> float:
        """``InsState.nees`` of the live state (tests; allocates)."""
        return self.st.nees(p_true_g, R_true_g, v_true_g)


class FusionFilter(FilterView):
    """The thesis ch. 6 complementary error filter (see module docstring).

    Parameters
    ----------
    params : FusionParams
    xi_filter : orientation.OrientationFilter, optional
        The sensor's ch. 2 filter (its ``R``, covariance and gyroscope offset), needed by
        measurement models 2 and 3 and used to initialise.
    imu_capacity, history_capacity, output_capacity : int
        Ring sizes (IMU samples kept for replay, pose history for motion compensation, poses
        waiting to be sent).
    fixed_source : bool
        The source does not move (``Phi = I``): history and output skip the frame change
        (``fusion_state.FixedSource``, chosen here once).
    core : coiltrack.firmware.core.Core
        The numeric core, chosen at composition.

    The nominal state and covariance of the live state are ``p``, ``v``, ``Th``, ``ba``, ``bg``,
    ``P`` (arrays, fixed for the filter's life), ``t_us``; ``pred`` is its ``CovariancePredict``.
    """

    def __init__(self, params: FusionParams, xi_filter=None, imu_capacity: int = 128,
                 history_capacity: int = 128, output_capacity: int = 16, fixed_source: bool = False,
                 core=_DEFAULT_CORE):
        self.fs = np.zeros(FS_N, dtype=np.int64)
        self._fsv = memoryview(self.fs)
        self.prm = params
        self.meas = make_measurement_model(params, xi_filter)
        self.layout = self.meas.layout
        self.n = n = self.layout.n
        self.frame = FixedSource() if fixed_source else MovingSource()
        white, white_q = self.meas.white(params)
        self.st = InsState(n, white, white_q, core)        # live
        self.sh = InsState(n, white, white_q, core)        # shadow: the replay of a delayed update
        self._auth = self.st                # the state that takes snapshots and is recorded
        self.snap = Snapshot(n, self.frame, xi_filter, core)
        self.prediction = InertialPrediction(params, n, self.frame, imu_capacity, self.st.ck is not None, core,
                                             (self.st, self.sh))
        self.imu = self.prediction.imu
        self.zlayout = self.meas.zlayout
        self.m = self.zlayout.n
        self.upd = KalmanUpdate(n, self.m, params.gate_probability, core)
        self.meas.fill_constant(memoryview(self.upd.H), memoryview(self.upd.R), params)
        self.recovery = Recovery(params, self.meas)
        self.history = PoseHistory(history_capacity, core)
        self.output = PoseOutput(params, output_capacity, self.frame, core, self.st, self.imu, self.history.live)
        #: the measurement's evaluation (shadow, snapshot) and the replay's kernel (None: :meth:`step`'s loop)
        self._evaluate = self.meas.bind(self.sh, self.snap, self.upd.y, core)
        self._replay_ck = (CompiledReplay(self.sh, self.prediction, self.history.shadow, self.snap, self.frame,
                                          core.ext) if self.sh.ck is not None else None)
        #: the live step split at a pending snapshot (``_advance``): that kernel on the live state (None: Python)
        self._live_ck = (CompiledReplay(self.st, self.prediction, self.history.live, self.snap, self.frame,
                                        core.ext) if self.st.ck is not None else None)
        if CompiledUpdate.fits(self):      # the delayed update's two halves, one compiled call each
            self._restore, self._update_shadow = CompiledUpdate(self, core.ext).methods()
        self.snap.bind(self.imu.d, core)
        self._live_take = self._live_ck is not None and self._live_ck.bind_snapshot()
        self.prepared = 0                # magnetic updates prepared (snapshot restored, measurement evaluated)
        self.initialized = False
        self.replaying = False          # a replay runs on the shadow (``fs``)
        self._pending = None            # a prepared magnetic update: (t_ref, q, R_ms, C, final)
        self.last_step_units = 0        # strapdown steps of the last ``step`` call
        self.rejects_in_row = self.accepted_in_row = self.last_update_t = self.last_flags = 0
        self.last_nis = 0.0
        self.updates = self.rejected = self.reinits = self.replays_lost = 0     # counters
        self.recorder = None       # optional offline hook (smoother); None on the board
        if self.st.ck is not None:
            self.prediction.bind_live(self.st, self.history.live, self.output._ck)
            self.push_imu = self._push_imu_compiled
            self.pose_at = self.history.pose_at         # (the kernel's method: PoseHistory.pose_at)

    def attach_recorder(self, recorder) -> None:
        """Attach an offline recorder (``estimate.smoother.FusionRecorder``; host only). Its
        per-step hook runs in the Python replay only: the compiled one is not used from now on."""
        self.recorder = recorder
        self._fsv[FS_RECORDER] = 1
        self._replay_ck = self._live_ck = None

    # ------------------------------------------------------------ inputs
    def schedule_snapshot(self, t_ref_us: int) -> None:
        """Keep the state at ``t_ref_us`` (the instant the next magnetic solution will refer to)."""
        self.snap.schedule(t_ref_us)

    def push_imu(self, t_us: int, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi) -> bool:
        """One sensor IMU sample (specific force m/s^2, rate rad/s, sensor frame) with the source's specific force in
        ``G`` (``r*``) and the source orientation ``Phi`` (3x3, memoryview or array). Returns True when a fused pose was
        produced (put in the output ring)."""
        k = self.prediction.push(t_us, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi)    # kept for replay
        return self._after_push(t_us, k)

    def _push_imu_compiled(self, t_us: int, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi) -> bool:
        """:meth:`push_imu` on the compiled core: a step not split by a snapshot, not recorded, not followed
        by ``P``'s symmetrisation (the queued variances read ``P``) and with room in the output queue is one
        call (``InertialPrediction.sample``); any other goes through :meth:`_after_push`."""
        st = self.st
        t0 = st.t_us
        out = self.output.out
        if not self.initialized or t_us <= t0 or t_us - t0 > self.prm.max_gap_us or self.snap.due(t0, t_us) \
                or self.recorder is not None or out.full or (st.pred.count + 1) % SYMMETRIZE_EVERY == 0:
            return self._after_push(t_us, self.prediction.push(t_us, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi))
        self.prediction.sample(st, self.history.live, t0, t_us, out.push(t_us), t_us - self.last_update_t,
                               self.recovery.recovering, bool(self.last_flags & ~(FUS_INITIALISED | FUS_GAP_REINIT)),
                               fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi)
        return True

    def live_ready(self, t_us: int) -> bool:
        """The sample at ``t_us`` meets :meth:`_push_imu_compiled`'s conditions for :meth:`live_sample` (but
        the output queue's room, which its kernel tests, and ``P``'s symmetrisation, which it runs)."""
        t0 = self.st.t_us
        fs = self._fsv
        return fs[FS_INIT] != 0 and t0 < t_us and t_us - t0 <= self.prm.max_gap_us \
            and not self.snap.due(t0, t_us) and fs[FS_RECORDER] == 0

    def live_split_kernel(self):
        """``_advance``'s split step taking the snapshot (``ext.Replay`` of the live state), or None."""
        return self._live_ck.kernel if self._live_take and self._live_ck is not None else None

    def live_sample(self, step, t_us: int, rx, ry, rz, Phi, *ori) -> int:
        """The oldest sample of the sensor's IMU ring (at ``t_us``, :meth:`live_ready`), with the source's
        ``r*`` and ``Phi``, through ``step`` (``ext.ImuSample.sample`` or ``finish``; ``ori``: its orientation
        filter's arguments): that filter's step and :meth:`_push_imu_compiled`'s in one call; the
        orientation step's bits, or -1 (nothing done) when the output queue is full."""
        st = self.st
        r = step(st.t_us, t_us - self.last_update_t, self.recovery.recovering,
                 bool(self.last_flags & ~(FUS_INITIALISED | FUS_GAP_REINIT)), st.pred.count, rx, ry, rz, Phi, *ori)
        if r >= 0:
            self.prediction.sampled(st, t_us)
        return r

    def _after_push(self, t_us: int, k: int) -> bool:
        """:meth:`push_imu` after the sample is kept in ring slot ``k``."""
        st = self.st
        if not self.initialized:
            snap = self.snap
            if snap.pending and t_us >= snap.t and not self.replaying:
                snap.take_aux(self.prediction._idv, k, False)
            return False
        if t_us <= st.t_us:
            return False
        if t_us - st.t_us > self.prm.max_gap_us:
            # the stream broke off: the inertial state is not worth keeping (its offsets may be)
            self.recovery.keep(st, RECOVER_STREAM)
            self.initialized = False
            self.snap.drop()
            self._end_replay()
            return False
        self._advance(st, self.history.live, k)
        self._output(t_us)
        return True

    def _advance(self, st: InsState, hist, k: int) -> int:
        """Propagate ``st`` to IMU slot ``k``'s time, splitting the step at a pending snapshot (taken if ``st`` is the
        authoritative state); append the poses to ``hist``. Returns the number of steps run (1 or 2)."""
        pr = self.prediction
        snap = self.snap
        t = pr._itv[k]
        t0 = st.t_us
        if snap.due(t0, t):
            if st is self.st and self._live_ck is not None and len(self.imu) > 1:
                # the newest sample k (the live state is at the one before it): the kernel's split step,
                # the snapshot taken between its halves when the live state is authoritative
                if self._live_take and st is self._auth:
                    self._live_ck.split_take()
                else:
                    self._live_ck.run(1, st is self._auth)
                return self._live_ck.units
            ts = snap.t
            n = 0
            if ts > t0:
                self._propagate(st, k, t0, ts)
                st.set_time(ts)
                pr.history(st, hist, k)
                n = 1
            if st is self._auth:
                snap.take(st, pr._idv, k)
            if t > ts:
                self._propagate(st, k, ts, t)
                n += 1
        else:
            pr.advance(st, hist, k, t0, t)         # (the step, the time, the history row)
            if self.recorder is not None and st is self._auth:
                self.recorder.on_step(self, st, k, t)
            return 1
        st.set_time(t)
        pr.history(st, hist, k)
        return n

    def _propagate(self, st: InsState, k: int, t0: int, t1: int) -> None:
        """``InertialPrediction.propagate`` of ``st`` over ``[t0, t1]``, recorded when it is the authoritative state."""
        self.prediction.propagate(st, k, t0, t1)
        if self.recorder is not None and st is self._auth:
            self.recorder.on_step(self, st, k, t1)

    def _step(self, k: int, t0: int, t1: int) -> None:
        """One step of the live state (``tools.commands.perf`` times it)."""
        self._propagate(self.st, k, t0, t1)

    def _output(self, t_us: int) -> None:
        """Queue the live state's fused pose (``PoseOutput.queue``)."""
        self.output.queue(t_us, self.history.live, self.st, self.prediction._idv, self.imu.peek(0), self.last_update_t,
                          self.recovery.recovering, bool(self.last_flags & ~(FUS_INITIALISED | FUS_GAP_REINIT)))

    def pop_output(self) -> int:
        """Slot of the oldest queued pose in ``out_t`` / ``out_d`` (rows ``OUT_*``), or -1; sent: :meth:`release_output`."""
        return self.output.pop()

    def release_output(self) -> None:
        self.output.release()

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
        while not self.step(2 * self.imu.capacity):
            pass

    def begin_magnetic_update(self, t_ref_us: int, q, R_ms, C, final: bool = True) -> int:
        """Fuse one magnetic solution referring to ``t_ref_us``: position ``q`` (3, source frame), orientation ``R_ms``
        (3x3, sensor to source) and their covariance ``C`` (6x6, ``(p, dtheta)`` as ``solver``, rows
        ``layout.POSE_POS``, ``POSE_ORI``). :meth:`prepare_magnetic_update` and :meth:`apply_magnetic_update` in one
        call (a tick may do them in two). Initialises the filter when needed. The update is applied to the shadow state
        at ``t_ref``; the replay to the newest IMU sample is left to :meth:`step` (none is needed when the state did not
        change: a rejected solution). Returns health flags (ekf flags, ``FUS_*``); never raises. With ``final=False`` a
        rejected solution leaves the snapshot in place (and counts nothing), so the caller can offer another solution of
        the same burst. ``FUS_BUSY``: the previous replay is still running (nothing done; call again once :meth:`step`
        has returned True)."""
        flags = self.prepare_magnetic_update(t_ref_us, q, R_ms, C, final)
        if flags != FUS_PREPARED:
            return flags
        return self.apply_magnetic_update()

    def prepare_magnetic_update(self, t_ref_us: int, q, R_ms, C, final: bool = True) -> int:
        """The first half of :meth:`begin_magnetic_update`: restore the snapshot at ``t_ref`` into the shadow state and
        evaluate the measurement model (``q``, ``R_ms``, ``C`` are read now). Returns ``FUS_PREPARED`` (then call
        :meth:`apply_magnetic_update`), or the final flags when it is already decided (busy, no snapshot,
        initialisation)."""
        if self.replaying:
            return FUS_BUSY
        snap = self.snap
        if not (snap.matches(t_ref_us) and self.prediction.covers(t_ref_us)):
            self.last_flags = FUS_NO_SNAPSHOT
            return FUS_NO_SNAPSHOT
        snap.drop()
        running = self.initialized and snap.initialized
        gap = running and t_ref_us - self.last_update_t > self.prm.dead_reckon_limit_us
        if not running or gap:
            return self._start(t_ref_us, q, R_ms, C, gap)
        self._restore(t_ref_us, q, R_ms, C)
        self._pending = (t_ref_us, q, R_ms, C, final)
        self.prepared += 1
        return FUS_PREPARED

    def _restore(self, t_ref_us: int, q, R_ms, C) -> None:
        """The shadow from the snapshot at ``t_ref``, its history rewound, the measurement evaluated (sec 6.2.3)."""
        self.sh.copy_from(self.snap.st)
        self.history.rewind_shadow(t_ref_us)
        self._evaluate(q, R_ms, C)

    def _update_shadow(self) -> int:
        """The shadow's Kalman update (eqs 6.5-6.6) and, accepted, its correction; the flags."""
        flags = self.upd.update(self.sh.P)
        if flags == EKF_OK:
            self.sh.correct(self.upd._dxv)
        return flags

    def _start(self, t_ref_us: int, q, R_ms, C, gap: bool) -> int:
        """(Re)start the shadow from the solution at ``t_ref`` (``gap``: the last update is too old to bridge) and
        replay from there; ``FUS_NOT_INITIALISED`` when the measurement model cannot start from this snapshot."""
        if not self.meas.ready(self.snap):
            self.last_flags = FUS_NOT_INITIALISED
            return FUS_NOT_INITIALISED
        flags = FUS_INITIALISED
        if gap:                     # too long to bridge: restart from the magnetic solution
            self.recovery.keep(self.snap.st, RECOVER_GAP)
            flags |= FUS_GAP_REINIT
        self._initialize(self.sh, t_ref_us, q, R_ms, C)
        self.last_flags = flags
        self.last_update_t = t_ref_us
        self._start_replay()
        return flags

    def apply_magnetic_update(self) -> int:
        """The second half of :meth:`begin_magnetic_update`: gate, gain and Joseph update of the prepared measurement,
        the correction of the shadow state and the start of its replay. Returns the health flags."""
        t_ref_us, q, R_ms, C, final = self._pending
        self._pending = None
        sh = self.sh
        if self.recorder is not None:
            self.recorder.on_prior(self, sh)
        flags = self._update_shadow()
        self.last_nis = self.upd.nis
        self.last_flags = flags
        if flags == EKF_OK:
            self.rejects_in_row = 0
            self.accepted_in_row += 1
            self.updates += 1
            self.recovery.accepted()
            self.last_update_t = t_ref_us
            if self.recorder is not None:
                self.recorder.on_update(self, sh, self.upd.dx)
        elif not final:
            self.snap.keep()
            return flags
        else:
            self.rejected += 1
            self.rejects_in_row += 1
            self.accepted_in_row = 0
            if not (self.rejects_in_row >= self.prm.reinit_after and self.meas.ready(self.snap)):
                return flags            # the state is unchanged: nothing to replay
            if self.recorder is not None:
                self.recorder.on_rewind(self, t_ref_us)
            self.recovery.keep(sh, RECOVER_DISAGREE)       # sh: the prior at t_ref
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
        """Replay IMU samples on the shadow state, at most ``max_replay_steps_per_step(budget)`` strapdown and
        covariance steps; when the shadow reaches the newest IMU sample it becomes the live state. Returns True when no
        replay is left (also when none was running)."""
        self.last_step_units = 0
        if not self.replaying:
            return True
        if self._replay_ck is not None:
            return self._step_compiled(budget_replay_steps)
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
            units += self._advance(sh, self.history.shadow, imu.slot(i))

    def _step_compiled(self, budget_replay_steps: int) -> bool:
        """:meth:`step`'s loop in one call of the compiled core (``fusion_replay.CompiledReplay``); the same ends."""
        ck = self._replay_ck
        rc = ck.run(budget_replay_steps)
        self.last_step_units = ck.units
        if rc == ck.ext.REPLAY_CAUGHT_UP:
            self._swap()
            return True
        if rc == ck.ext.REPLAY_BUDGET:
            return False
        # the sample before the next one left the ring: the replay cannot go on
        self._end_replay()
        self.replays_lost += 1
        self.last_flags |= FUS_REPLAY_LOST
        return True

    def _swap(self) -> None:
        """The shadow has caught up: it becomes the live state."""
        self.st.copy_from(self.sh)
        self.history.commit()
        self.initialized = True
        self._end_replay()

    def _initialize(self, st: InsState, t_ref_us: int, q, R_ms, C) -> None:
        """``st`` at ``t_ref`` from the magnetic solution (``Recovery.initialize``); its pose history starts anew."""
        self.recovery.initialize(st, t_ref_us, self.snap, q, R_ms, C)
        self.rejects_in_row = 0
        self.accepted_in_row = 0
        self.history.restart_shadow()
        if self.recorder is not None:
            self.recorder.on_init(self, st)
