"""The tightly coupled tracker (``[tight] tight_fusion = true``): each pulse window is a
measurement at its own instant.

The burst fusion (:mod:`coiltrack.firmware.track.burst_fusion`, thesis
``002_cd7f1fdb7fc67471.txt`` ch. 6) solves each X, Y, Z burst for one pose,
assuming the sensor still over the 260 ms of its three pulses, and feeds that
pose to the fusion filter once a cycle. On the body the sensor moves a few
centimetres within a burst (the thigh at 1 m/s: 26 cm), so that pose's error
is large and correlated from burst to burst, which no filter averages away
(sec 6.5 names the relative motion within the burst the main error source).
Here, as a tracker would on the board:

* both IMUs drive a relative inertial EKF per sensor
  (:class:`coiltrack.firmware.estimate.relative_inertial.RelativeInertialEKF`):
  the sensor's pose relative to the source in the source frame, where
  eq 6.8 reads ``R f_sensor - f_source`` and gravity cancels, so neither
  ``Phi`` nor ``Theta`` has to be known in the global frame; the source
  IMU's offsets are filter states (sec 6.5); a fixed source (no source IMU)
  is ``f_source = -g``;
* when a cycle is commanded (:meth:`on_burst`) the EKF clones its pose at
  each pulse's measurement time; when that pulse's window closes its
  amplitude ``y = I R^T B_k(p) + v`` corrects the EKF through the clone
  (the one signal model, the one Kalman update: ``SchepersEKF.update_single_coil``),
  at most one window per tick, in a tick of its own (the burst's solve
  waits a tick);
* the burst is still solved as by :class:`MagneticTracker` (magnetic POSEs
  without ``POSE_FUSED``, from their own warm start, so the magnetic-only
  figures of the same run are those of the magnetic tracker); the first
  solution starts the EKF (and a new one after the EKF lost track);
* between pulses (with a source module): every ``tight_quiet_every`` IMU steps
  the sensor's quiet field, the magnetometer sample nearest the step outside
  every pulse (``burst_fusion.PulseGate``), against the source module's quiet
  field at the same time, both with their set/reset residual removed
  (``burst_fusion.FlipOffset``) and turned to the step's time with their
  gyroscopes: ``b = R^T e`` observes the relative orientation
  (:meth:`RelativeInertialEKF.update_quiet_field`); not used while the health
  monitor finds either field distorted, or when their magnitudes differ by
  more than ``5 tight_quiet_sigma_t`` (metal near one of them), or beyond
  the chi-square gate, or while the orientation std of an axis is above
  ``QUIET_MAX_ORI_SIGMA`` (after a start); at most one per sensor per tick;
* fused POSEs (``POSE_FUSED``) at the IMU rate (every ``pose_every`` sensor
  samples), at most ``imu_steps_per_tick`` IMU steps per sensor per tick.

Work per tick: the IMU steps (a 39-state covariance step each), at most one
quiet-field update per sensor (a 3-row update, no field evaluation), at most one
window update (one evaluation of every coil's field and Jacobian, counted
in the solver's field evaluations' units: ``n`` per update) or the burst
solver's step; at a start (once, and after a lost track) the starting
burst's ``n`` windows in the tick of its solution. All arrays are allocated here; nothing in the steady-state
tick allocates.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.protocol.schema import POSE_FUSED, POSE_INCONSISTENT, POSE_STALE, POSE_VALID

from coiltrack.firmware.transmit import PoseReport, fill_pose
from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NONFINITE, EKF_NOT_PD
from coiltrack.firmware.estimate.layout import ORI, POS
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.relative_inertial import RelativeInertialEKF
from coiltrack.firmware.measure.imu import ImuRing
from coiltrack.firmware.measure.pulse import PULSE_UNUSABLE, SampleRing
from coiltrack.firmware.rotation import quat_tuple, rotation_angle
from coiltrack.firmware.track.burst_fusion import FlipOffset, PulseGate, quiet_sample
from coiltrack.firmware.track.magnetic import MagneticTracker, in_range3
from coiltrack.firmware.track.quality import quality_from
from coiltrack.firmware.track.status import COIL_FATAL


#: rad: the quiet field is not used while the orientation std of any axis is beyond this (the
#: filter has not converged after a start; ``TightFusionTracker._quiet``)
QUIET_MAX_ORI_SIGMA = math.radians(3.0)


class _SourceSamples:
    """The source module (``source_imu_id``): its IMU's samples, read at a sensor sample's time
    (linear between the two samples around it; the newest held when none is newer), and its
    magnetometer between pulses with its set/reset residual (the quiet field)."""

    fixed = False

    def __init__(self, node: int, cfg):
        self.node = node
        self.ring = ImuRing(cfg.imu.imu_ring_capacity)
        self.t0 = -(1 << 62)                 # the last popped sample
        self.s0 = [0.0] * 6
        self.have = False
        self.out = [0.0] * 6                 # the source at the asked time: f (m/s^2), w (rad/s)
        self.fo = [0.0, 0.0, 0.0]
        self.wo = [0.0, 0.0, 0.0]
        g = [-float(v) for v in cfg.imu.gravity_mps2]
        self.fo[0], self.fo[1], self.fo[2] = g[0], g[1], g[2]
        self.samples = 0
        self.mag = SampleRing(max(16, int(cfg.pulse.mag_rate_hz)))
        self.flip = FlipOffset()
        self.mag_t = -(1 << 62)

    def on_imu(self, msg) -> None:
        """An IMU sample of a node that is not a tracked sensor: kept if it is the source's."""
        if msg.node == self.node:
            self.ring.push(msg)

    def on_mag(self, msg, lsb: float) -> None:
        """A MAG_SAMPLE of a node that is not a tracked sensor: kept if it is the source's."""
        if msg.node == self.node:
            self.mag.push(msg.t_us, msg.x * lsb, msg.y * lsb, msg.z * lsb, bool(msg.flip & 2), msg.flip & 1)

    def ready(self, t: int) -> bool:
        """A sample at or after ``t`` is in."""
        return self.ring.last_t >= t

    def sample_into(self, t: int, f, w, g) -> None:
        """The source's specific force and rate at ``t`` (us) into ``f``, ``w`` (3,) (``g`` unused:
        a fixed source's)."""
        self.at(t)
        f[0], f[1], f[2] = self.fo
        w[0], w[1], w[2] = self.wo

    def at(self, t: int) -> None:
        """``fo``, ``wo`` at ``t`` (us)."""
        ring, s0 = self.ring, self.s0
        tv = ring.tv
        while len(ring) and tv[ring.slot(0)] <= t:
            self.t0 = ring.pop_sample(s0)
            self.have = True
            self.samples += 1
        if not self.have:
            return
        fo, wo = self.fo, self.wo
        if len(ring):
            k = ring.slot(0)
            t1 = tv[k]
            d = ring.dv
            a = (t - self.t0) / (t1 - self.t0) if t1 > self.t0 else 0.0
            b = 1.0 - a
            fo[0], fo[1], fo[2] = b * s0[0] + a * d[k, 0], b * s0[1] + a * d[k, 1], b * s0[2] + a * d[k, 2]
            wo[0], wo[1], wo[2] = b * s0[3] + a * d[k, 3], b * s0[4] + a * d[k, 4], b * s0[5] + a * d[k, 5]
        else:
            fo[0], fo[1], fo[2] = s0[0], s0[1], s0[2]
            wo[0], wo[1], wo[2] = s0[3], s0[4], s0[5]

    def observe_flip(self, t: int, age: int, gate: PulseGate, ws) -> None:
        """The set/reset residual from the quiet sample nearest ``t`` (fed once per sample,
        whichever sensor reaches it first; ``ws`` the source's rate, rad/s)."""
        k = quiet_sample(self.mag, self.mag_t, t, age, gate)
        if k >= 0:
            self.mag_t = self.mag.time_at(k)
            bx, by, bz = self.mag.field_at(k)
            self.flip.observe(self.mag_t, 1 if self.mag.flip_at(k) else 0, bx, by, bz, ws, age)

    def counters(self) -> dict:
        return {"source_imu_samples": self.samples}


class _FixedSource:
    """No source module (the null object of :class:`_SourceSamples`): ``f_source = -g``, ``w_s = 0``."""

    fixed = True

    def on_imu(self, msg) -> None:
        """No source IMU: nothing to keep."""

    def on_mag(self, msg, lsb: float) -> None:
        """No source module: nothing to keep."""

    def ready(self, t: int) -> bool:
        return True

    def sample_into(self, t: int, f, w, g) -> None:
        """``f = -g`` (the filter's gravity, m/s^2); ``w`` stays zero."""
        np.negative(g, out=f)

    def counters(self) -> dict:
        return {}


def _make_source(cfg):
    """The source of ``cfg``, chosen once: its module (``source_imu_id``) or fixed."""
    return _SourceSamples(cfg.link.source_imu_id, cfg) if cfg.link.source_imu_id else _FixedSource()


def _turned_field(ring, k: int, offset, w, t: int, out) -> None:
    """``out`` (3,) = the field of ``ring``'s sample in slot ``k`` with its set/reset residual
    ``offset`` (3,) removed and turned to time ``t`` (us) with its frame's rate ``w`` (3,) rad/s:
    the field is fixed in the world, so seen from a frame turning at ``w`` it turns at ``-w``."""
    bx, by, bz = ring.field_at(k)
    sg = 1.0 if ring.flip_at(k) else -1.0
    bx, by, bz = bx - sg * offset[0], by - sg * offset[1], bz - sg * offset[2]
    d = (t - ring.time_at(k)) * 1e-6
    out[0] = bx - d * (w[1] * bz - w[2] * by)
    out[1] = by - d * (w[2] * bx - w[0] * bz)
    out[2] = bz - d * (w[0] * by - w[1] * bx)


class _QuietField:
    """The quiet-field update between pulses (module docstring): with a source module only."""

    def __init__(self, cfg, source: _SourceSamples, gate: PulseGate, supervisor):
        self.source = source
        self.gate = gate
        self.supervisor = supervisor
        self.every = cfg.tight.tight_quiet_every
        self.var = cfg.tight.tight_quiet_sigma_t * cfg.tight.tight_quiet_sigma_t
        self.tol = 5.0 * cfg.tight.tight_quiet_sigma_t
        self.max_ori_var = QUIET_MAX_ORI_SIGMA * QUIET_MAX_ORI_SIGMA
        self.age = int(2e6 / cfg.imu.imu_rate_hz) + int(2e6 / cfg.pulse.mag_rate_hz)

    def step(self, s: "_TightSensor", t: int, tick: int) -> None:
        """The set/reset residuals from the quiet samples nearest ``t`` (the IMU step's time), and
        every ``tight_quiet_every`` steps the quiet-field update (module docstring)."""
        ekf = s.ekf
        gate = self.gate
        age = self.age
        self.source.observe_flip(t, age, gate, ekf.ws)
        k = s.observe_quiet(t, age, gate)
        if k < 0:
            return
        if s.quiet_due < self.every or not ekf.initialized or s.quiet_tick == tick:
            return
        # not while the orientation is still far from known (a start from one burst of a moving
        # sensor: its std past QUIET_MAX_ORI_SIGMA on any axis): the windows' linearisation there
        # correlates the orientation's axes wrongly, and the field's correction across it also
        # shrinks the variance about it, where the start's error stays (roetenberg-walking-arm, 20 s,
        # seed 1: 12 deg about the field held for 3 s against a std of 1.2 deg, the track lost twice)
        P = ekf.P
        o = ORI.start
        lim = self.max_ori_var
        if P[o, o] > lim or P[o + 1, o + 1] > lim or P[o + 2, o + 2] > lim:
            return
        if self._update(s, t, k, tick):
            s.quiet_done()

    def _update(self, s: "_TightSensor", t: int, k: int, tick: int) -> bool:
        """The quiet-field update at ``t`` (the filter's time) from the sensor's sample in slot ``k``
        and the source's sample nearest it; False when the source has none (nothing done)."""
        src = self.source
        ts = s.ch.ring.time_at(k)
        ks = quiet_sample(src.mag, -(1 << 62), ts, self.age, self.gate)
        if ks < 0:
            return False
        hl = self.supervisor.health
        if hl.is_distorted(s.node) or hl.is_distorted(src.node):
            s.quiet_skip()
            return True
        s.quiet_update(t, k, src.mag, ks, src.flip.o, self.var, self.tol, tick)
        return True


class _NoQuietField:
    """No source module: no quiet-field update."""

    def step(self, s: "_TightSensor", t: int, tick: int) -> None:
        """Nothing to do."""


class _TightSensor:
    """One sensor's IMU ring, relative EKF and window bookkeeping."""

    def __init__(self, ch, cfg, n: int, source_imu: bool, core=_DEFAULT_CORE):
        self.ch = ch
        self.node = ch.node
        self._report = PoseReport(ch.node)     # the POSE being sent (filled in place)
        self.n = n
        self.ekf = RelativeInertialEKF.from_config(cfg, n_clones=n, source_imu=source_imu, core=core)
        self.imu = ImuRing(cfg.imu.imu_ring_capacity)
        self.s6 = [0.0] * 6
        self.acc = np.zeros(3)
        self.gyr = np.zeros(3)
        self.sacc = np.zeros(3)
        self.sgyr = np.zeros(3)
        self.pending = np.zeros(n, dtype=bool)      # clone scheduled, window not yet used
        self.col = np.zeros(3)
        self.P6 = np.zeros((6, 6))
        self.G = np.zeros((n, 3, 3))                # at a start: R_now^T R(t_j) of each pulse
        self.dt = np.zeros(n)                       # ... and the time since it (s)
        self.have = [False] * n
        self.Rnow = np.eye(3)
        self.R3 = np.eye(3)
        self.last_imu_us: int | None = None
        self.last_update_us = 0
        self.samples = 0
        self.updates = 0
        self.gated = 0
        self.gated_in_row = 0
        self.unusable = 0
        self.starts = 0
        self.since_start = 0                      # window updates since the last start
        self.lost = 0
        self.out_of_range = 0
        self.unconverged = 0                        # fused poses sent not valid: position std too large
        self.nis_sum = 0.0
        self.nis_n = 0
        self.q_x = 0.0
        # quiet field: the sensor's set/reset residual, the newest sample seen, the steps since an update
        self.flip = FlipOffset()
        self.mag_t = -(1 << 62)
        self.quiet_due = 0
        self.quiet_tick = -1                      # the tick of the last quiet-field update
        self.b = [0.0, 0.0, 0.0]                  # the quiet field (T, sensor frame), residual removed
        self.e = [0.0, 0.0, 0.0]                  # the source's quiet field (T, source frame)
        self.quiet_updates = 0
        self.quiet_gated = 0
        self.quiet_skipped = 0                    # distorted or magnitudes apart
        self.quiet_nis_sum = 0.0

    # ------------------------------------------------------------ IMU
    def step_imu(self, t: int, source, timeout_us: int) -> None:
        """Pop the oldest IMU sample (at ``t``) and propagate the EKF with it and the source's
        sample of the same time; a hole in the stream longer than ``timeout_us`` restarts the
        inputs (the state cannot be carried across it: the track is lost)."""
        self.imu.pop_sample(self.s6)
        a, g = self.acc, self.gyr
        a[0], a[1], a[2], g[0], g[1], g[2] = self.s6
        ekf = self.ekf
        source.sample_into(t, self.sacc, self.sgyr, ekf.g)
        if self.last_imu_us is not None and t - self.last_imu_us > timeout_us:
            ekf.restart_inputs()
            if ekf.initialized:
                self.lose()
        self.last_imu_us = t
        ekf.propagate_relative(t, self.acc, self.gyr, self.sacc, self.sgyr)
        self.samples += 1

    def lose(self) -> None:
        """The track is lost: the EKF starts again from the next burst's solution."""
        self.ekf.reset()
        self.gated_in_row = 0
        self.lost += 1

    # ------------------------------------------------------------ quiet field
    def observe_quiet(self, t: int, age: int, gate: PulseGate) -> int:
        """The sensor's quiet sample nearest ``t`` (newer than the last one): its set/reset
        residual, one more step towards a quiet-field update; its slot, or -1."""
        ring = self.ch.ring
        k = quiet_sample(ring, self.mag_t, t, age, gate)
        if k < 0:
            return -1
        ts = ring.time_at(k)
        self.mag_t = ts
        bx, by, bz = ring.field_at(k)
        self.flip.observe(ts, 1 if ring.flip_at(k) else 0, bx, by, bz, self.ekf.w, age)
        self.quiet_due += 1
        return k

    def quiet_skip(self) -> None:
        """A quiet-field pair not used (a field distorted, or their magnitudes apart)."""
        self.quiet_skipped += 1

    def quiet_done(self) -> None:
        self.quiet_due = 0

    def quiet_update(self, t: int, k: int, src_ring, ks: int, src_offset, var: float, tol: float,
                     tick: int) -> None:
        """The quiet-field update at ``t`` from the sensor's sample in slot ``k`` and the source's
        in slot ``ks`` of ``src_ring`` (residual ``src_offset``): both turned to ``t`` with their
        rates; skipped when their magnitudes differ by more than ``tol`` (T)."""
        ekf = self.ekf
        # residuals removed, both turned to t with their rates (the field is fixed in the world:
        # seen from a frame turning at w it turns at -w)
        _turned_field(self.ch.ring, k, self.flip.o, ekf.w, t, self.b)
        _turned_field(src_ring, ks, src_offset, ekf.ws, t, self.e)
        b, e = self.b, self.e
        nb = math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
        ne = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        if abs(nb - ne) > tol:
            self.quiet_skipped += 1
            return
        self.quiet_tick = tick
        flags = ekf.update_quiet_field(b, e, var)
        if flags & EKF_GATED:
            self.quiet_gated += 1
        elif not flags & (EKF_NOT_PD | EKF_NONFINITE):
            self.quiet_updates += 1
            self.quiet_nis_sum += ekf.quiet_nis

    # ------------------------------------------------------------ windows
    def schedule_clones(self, t0: int, spacing_us: int, mid) -> None:
        """A cycle was commanded: a clone at each pulse's measurement time."""
        for j in range(self.n):
            self.ekf.release_clone(j)
            self.ekf.schedule_clone(j, t0 + j * spacing_us + mid[j])
            self.pending[j] = True

    def ready_window(self) -> int:
        """The oldest closed window whose clone waits for it (now taken: not offered again), or -1."""
        ch = self.ch
        for j in range(self.n):
            if self.pending[j] and ch.done[j]:
                self.pending[j] = False
                return j
        return -1

    def count_unusable(self) -> None:
        self.unusable += 1

    def window_update(self, j: int, current: float, model, rel: float) -> int:
        """Window ``j`` (its amplitudes and variances) as an update through its clone; the flags."""
        ch = self.ch
        col = self.col
        for i in range(3):
            col[i] = float(ch.var[i, j])
        return self.ekf.update_single_coil(j, ch.S[:, j], col, j, current, model, rel, 1.0, gate=True)

    def after_window(self, flags: int, now_us: int, lost_var: float, settle: int, reacquire_after: int) -> None:
        """Count a window update's outcome; lose the track after ``reacquire_after`` gated in a
        row, or when a position variance is beyond ``lost_var`` ``settle`` updates after a start."""
        ekf = self.ekf
        if flags & (EKF_NOT_PD | EKF_NONFINITE):
            self.unusable += 1
            return
        self.since_start += 1
        if flags & EKF_GATED:
            self.gated += 1
            self.gated_in_row += 1
        else:
            self.gated_in_row = 0
            self.updates += 1
            self.last_update_us = now_us
            self.nis_sum += ekf.nis
            self.nis_n += 1
            self.q_x = ekf.nis / 3.0
        P = ekf.P
        b = POS.start
        wide = P[b, b] > lost_var or P[b + 1, b + 1] > lost_var or P[b + 2, b + 2] > lost_var
        if self.gated_in_row >= reacquire_after or (wide and self.since_start >= settle):
            self.lose()

    # ------------------------------------------------------------ start
    def start(self, sv, cfg, half_burst_us: int, currents, model, now_us: int) -> int:
        """The burst's solution ``sv`` (the solver) starts the EKF (when it is not running and a
        clone of the middle pulse was taken): the pose at the burst's middle carried to the
        present by the gyroscopes, widened by the motion since, then the burst's windows once
        more, each at its own instant. Returns the field evaluations spent (``n`` per window)."""
        ekf = self.ekf
        if ekf.initialized or ekf.t_us is None:
            return 0
        n = self.n
        m = n // 2
        if not ekf.clone_taken[m]:
            return 0
        np.matmul(sv.rotation, ekf.clone_R[m].T, out=self.R3)
        np.matmul(self.R3, ekf.R, out=self.Rnow)
        lag = (ekf.t_us - int(ekf.clone_t[m])) * 1e-6
        half = half_burst_us * 1e-6
        P6 = self.P6
        np.copyto(P6, sv.covariance)
        extra = (cfg.tight.tight_init_sigma_vel * (lag + half)) ** 2
        ori = (cfg.imu.imu_gyro_bias_sigma * (lag + half)) ** 2
        # the burst's solution takes the sensor as still: turned by theta between its first and last
        # pulse (the gyroscopes' relative rotation, the clones'), it is off by up to theta / 2 in
        # orientation (roetenberg-walking-arm, 20 s, seed 1: a start 13.7 deg off against a std of
        # 3.8 deg, the arm turning 0.4 rad within the burst)
        a, z = -1, -1
        for j in range(n):
            if ekf.clone_taken[j]:
                z = j
                if a < 0:
                    a = j
        if 0 <= a < z:
            np.matmul(ekf.clone_R[a].T, ekf.clone_R[z], out=self.R3)
            th = rotation_angle(self.R3)
            ori += 0.25 * th * th
        for i in range(3):
            P6[i, i] += extra
            P6[3 + i, 3 + i] += ori
        # the gyroscopes' rotation since each pulse (R_now^T R(t_j)), before R is replaced
        have = self.have
        for j in range(n):
            have[j] = bool(ekf.clone_taken[j])
            if have[j]:
                np.matmul(ekf.R.T, ekf.clone_R[j], out=self.G[j])
                self.dt[j] = (ekf.t_us - int(ekf.clone_t[j])) * 1e-6
            ekf.release_clone(j)
            self.pending[j] = False
        ekf.initialize(sv.position, self.Rnow, P6, ekf.t_us, cfg.tight.tight_init_sigma_vel, cfg.imu.imu_acc_bias_sigma,
                       cfg.imu.imu_gyro_bias_sigma)
        self.starts += 1
        self.since_start = 0
        evals = self._start_windows(cfg, currents, model)
        self.last_update_us = now_us
        return evals

    def _start_windows(self, cfg, currents, model) -> int:
        """The burst's windows once more, each at its own instant, through clones predicted back
        from the new state (SchepersEKF.back_clone): the motion within the burst, which the
        solution averages, corrects position, orientation and velocity together."""
        ekf = self.ekf
        ch = self.ch
        evals = 0
        for j in range(self.n):
            if not self.have[j] or ch.flags[j] & PULSE_UNUSABLE:
                continue
            ekf.back_clone(j, float(self.dt[j]), self.G[j])
            col = self.col
            for i in range(3):
                col[i] = float(ch.var[i, j])
            c = float(currents[j])
            rc = cfg.limits.current_tolerance_a / max(abs(c), 1e-6)
            rel = math.sqrt(cfg.adaptive.field_model_rel_sigma * cfg.adaptive.field_model_rel_sigma + rc * rc)
            ekf.update_single_coil(j, ch.S[:, j], col, j, c, model, rel, 1.0, gate=False)
            ekf.release_clone(j)
            evals += self.n
        return evals

    # ------------------------------------------------------------ output
    def emit(self, tx, t_us: int, now_us: int, cfg, range_m: float) -> None:
        """Send the fused POSE (``POSE_FUSED``) at ``t_us``: stale past ``stale_us`` without an
        update, inconsistent while windows are gated, not valid beyond the working volume or
        while a position std is above ``tight_valid_sigma_m``."""
        ekf = self.ekf
        p = ekf.p
        status = POSE_VALID | POSE_FUSED
        if now_us - self.last_update_us > cfg.link.stale_us:
            status |= POSE_STALE
        if self.gated_in_row:
            status |= POSE_INCONSISTENT
        if not in_range3(p[0], p[1], p[2], range_m):
            status &= ~POSE_VALID
            self.out_of_range += 1
        qw, qx, qy, qz = quat_tuple(ekf.R)
        P = ekf.P
        b, o = POS.start, ORI.start
        vp = float(P[b, b]) + float(P[b + 1, b + 1]) + float(P[b + 2, b + 2])
        lim = cfg.tight.tight_valid_sigma_m
        if lim > 0.0 and status & POSE_VALID:
            l2 = lim * lim
            if P[b, b] > l2 or P[b + 1, b + 1] > l2 or P[b + 2, b + 2] > l2:
                status &= ~POSE_VALID            # not converged: sent, not valid
                self.unconverged += 1
        r = self._report
        r.t_us, r.status = t_us, status
        r.quality = quality_from(vp, self.q_x, cfg.quality.quality_error_scale_m)
        fill_pose(r, p, (qw, qx, qy, qz), P, b, o)
        tx.pose(r)


class TightFusionTracker(MagneticTracker):
    """Magnetic-only poses of each burst, and the tightly coupled fused poses (module docstring)."""

    def __init__(self, cfg, coils, channels, schedule, burst, supervisor, tx, solvers, core=_DEFAULT_CORE):
        super().__init__(cfg, coils, channels, schedule, burst, supervisor, tx, solvers, core)
        n = len(coils)
        self.n = n
        self.source = _make_source(cfg)           # the source module, or fixed: chosen once
        self.sensors = {ch.node: _TightSensor(ch, cfg, n, not self.source.fixed, core) for ch in self.channels}
        self._sens = tuple(self.sensors.values())
        self.model = SingleCoilModel(coils, cfg.source.field_model, core)
        # mid time of a pulse's used samples from its start edge (as the extractor uses them)
        self.mid_us = (cfg.pulse.settle_us + cfg.timing.pulse_us - cfg.pulse.guard_us) // 2
        # ... and as the last windows had it (their samples' mean time from the start edge)
        self._mid = [self.mid_us] * n
        self.half_burst_us = ((n - 1) * cfg.timing.spacing_us + cfg.timing.pulse_us) // 2
        self.source_wait_us = int(1.5e6 / cfg.imu.imu_delta_rate_hz)
        # quiet field (module docstring): with the source module's magnetometer, chosen once
        gate = PulseGate(schedule.start, schedule.end, cfg.pulse.fall_us, cfg.orientation.compass_guard_us)
        self.quiet = (_QuietField(cfg, self.source, gate, supervisor)
                      if not self.source.fixed and cfg.tight.tight_quiet_every else _NoQuietField())
        self.ticks = 0
        self.imu_steps = cfg.budget.imu_steps_per_tick
        self.evals = 0                       # field evaluations of the window updates (n per update)
        self.fused_poses = 0
        self.now_us = 0

    # ------------------------------------------------------------ inputs
    def on_imu(self, msg, now_us: int) -> None:
        s = self.sensors.get(msg.node)
        if s is not None:
            s.imu.push(msg)
        else:
            self.source.on_imu(msg)

    def on_mag(self, msg, lsb: float) -> None:
        """A MAG_SAMPLE of a node that is not a tracked sensor: the source's module."""
        self.source.on_mag(msg, lsb)

    def on_burst(self, t_ref: int) -> None:
        """Clone each sensor's pose at every pulse's measurement time."""
        t0 = int(t_ref) - self.half_burst_us
        for s in self._sens:
            s.schedule_clones(t0, self.cfg.timing.spacing_us, self._mid)

    # ------------------------------------------------------------ tick
    def step(self, now_us: int) -> None:
        """Propagate, use at most one closed window (then the solve waits a tick), solve, send."""
        self.now_us = now_us
        self.ticks += 1
        for s in self._sens:
            self._propagate(s, now_us)
        if self._update_one(now_us):
            return
        super().step(now_us)

    def _propagate(self, s: _TightSensor, now_us: int) -> None:
        ring = s.imu
        src = self.source
        tv = ring.tv
        ekf = s.ekf
        cfg = self.cfg
        for _ in range(self.imu_steps):
            if not len(ring):
                return
            t = tv[ring.slot(0)]
            if not src.ready(t) and now_us - t < self.source_wait_us:
                return                       # the source's sample of this time is not in yet
            s.step_imu(t, src, cfg.imu.imu_timeout_us)
            self.quiet.step(s, t, self.ticks)
            if ekf.initialized and s.samples % cfg.adaptive.pose_every == 0:
                s.emit(self.tx, t, now_us, cfg, self.range_m)
                self.fused_poses += 1

    def _update_one(self, now_us: int) -> bool:
        """The oldest closed, unused window of one sensor as an EKF update; True if one was used."""
        for s in self._sens:
            j = s.ready_window()
            if j >= 0:
                if s.ekf.initialized:
                    self._window(s, j, now_us)
                    s.ekf.release_clone(j)
                else:                    # kept: the burst's solution starts the EKF from it
                    s.count_unusable()
                return True
        return False

    def _window(self, s: _TightSensor, j: int, now_us: int) -> None:
        ch = s.ch
        cfg = self.cfg
        if ch.flags[j] & PULSE_UNUSABLE or self.schedule.any_faults() & COIL_FATAL \
                or self.supervisor.veto:
            s.count_unusable()
            return
        mc = self.schedule.measured[j]
        current = float(mc) if mc != 0.0 else float(self.nominal[j])
        rc = cfg.limits.current_tolerance_a / max(abs(current), 1e-6)
        rel = math.sqrt(cfg.adaptive.field_model_rel_sigma * cfg.adaptive.field_model_rel_sigma + rc * rc)
        if not s.ekf.clone_taken[j]:
            s.count_unusable()               # the IMU stream never reached the pulse's time
            return
        m = int(ch.pulse_mid[j]) - int(self.schedule.start[j])
        if 0 < m < cfg.timing.pulse_us:
            self._mid[j] = m
        flags = s.window_update(j, current, self.model, rel)
        self.evals += self.n
        s.after_window(flags, now_us, cfg.tight.tight_lost_sigma_m * cfg.tight.tight_lost_sigma_m, 5 * self.n,
                       cfg.adaptive.reacquire_after)

    # ------------------------------------------------------------ start
    def on_solution(self, ch, solved: bool) -> None:
        """The first burst solution (or the first after a lost track) starts the EKF: the pose at
        the burst's middle carried to the present by the gyroscopes (the EKF's own relative
        orientation since the middle pulse's clone), widened by the motion since
        (:meth:`_TightSensor.start`)."""
        if solved:
            self.evals += self.sensors[ch.node].start(self.solver, self.cfg, self.half_burst_us, self.currents,
                                                      self.model, self.now_us)

    def counters(self) -> dict:
        d = super().counters()
        ss = self._sens
        nn = sum(s.nis_n for s in ss)
        nq = sum(s.quiet_updates for s in ss)
        d.update({
            "imu_samples": sum(s.samples for s in ss),
            "fusion_updates": sum(s.updates for s in ss),
            "fusion_rejected": sum(s.gated for s in ss),
            "fusion_unusable_windows": sum(s.unusable for s in ss),
            "fusion_starts": sum(s.starts for s in ss),
            "fusion_lost": sum(s.lost for s in ss),
            "fusion_window_evals": self.evals,
            "fusion_nis_mean": round(sum(s.nis_sum for s in ss) / nn, 3) if nn else None,
            "fused_poses_out_of_range": sum(s.out_of_range for s in ss),
            "fused_poses_unconverged": sum(s.unconverged for s in ss),
            "fusion_quiet_updates": sum(s.quiet_updates for s in ss),
            "fusion_quiet_rejected": sum(s.quiet_gated for s in ss),
            "fusion_quiet_skipped": sum(s.quiet_skipped for s in ss),
            "fusion_quiet_nis_mean": (round(sum(s.quiet_nis_sum for s in ss) / nq, 3) if nq else None),
        })
        d.update(self.source.counters())
        return d
