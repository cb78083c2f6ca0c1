"""The inertial side of the firmware: IMU sample rings, the orientation filters
of the sensors and of the source, the fusion filter of each sensor, and the
motion compensation within a burst.

Glue between ``firmware.Firmware`` (which owns the pulse schedule, the
magnetometer rings and the pose solver) and the estimators
(``orientation.OrientationFilter``, thesis ch. 2; ``fusion.FusionFilter``,
thesis ch. 6). Per sensor node (:class:`SensorInertial`), at each IMU sample:

1. the ch. 2 filter ``Xi``: gyroscope strapdown, inclination update from the
   accelerometer, compass update from the newest magnetometer sample that is
   not inside a coil pulse (``PulseGate``; thesis ch. 2 needs the earth field
   alone) and corrected for the set/reset offset (``FlipOffset``);
2. the fusion filter's inertial step with the sensor's specific force and
   rate, and the source's specific force and orientation (eq 6.8):
   :class:`SourceInertial` (the source's own IMU and magnetometer through a
   second ch. 2 filter) or, for a fixed source, ``-gravity_mps2`` and the
   identity.

After a burst (``SensorInertial.fuse``): the three pulse amplitudes are
brought to the burst's reference instant with the inertial pose history
(thesis sec 6.5: the relative motion during the X, Y, Z burst is the main
error source), the pose is solved again from the compensated signals, and the
solution with its covariance updates the fusion filter at that instant.

All buffers are allocated in the constructors; the per-sample and per-burst
paths allocate no numpy array.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.protocol.schema import (ACC_LSB, EVT_DEAD_RECKONING, EVT_TRACK_REINIT, GYR_LSB, POSE_DEAD_RECKONING,
                                       POSE_FUSED, POSE_INCONSISTENT, POSE_RECOVERED, POSE_STALE, POSE_VALID)

from coiltrack.firmware.transmit import PoseReport
from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NONFINITE, EKF_NOT_PD, SYMMETRIZE_EVERY
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.magnetic_inertial import (FS_INIT, FS_N, FUS_PREPARED, OUT_DEAD_RECKONING,
                                                          OUT_INCONSISTENT, OUT_LOST, OUT_RECOVERED, OUT_STALE,
                                                          FusionFilter, FusionParams)
from coiltrack.firmware.estimate.fusion_snapshot import Snapshot
from coiltrack.firmware.estimate.layout import BIAS, DIST, THETA
from coiltrack.firmware.estimate.orientation import (N as ORI_N, OF_INIT, OF_STEPS, OF_T, OS_MAG, OS_ROUND,
                                                    OrientationFilter, OrientationParams)
from coiltrack.firmware.measure.imu import ImuRing
from coiltrack.firmware.measure.pulse import SampleRing
from coiltrack.firmware.pose.solver import SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_NONFINITE, SOLVE_RUNNING
from coiltrack.firmware.track.burst_compiled import FZ_N as _FZ_N
from coiltrack.firmware.track.burst_compiled import CompiledBurst
from coiltrack.firmware.track.magnetic import MagneticTracker, in_range, in_range3
from coiltrack.firmware.track.solve_tick import SolveTick
from coiltrack.firmware.track.source_unaccelerated import Unaccelerated

#: ``SensorInertial.process``'s default ``max_steps``: every queued sample
ALL_STEPS = 1 << 30
#: motion compensation needs the inertial velocity to better than this (m/s, rms per axis)
_COMP_MAX_VEL_SIGMA = 0.05
#: the steps of fusing one burst (``SensorInertial.fuse``)
_COMPENSATE, _COMPENSATE_PULSES, _SOLVE, _UPDATE_COMP, _APPLY_COMP, _UPDATE_MAG, _APPLY_MAG, _REPLAY = range(8)
#: the POSE status of a fused pose whose filter raised no ``OUT_*`` bit
_FUSED_VALID = POSE_VALID | POSE_FUSED


class PulseGate:
    """Is a magnetometer sample free of coil field? Outside every pulse of the
    current schedule by ``guard_us`` before its start and ``fall_us + guard_us``
    after its end."""

    def __init__(self, pulse_start, pulse_end, fall_us: int, guard_us: int):
        self._ps = memoryview(pulse_start)
        self._pe = memoryview(pulse_end)
        self.n = len(pulse_start)
        self.before = int(guard_us)
        self.after = int(fall_us) + int(guard_us)

    def quiet(self, t_us: int) -> bool:
        ps, pe = self._ps, self._pe
        for j in range(self.n):
            if ps[j] - self.before <= t_us <= pe[j] + self.after:
                return False
        return True

    def sample_kernel(self, ext, ring: SampleRing):
        """:func:`quiet_sample` of ``ring`` with this gate on the compiled core
        (``core/src/fusimu.c ct_quiet_sample``, ``ext.QuietSample``), bound to the ring's arrays and
        the schedule's (read as they are at each call)."""
        return ext.QuietSample(ring.t, ring.flags, self._ps, self._pe, self.before, self.after)


class FlipOffset:
    """Residual set/reset offset of a flipped magnetoresistive sensor.

    A flipped sensor reads ``s B + o`` with the flip state ``s``; the flip
    electronics remove most of ``o`` and leave ``s o_r`` (thesis sec 5.5 and
    7.2 on flipping). Pulse extraction removes it with the baseline; the
    compass does not, so ``o_r`` is estimated across each flip: the jump
    between the last sample before and the first after a flip, less the
    rotation the gyroscope saw between them, is ``2 s o_r``. A running mean
    of these jumps gives ``o_r``; compass samples are corrected by ``-s o_r``.
    """

    def __init__(self, gain: float = 0.2):
        # the state in two arrays the compiled core shares (core/include/ct_fusimu.h CT_FL_*, CT_FI_*):
        # the offset o and the previous sample (T); the previous flip state, its time, the jumps seen
        self.s = np.zeros(6)
        self.si = np.zeros(3, dtype=np.int64)
        self.o = memoryview(self.s)[0:3]
        self.prev = memoryview(self.s)[3:6]
        self._i = memoryview(self.si)
        self._i[0] = -1
        self.gain = float(gain)

    def observe(self, t_us: int, state: int, mx, my, mz, rate, max_dt_us: int) -> None:
        """Feed every quiet compass sample (T) with its flip state (0/1) and
        the current bias-free rate (rad/s, 3 floats)."""
        si = self._i                           # previous state, its time, jumps seen
        if state == si[0]:                     # no flip: just remember the sample
            p = self.prev
            p[0], p[1], p[2] = mx, my, mz
            si[1] = t_us
            return
        if si[0] >= 0 and 0 < t_us - si[1] <= max_dt_us:
            dt = (t_us - si[1]) * 1e-6
            wx, wy, wz = rate[0] * dt, rate[1] * dt, rate[2] * dt
            px, py, pz = self.prev
            # field seen from the rotated frame: p - w x p (first order)
            ex = px - (wy * pz - wz * py)
            ey = py - (wz * px - wx * pz)
            ez = pz - (wx * py - wy * px)
            s = 1.0 if state else -1.0
            n = si[2]
            k = 1.0 / (n + 1) if n < 1.0 / self.gain else self.gain
            o = self.o
            o[0] += k * (0.5 * s * (mx - ex) - o[0])
            o[1] += k * (0.5 * s * (my - ey) - o[1])
            o[2] += k * (0.5 * s * (mz - ez) - o[2])
            si[2] = n + 1
        si[0] = state
        p = self.prev
        p[0], p[1], p[2] = mx, my, mz
        si[1] = t_us


def quiet_sample(ring: SampleRing, after_t: int, t_imu: int, max_age_us: int, gate: PulseGate):
    """The magnetometer sample of ``ring`` nearest ``t_imu`` (:meth:`SampleRing.nearest_slot`) if
    it is newer than ``after_t``, within ``max_age_us`` of ``t_imu``, not saturated and outside
    the pulses; returns its slot or -1. IMU samples given back from an IMU_DELTA pair reach the
    filter up to one interval after the magnetometer samples of their time."""
    best = ring.nearest_slot(t_imu)
    if best < 0:
        return -1
    t = ring.time_at(best)
    if t <= after_t or abs(t - t_imu) > max_age_us:
        return -1
    if ring.saturated_at(best) or not gate.quiet(t):
        return -1
    return best


class _Ori:
    """A ch. 2 filter fed from an IMU ring and a magnetometer ring."""

    def __init__(self, cfg, gate: PulseGate, max_age_us: int | None = None, core=_DEFAULT_CORE):
        self.f = OrientationFilter(OrientationParams.from_config(cfg), core)
        self.gate = gate
        self.flip = FlipOffset()
        self._ct = np.full(1, -(1 << 62), dtype=np.int64)    # the last compass sample's time (us)
        self._ctv = memoryview(self._ct)
        # a compass sample's largest distance from the IMU sample it serves (default two intervals of each)
        self.max_age_us = int(2e6 / cfg.imu.imu_rate_hz) + int(2e6 / cfg.pulse.mag_rate_hz) if max_age_us is None \
            else int(max_age_us)
        # the samples since the last update round (``n``) and the compass samples used
        # (``compass_used``) in an int64 array the compiled one-call IMU sample updates in place
        self.ns = np.zeros(2, dtype=np.int64)
        self._nsv = memoryview(self.ns)
        self.every = cfg.orientation.ori_update_every
        self.gap_us = cfg.imu.imu_timeout_us     # a longer break in the IMU stream: the orientation is lost
        self.lost = False
        # the compass sample's search (quiet_sample) on the compiled core: bound to the magnetometer
        # ring at its first sample (the ring a filter is fed from does not change); None: Python
        # (also for a gate without the compiled search)
        self._ext = core.ext if getattr(gate, "sample_kernel", None) is not None else None
        self._qk = None
        self._qring = None
        # one sample of an initialised filter whose compass has learned, in one call of the compiled
        # core (core/src/fusimu.c ct_ori_sample, ext.OriStep), bound to the magnetometer ring at its first
        # such sample; the filter's compiled updates are its reference's kernels
        self._sk = None
        self._sring = None
        self.one_call = self._ext is not None and getattr(self.f, "_cku", None) is not None
        if self.one_call:
            self.step = self._step_compiled

    compass_t = property(lambda self: self._ctv[0])     # the last compass sample's time (us)

    def _set_n(self, v: int) -> None:
        self._nsv[0] = v

    def _set_used(self, v: int) -> None:
        self._nsv[1] = v

    n = property(lambda self: self._nsv[0], _set_n)
    compass_used = property(lambda self: self._nsv[1], _set_used)
    kernel = property(lambda self: self._ext)            # the compiled core's module (None: Python)
    sample_kernel = property(lambda self: self._sk)      # ext.OriStep (bound by takes)

    def bind_ring(self, mag: SampleRing) -> None:
        """Bind the compiled core's kernels to ``mag``, the magnetometer ring this filter is fed
        from (it does not change), at start-up: the compass sample's search (``ext.QuietSample``)
        and the one-call sample (``ext.OriStep``). Their first contact with the ring inside a
        tick then finds them bound (``multi16``: sixteen sensors' bindings in its first tick took
        2-4 ms); a ring given later still binds there. Nothing on the Python core."""
        if self._ext is None:
            return
        if mag is not self._qring:
            self._qk = self.gate.sample_kernel(self._ext, mag)
            self._qring = mag
        if self.one_call and mag is not self._sring:
            self._bind_sample(mag)

    def bind(self, mag: SampleRing):
        """``ext.OriStep`` bound to ``mag`` (the one of the samples :meth:`ready` lets through)."""
        if mag is not self._sring:
            self._bind_sample(mag)
        return self._sk

    def _bind_sample(self, mag: SampleRing) -> None:
        """``ext.OriStep`` bound to the filter, its updates, ``mag`` and the gate's schedule."""
        f, g, fl = self.f, self.gate, self.flip
        self._sk = self._ext.OriStep(f, f.incl.upd, f.compass.upd, f.compass, fl.s, fl.si, f.incl.st, self._ct,
                                     mag.t, mag.flags, mag.b, g._ps, g._pe, g.before, g.after, self.every,
                                     self.max_age_us, SYMMETRIZE_EVERY, fl.gain, ORI_N, THETA.start, BIAS.start,
                                     DIST.start)
        self._sring = mag

    def takes(self, t: int, mag: SampleRing) -> bool:
        """The compiled core takes the sample at ``t`` whole (:meth:`ready`; ``ext.OriStep``, bound to
        ``mag`` here)."""
        if not self.ready(t):
            return False
        if mag is not self._sring:
            self._bind_sample(mag)
        return True

    def ready(self, t: int) -> bool:
        """The sample at ``t`` is one the compiled core takes whole in one call (:meth:`settled`, and no
        orthonormalisation due)."""
        s = self.f.state_view
        return self.settled(t) and (t <= s[OF_T] or (s[OF_STEPS] + 1) & 63 != 0)

    def settled(self, t: int) -> bool:
        """An initialised filter, no break in the stream before ``t``, the compass learned."""
        s = self.f.state_view                          # (OrientationFilter.state: initialised, time)
        return s[OF_INIT] != 0 and t - s[OF_T] <= self.gap_us and not self.f.compass.learning

    def _step_compiled(self, t, ax, ay, az, wx, wy, wz, mag: SampleRing) -> None:
        """:meth:`step` of a sample the compiled core takes whole (:meth:`takes`; ``ext.OriStep.sample``:
        the compass sample, the set/reset offset, the prediction and the update round, the
        operations of :meth:`step_python` in its order); any other goes through :meth:`step_python`."""
        if not self.takes(t, mag):
            self.step_python(t, ax, ay, az, wx, wy, wz, mag)
            return
        f = self.f
        h = mag.last_pushed_slot() + 1                 # (the ring's head: the next push's slot)
        self.sampled(t, self._sk.sample(t, ax, ay, az, wx, wy, wz, f.t_us, self.n, h if h < mag.capacity else 0,
                                        len(mag), f.pred.count, f.incl.upd.count, f.compass.upd.count))

    def sampled(self, t: int, r: int) -> bool:
        """The bookkeeping of a sample at ``t`` the compiled core took whole (what it did: the
        ``orientation.OS_*`` bits ``r``); False (nothing done) for ``r`` < 0: the core did not take it."""
        if r < 0:
            return False
        self.f.sample_done(t, r)
        ns = self._nsv
        if r & OS_ROUND:
            ns[0] = 0
            if r & OS_MAG:
                ns[1] += 1
        else:
            ns[0] += 1
        return True

    def _quiet(self, mag: SampleRing, t: int) -> int:
        """:func:`quiet_sample` for the IMU sample at ``t``, on the filter's core."""
        if self._ext is None:
            return quiet_sample(mag, self.compass_t, t, self.max_age_us, self.gate)
        if mag is not self._qring:
            self._qk = self.gate.sample_kernel(self._ext, mag)
            self._qring = mag
        h = mag.last_pushed_slot() + 1                 # (the ring's head: the next push's slot)
        return self._qk.find(h if h < mag.capacity else 0, len(mag), self.compass_t, t, self.max_age_us)

    def step(self, t, ax, ay, az, wx, wy, wz, mag: SampleRing) -> None:
        """One IMU sample (specific force, rate) with the magnetometer ring ``mag``: the compass
        sample and its set/reset offset, the prediction and every ``every`` samples the updates."""
        self.step_python(t, ax, ay, az, wx, wy, wz, mag)

    def step_python(self, t, ax, ay, az, wx, wy, wz, mag: SampleRing) -> None:
        """:meth:`step` on the Python reference (and any sample the compiled one does not take)."""
        f = self.f
        if f.initialized and t - f.t_us > self.gap_us:
            f.lose()                           # what the gyroscopes missed cannot be integrated
            self.lost = True
        slot = self._quiet(mag, t)
        if slot >= 0:
            self._ctv[0] = mag.time_at(slot)
            st = 1 if mag.flip_at(slot) else 0
            mx, my, mz = mag.field_at(slot)
            bb = f.bias_v
            self.flip.observe(self.compass_t, st, mx, my, mz, (wx - bb[0], wy - bb[1], wz - bb[2]),
                              self.max_age_us)
            s = 1.0 if st else -1.0
            o = self.flip.o
            mx -= s * o[0]
            my -= s * o[1]
            mz -= s * o[2]
        if not f.initialized:
            if slot >= 0:
                if self.lost:                  # found again in the same frame, offsets kept
                    self.lost = not f.reacquire(t, ax, ay, az, mx, my, mz)
                else:
                    f.initialize(t, ax, ay, az, mx, my, mz)
            return
        f.predict(t, wx, wy, wz)
        self.n += 1
        if self.n >= self.every:
            self.n = 0
            f.update_acc(ax, ay, az)
            if slot >= 0:
                f.update_mag(mx, my, mz)
                self.compass_used += 1
        elif slot >= 0 and f.learning:
            f.update_mag(mx, my, mz)          # learning |m| and the dip: every sample counts


class SourceInertial:
    """The source's IMU and magnetometer (thesis sec 6.2.3): its orientation
    ``Phi`` (a ch. 2 filter; identity until initialised) and its specific force
    in the global frame ``Phi f_source`` (eq 6.8)."""

    def __init__(self, node: int, cfg, gate: PulseGate, force=None, core=_DEFAULT_CORE):
        """``force``: how ``Phi f_source`` follows the source's accelerometer (default
        :class:`MeasuredForce`; ``source_unaccelerated.Unaccelerated`` keeps it ``-g``);
        ``core``: the numeric core of its orientation filter."""
        self.node = node
        self.force = MeasuredForce() if force is None else force
        self.imu = ImuRing(cfg.imu.imu_ring_capacity, core)
        self._s6 = [0.0] * 6                # one popped IMU sample (f, w)
        self.mag = SampleRing(max(16, int(cfg.pulse.mag_rate_hz)))
        self.ori = _Ori(cfg, gate, core=core)
        self.phi = np.eye(3)
        self.fref = np.zeros(3)
        self._phiv = memoryview(self.phi)
        self._fv = memoryview(self.fref)
        g = [-v for v in cfg.imu.gravity_mps2]
        self._fv[0], self._fv[1], self._fv[2] = g[0], g[1], g[2]
        self.samples = 0
        self.ori.bind_ring(self.mag)        # (its own ring: bound at start-up)

    fixed = False

    def on_imu(self, msg) -> None:
        """An IMU sample of a node that is not a tracked sensor: kept if it is the source's."""
        if msg.node == self.node:
            self.imu.push(msg)

    def on_mag(self, msg, lsb: float) -> None:
        """A MAG_SAMPLE of a node that is not a tracked sensor: kept if it is the source's."""
        if msg.node == self.node:
            self.mag.push(msg.t_us, msg.x * lsb, msg.y * lsb, msg.z * lsb, bool(msg.flip & 2), msg.flip & 1)

    def hold(self, t_next: int, now_us: int, wait_us: int) -> bool:
        """A sensor sample at ``t_next`` waits (True) until the source's samples reach its time
        (at most ``wait_us`` behind the clock ``now_us``); else the source is brought to it."""
        if self.imu.last_t < t_next and now_us - t_next < wait_us:
            return True
        self.process(t_next)
        return False

    def catch_up(self, until_us: int, pairs) -> None:
        """Process what no sensor sample of ``pairs`` waits for: up to ``until_us`` and the
        oldest sensor sample still queued."""
        until = until_us
        for _, ins in pairs:
            if len(ins.imu):
                t = ins.imu.tv[ins.imu.slot(0)]
                if t < until:
                    until = t
        self.process(until)

    def counters(self) -> dict:
        return {"source_imu_samples": self.samples}

    def queued(self) -> int:
        """IMU samples waiting in the ring."""
        return len(self.imu)

    def process(self, until_us: int | None = None) -> None:
        """Drain the IMU ring (up to the samples at ``until_us`` when given)."""
        ring, s6 = self.imu, self._s6
        tv = ring.tv
        while True:
            if until_us is not None and (len(ring) == 0 or tv[ring.slot(0)] > until_us):
                return
            t = ring.pop_sample(s6)
            if t < 0:
                return
            ax, ay, az, wx, wy, wz = s6
            self.ori.step(t, ax, ay, az, wx, wy, wz, self.mag)
            self.samples += 1
            f = self.ori.f
            if f.initialized:
                np.copyto(self.phi, f.R)
                self.force.update(self._phiv, self._fv, ax, ay, az)


class MeasuredForce:
    """``Phi f_source`` (eq 6.8, global frame, m/s^2) from the source's accelerometer sample."""

    def update(self, P, fv, ax: float, ay: float, az: float) -> None:
        """``fv`` (3,) = ``P`` (Phi, 3x3) times the sample ``(ax, ay, az)``."""
        for i in range(3):
            fv[i] = P[i, 0] * ax + P[i, 1] * ay + P[i, 2] * az


class FixedSource:
    """A source without an IMU (the null object of :class:`SourceInertial`): ``Phi = I`` and
    ``Phi f_source = -g`` (``-gravity_mps2``, m/s^2), no sample to keep, wait for or count."""

    fixed = True

    def __init__(self, cfg):
        self.phi = np.eye(3)
        self.fref = np.array([-v for v in cfg.imu.gravity_mps2])

    def on_imu(self, msg) -> None:
        """No source IMU: nothing to keep."""

    def on_mag(self, msg, lsb: float) -> None:
        """No source module: nothing to keep."""

    def hold(self, t_next: int, now_us: int, wait_us: int) -> bool:
        return False

    def catch_up(self, until_us: int, pairs) -> None:
        """Nothing to process."""

    def process(self, until_us: int | None = None) -> None:
        """Nothing to process."""

    def queued(self) -> int:
        """No samples wait."""
        return 0

    def counters(self) -> dict:
        return {}


def make_source(cfg, gate: PulseGate, core=_DEFAULT_CORE):
    """The source of ``cfg``, chosen once: its IMU and magnetometer (``source_imu_id``; taken as
    unaccelerated when ``source_acceleration`` is off: eq 6.8 without ``a_source`` in the
    comparison runs) or a fixed source."""
    if not cfg.link.source_imu_id:
        return FixedSource(cfg)
    return SourceInertial(cfg.link.source_imu_id, cfg, gate, MeasuredForce() if cfg.body.source_acceleration else Unaccelerated(),
                          core)


class _OneCall:
    """:meth:`SensorInertial.process` on the compiled core: a sample both filters take whole
    (``_Ori.takes``, ``FusionFilter.live_ready``) is one call (``ext.ImuSample`` through
    ``FusionFilter.live_sample``: the sample off the IMU ring, the orientation filter's step, the
    fusion filter's forward step, ``w_last``; the same steps in the same order), bound at the first
    such sample; any other goes through ``slow`` (the steps one by one)."""

    def __init__(self, imu, ori: _Ori, fusion, source, w_last, slow, count):
        """``count``: the sensor's processed samples (a memoryview of one int64), which :meth:`run`
        adds to."""
        self.imu, self.ori, self.fusion, self.source, self.w_last, self.slow = imu, ori, fusion, source, w_last, slow
        self._count = count
        self._phiv = memoryview(source.phi)
        self._frv = memoryview(source.fref)
        self.kernel = None
        self._ring = None
        self._hold = None if source.fixed else source.hold     # (a fixed source never holds)
        self._b = ()

    def run(self, mag: SampleRing, now_us: int = 0, wait_us: int = 0, max_steps: int = ALL_STEPS) -> int:
        """:meth:`SensorInertial.process`'s loop; the samples processed. Without a source that may hold
        a sample (a fixed source) the samples both filters take whole run in the compiled loop
        (``ext.ImuSample.drain``: :meth:`one`'s tests and bookkeeping on the owners' state arrays, in
        place; a sample whose prediction orthonormalises the orientation, and one whose step a pending
        snapshot splits while no replay runs, there too), which hands back each other sample (one that
        :meth:`one`'s tests send to ``slow`` too), and ``slow`` runs it."""
        if self._ring is not mag:
            self._bind(mag)
        if self._hold is not None:
            n = self._run_held(mag, now_us, wait_us, max_steps)
        else:
            drain = self._drain
            n = 0
            while n < max_steps:
                r = drain(max_steps - n)
                n += r >> 2
                if not r & 3:
                    break
                self.slow(mag)                         # (the oldest sample, which :meth:`one`'s tests
                n += 1                                 # refuse too: the steps one by one)
        self._count[0] += n
        return n

    def _run_held(self, mag: SampleRing, now_us: int, wait_us: int, max_steps: int) -> int:
        """:meth:`run` with a source whose samples a sensor sample may wait for (``hold``)."""
        peek, hold = self._b[0], self._hold
        t = peek()                                     # (the oldest sample's time; -1: none)
        n = 0
        while max_steps > 0 and t >= 0:
            max_steps -= 1
            if hold(t, now_us, wait_us):
                break
            self.one(mag, t)
            n += 1
            t = peek()
        return n

    def one(self, mag: SampleRing, t: int) -> None:
        """The oldest sample (at ``t``): in one call when both filters take it whole, else
        through ``slow`` (the steps one by one). (What does not change after :meth:`_bind` is read
        from one tuple made there.)"""
        peek, sample, begin, finish, f, pu, iu, cu, hold, phi, fr, cap, last = self._b
        ori, fus = self.ori, self.fusion
        if not (ori.settled(t) and fus.live_ready(t)):
            self.slow(mag)
            return
        h = last() + 1
        if h == cap:
            h = 0
        tp = f.t_us
        if t > tp and (f.steps + 1) & 63 == 0:         # (the prediction orthonormalises R)
            r = begin(tp, h, len(mag))
            if r >= 0:
                f.sample_done(t, r)
                r = fus.live_sample(finish, t, fr[0], fr[1], fr[2], phi, ori.n, pu.count, iu.count, cu.count)
        else:
            r = fus.live_sample(sample, t, fr[0], fr[1], fr[2], phi, tp, ori.n, h, len(mag), pu.count,
                                iu.count, cu.count)
        if not ori.sampled(t, r):
            self.slow(mag)

    def bind(self, mag: SampleRing) -> None:
        """Bind to ``mag`` at start-up (:meth:`_bind`), unless bound to it already."""
        if self._ring is not mag:
            self._bind(mag)

    def _bind(self, mag: SampleRing):
        """``ext.ImuSample`` bound to the rings, the filters' kernels (the orientation filter's as bound
        to ``mag``) and ``w_last``; with what :meth:`run` reads of it, the filters and ``mag``."""
        fus = self.fusion
        pimu, live, out = fus.prediction.imu, fus.history.live, fus.output.out
        ks = self.kernel = self.ori.kernel.ImuSample(self.ori.bind(mag), fus.prediction.live_kernel, self.imu.t,
                                                     self.imu.d, self.imu.hc, pimu.t, pimu.hc, live.t, live.hc,
                                                     out.t, out.hc, self.w_last, fus.st.pred._T2, SYMMETRIZE_EVERY)
        f = self.ori.f
        # (the filters' update objects: their counts are the kernel's arguments)
        self._b = (ks.peek, ks.sample, ks.begin, ks.finish, f, f.pred, f.incl.upd, f.compass.upd, self._hold,
                   self._phiv, self._frv, mag.capacity, mag.last_pushed_slot)
        ks.bind_state(f.state, f.compass.learn_state, self.ori.ns, f.pred.cst, f.incl.upd.kst, f.compass.upd.kst,
                      fus.fs, fus.st.ts, fus.st.pred.cst, fus.prediction.ps, fus.snap.sq, fus.recovery.rs, mag.hc,
                      self.source.fref, self.source.phi, self.ori.gap_us, fus.prm.max_gap_us)
        split = fus.live_split_kernel()
        if split is not None:          # (a sample with a snapshot inside its step, in the loop too)
            ks.bind_split(split, fus.snap.st.ts)
        self._drain = ks.drain
        self._ring = mag
        return ks


class SensorInertial(CompiledBurst):
    """IMU ring, ch. 2 filter ``Xi``, ch. 6 fusion filter and the motion
    compensation buffers of one sensor node."""

    def __init__(self, node: int, cfg, gate: PulseGate, source, compass_max_age_us: int | None = None,
                 burst_rms_s: float | None = None, core=_DEFAULT_CORE):
        """``source``: :class:`SourceInertial` or :class:`FixedSource` (:func:`make_source`);
        ``gate``: the compass gate; ``compass_max_age_us`` (default :class:`_Ori`'s) and
        ``burst_rms_s`` (default the fixed cycle's, below) are given by a pipeline whose bursts
        are not the fixed cycle's (AC blocks: ``track.ac``)."""
        self.node = node
        self._report = PoseReport(node)     # the fused POSE being sent (filled in place)
        self.cfg = cfg
        n = len(cfg.source.coils)
        self.imu = ImuRing(cfg.imu.imu_ring_capacity, core)
        self._s6 = [0.0] * 6                # one popped IMU sample (f, w)
        self.ori = _Ori(cfg, gate, compass_max_age_us, core)
        self.fusion = FusionFilter(FusionParams.from_config(cfg, not source.fixed), self.ori.f,
                                   imu_capacity=cfg.fusion.fusion_replay_capacity,
                                   history_capacity=cfg.fusion.fusion_history_capacity,
                                   output_capacity=cfg.fusion.pose_output_capacity, fixed_source=source.fixed,
                                   core=core)
        self._take = self.fusion.output.take_report     # the next queued fused pose into a record
        self._send_plain = self.fusion.output.send_plain    # the queued poses that need their frame alone
        self._recovery = self.fusion.recovery           # its restarts (read: the events on changes)
        self.source = source
        self._phi = source.phi
        self._phiv = memoryview(self._phi)
        self._fref = source.fref
        self._frv = memoryview(self._fref)
        # one burst: reference instant, compensated signals
        self.tr = np.zeros(1, dtype=np.int64)
        self._trv = memoryview(self.tr)
        self.fz = np.zeros(_FZ_N, dtype=np.int64)
        self._fzv = memoryview(self.fz)
        self.t_ref = 0
        self.pending = False
        self.S_comp = np.zeros((3, n))
        self._h_ref = np.zeros((3, n))
        self._h_j = np.zeros((3, n))
        self._p_ref = np.zeros(3)
        self._R_ref = np.zeros((3, 3))
        self._p_j = np.zeros(3)
        self._R_j = np.zeros((3, 3))
        self._pr = memoryview(self._p_ref)
        self._Rr = memoryview(self._R_ref)
        self._pj = memoryview(self._p_j)
        self._Rj = memoryview(self._R_j)
        self._Scv = memoryview(self.S_comp)
        self._hrv = memoryview(self._h_ref)
        self._hjv = memoryview(self._h_j)
        self.mag_position = np.zeros(3)
        self.mag_rotation = np.eye(3)
        self.mag_cov = np.zeros((6, 6))
        self.comp_position = np.zeros(3)   # the motion-compensated solution of the burst
        self.comp_rotation = np.eye(3)
        self.comp_cov = np.zeros((6, 6))
        self.waiting = False               # the last fuse found no room for the re-solve
        self._Cf = np.zeros((6, 6))        # covariance handed to the fusion update
        self._Cfv = memoryview(self._Cf)
        # rms time of the pulses about the burst's middle (n equally spaced pulses)
        self.burst_rms_s = cfg.timing.spacing_us * 1e-6 * math.sqrt((n * n - 1) / 12.0) if burst_rms_s is None \
            else float(burst_rms_s)
        self.w_last = np.zeros(3)          # latest rate, offset removed (rad/s)
        self._wlv = memoryview(self.w_last)
        self.sc = np.zeros(1, dtype=np.int64)     # the samples processed (``samples``)
        self._scv = memoryview(self.sc)
        if self.ori.one_call and self.fusion.st.ck is not None:
            # process on the compiled core (:class:`_OneCall`; an empty ring returns at once there)
            self._one = _OneCall(self.imu, self.ori, self.fusion, source, self.w_last, self._sample_python, self._scv)
            self.process = self._one.run
        self.comp_rejected = 0
        self.fused = 0
        self.last_fuse_flags = 0
        # recovery bookkeeping (events on changes): 0 tracking, 1 dead reckoning, 2 lost
        self.dr_state = 0
        self.recoveries_seen = 0
        self.kept_seen = 0
        self.poses_dead_reckoning = 0
        self.poses_lost = 0
        self.poses_out_of_range = 0     # fused poses beyond the working volume (sent, not valid)
        self._bind_burst_kernels(core, _COMP_MAX_VEL_SIGMA)

    def bind_ring(self, mag: SampleRing) -> None:
        """Bind the compiled core's per-sample kernels (the orientation filter's and the one-call
        sample's) to ``mag``, the magnetometer ring :meth:`process` is given (the tracker's, fixed
        at composition), at start-up rather than at the first sample inside a tick."""
        self.ori.bind_ring(mag)
        one = getattr(self, "_one", None)
        if one is not None:
            one.bind(mag)

    # ------------------------------------------------------------ per sample
    def process(self, mag: SampleRing, now_us: int = 0, wait_us: int = 0, max_steps: int = ALL_STEPS) \
            -> None:
        """Drain the IMU ring through Xi and the fusion filter, at most ``max_steps`` samples
        (the rest wait for the next tick: IMU steps given back from an IMU_DELTA pair arrive
        twelve at once). With the source's IMU (eq 6.8) a sample waits (at most ``wait_us``)
        until the source's samples reach its time, and the source is brought to that time
        first, so ``Phi f_source`` is the one of the same instant: the source's steps and the
        sensor's arrive an interval apart."""
        ring, s6 = self.imu, self._s6
        if not len(ring):
            return
        push = self.fusion.push_imu
        ori_step = self.ori.step
        b = self.ori.f.bias_v
        wl = self._wlv
        phi = self._phiv
        fr = self._frv
        hold = None if self.source.fixed else self.source.hold      # (a fixed source never holds)
        tv = ring.tv
        while max_steps > 0 and len(ring):
            max_steps -= 1
            if hold is not None and hold(tv[ring.slot(0)], now_us, wait_us):
                return
            t = ring.pop_sample(s6)
            ax, ay, az, wx, wy, wz = s6
            ori_step(t, ax, ay, az, wx, wy, wz, mag)
            push(t, ax, ay, az, wx, wy, wz, fr[0], fr[1], fr[2], phi)
            self.samples += 1
            wl[0], wl[1], wl[2] = wx - b[0], wy - b[1], wz - b[2]

    def _sample_python(self, mag: SampleRing) -> None:
        """The oldest sample through :meth:`process`'s steps one by one."""
        s6 = self._s6
        t = self.imu.pop_sample(s6)
        ax, ay, az, wx, wy, wz = s6
        self.ori.step(t, ax, ay, az, wx, wy, wz, mag)
        fr = self._frv
        self.fusion.push_imu(t, ax, ay, az, wx, wy, wz, fr[0], fr[1], fr[2], self._phiv)
        b = self.ori.f.bias_v
        wl = self._wlv
        wl[0], wl[1], wl[2] = wx - b[0], wy - b[1], wz - b[2]

    def on_solution(self, solver, solved: bool) -> None:
        """The burst's magnetic-only solution (``solver`` holds it) is to be fused; none
        (``solved`` False): nothing to fuse."""
        if solved:
            np.copyto(self.mag_position, solver.position)
            np.copyto(self.mag_rotation, solver.rotation)
            np.copyto(self.mag_cov, solver.covariance)
            self.pending = True
            self.stage = _COMPENSATE
        else:
            self.pending = False

    def send_fused(self, tx, node: int, range_m: float, quality) -> None:
        """Send the fused poses the fusion filter queued (``POSE_FUSED``, with ``quality``, that
        of the last magnetic solution), their status from the filter's bits; the recovery and
        dead-reckoning events on changes."""
        rec = self._recovery
        if rec.recoveries != self.recoveries_seen:
            kept = rec.biases_kept != self.kept_seen
            self.recoveries_seen = rec.recoveries
            self.kept_seen = rec.biases_kept
            tx.event(EVT_TRACK_REINIT, node | (rec.recovery_reason << 8) | ((1 << 12) if kept else 0))
        if not self.dr_state and self._send_plain(tx, node, _FUSED_VALID, quality, range_m):
            return                             # (each sent as below: no OUT_* bit, in range)
        r = self._report
        take = self._take
        st = take(r)                           # time, position, quaternion, variances; -1: none
        if st < 0:
            return
        rp = r.p
        pose = tx.pose
        while st >= 0:
            status = self._status(st) if st else _FUSED_VALID
            if st or self.dr_state:
                self._dead_reckoning(tx, node, st)
            if status & POSE_VALID and not in_range3(rp[0], rp[1], rp[2], range_m):
                status &= ~POSE_VALID          # diverged: beyond the working volume, not a pose
                self.poses_out_of_range += 1
            r.node, r.status, r.quality = node, status, quality
            pose(r)
            st = take(r)

    def _status(self, st: int) -> int:
        """The POSE status of a fused pose with the filter's ``OUT_*`` bits ``st``."""
        status = POSE_VALID | POSE_FUSED
        if st & OUT_STALE:
            status |= POSE_STALE
        if st & OUT_INCONSISTENT:
            status |= POSE_INCONSISTENT
        if st & OUT_RECOVERED:
            status |= POSE_RECOVERED
        if st & OUT_DEAD_RECKONING:
            status |= POSE_DEAD_RECKONING
            self.poses_dead_reckoning += 1
            if st & OUT_LOST:          # past what the filter vouches for: sent, not valid
                status &= ~POSE_VALID
                self.poses_lost += 1
        return status

    def _dead_reckoning(self, tx, node: int, st: int) -> None:
        """``EVT_DEAD_RECKONING`` when the dead-reckoning state (0 tracking, 1 dead
        reckoning, 2 lost) of the filter's bits ``st`` changes."""
        dr = 0
        if st & OUT_DEAD_RECKONING:
            dr = 2 if st & OUT_LOST else 1
        if dr != self.dr_state:
            if dr > self.dr_state:
                tx.event(EVT_DEAD_RECKONING, node | ((1 << 8) if dr == 2 else 0))
            elif dr == 0:
                tx.event(EVT_DEAD_RECKONING, node | (1 << 9))
            self.dr_state = dr

    def schedule(self, t_ref: int) -> None:
        """A burst was commanded; its pose will refer to ``t_ref``."""
        self.t_ref = int(t_ref)
        self.fusion.schedule_snapshot(self.t_ref)

    # ------------------------------------------------------------ per burst
    def compensate_begin(self, solver, S, currents) -> bool:
        """Start bringing the pulses to ``t_ref`` (thesis sec 6.5): ``S_c[:, j] = S[:, j] + h_j(x_ref) - h_j(x_j)`` with
        the inertial poses ``x_j`` at pulse ``j``'s mean sample time and ``x_ref`` at ``t_ref``. This step predicts
        ``h(x_ref)``; :meth:`compensate_step` does the pulses. False (``S_comp = S``) when the filter cannot tell the
        motion: it knows its velocity worse than the motion it is to remove, or its history does not reach ``t_ref``."""
        np.copyto(self.S_comp, S)
        fus = self.fusion
        if not fus.initialized or fus.velocity_sigma() > _COMP_MAX_VEL_SIGMA \
                or not fus.pose_at(self.t_ref, self._pr, self._Rr):
            return False
        solver.predict_signals(self._pr, self._Rr, currents, self._h_ref)
        self._comp_j = 0
        return True

    def compensate_step(self, solver, S, currents, pulse_t, budget: int) -> int:
        """Correct the next pulses, ``n`` field evaluations each, within ``budget`` (at least one pulse); returns 1 when
        all are done, 0 while some are left, -1 (``S_comp = S``) when the history misses a pulse's time (``pulse_t[j]``,
        memoryview of int)."""
        n = self.S_comp.shape[1]
        Sc, hr, hj = self._Scv, self._hrv, self._hjv
        fus = self.fusion
        used = 0
        while self._comp_j < n and (used == 0 or used + n <= budget):
            j = self._comp_j
            if not fus.pose_at(pulse_t[j], self._pj, self._Rj):
                np.copyto(self.S_comp, S)
                return -1
            solver.predict_signals(self._pj, self._Rj, currents, self._h_j)
            for i in range(3):
                Sc[i, j] = Sc[i, j] + hr[i, j] - hj[i, j]
            used += n
            self._comp_j += 1
        if self._comp_j < n:
            return 0
        self.compensated += 1
        return 1

    def fuse(self, solver, S, currents, sigma, pulse_t, budget: int, replay_budget: int, fresh: bool,
             e0: int | None = None) -> bool:
        """Fusing the burst whose magnetic-only solution is in ``mag_*``, as far
        as this tick allows; returns True when the burst is fused (or dropped).
        (``e0``: the solver's evaluation count where this call began, when the compiled start of
        this call ran before, :meth:`_fuse_compiled`; its evaluations count against ``budget``.)

        0. with motion compensation, bring the pulses to ``t_ref``
           (:meth:`compensate_begin`, :meth:`compensate_step`) and solve again
           (started from the magnetic-only solution): these steps follow one
           another within ``budget`` field evaluations;
        1. update the fusion filter at ``t_ref`` with the compensated solution
           and its covariance, in two ticks (``FusionFilter.prepare_magnetic_update``,
           ``apply_magnetic_update``); if the update is rejected (the inertial
           motion was wrong), the magnetic-only one is offered instead;
        2. replay the IMU samples since ``t_ref``, ``replay_budget`` of them
           per tick, on the filter's shadow state (the fused outputs go on from
           the live state meanwhile).

        The update and the replay steps (no field evaluation, but the heaviest
        matrix work) each take a tick of their own: only a ``fresh`` tick (no
        other work done in it) and no evaluation spent before them.

        The solver's covariance assumes the sensor still during the burst. The
        motion left in the signals is added to it: without compensation the
        motion itself (``|v| t_rms`` and ``|w| t_rms`` per axis, ``t_rms`` the
        rms pulse time about the middle of the burst), and the position error
        the rotation makes: the pulses are measured in frames turned by about
        ``|w| t_rms`` from one another, which turns the coil fields' mutual
        angles (the invariants ``h_i . h_j`` the position comes from, thesis
        Appendix 5.A, eqs 5.9-5.16) by as much and moves the solution sideways
        by about ``r |w| t_rms`` at range ``r`` (4 mm at 18 cm and 15 deg/s).
        Near the source the noise alone claims 0.2-0.4 mm while the
        magnetic-only solutions of a turning sensor are 5-10 mm off: without
        the term the fused track took them at their word and 4.6 % of the
        valid poses of roetenberg-fusion seed 1 (120 s) were overconfident,
        0.5 % with it. With compensation: the error of the inertial motion
        (velocity uncertainty times ``t_rms``)."""
        n = self.S_comp.shape[1]
        if e0 is None:
            e0 = solver.signal.evals
        self.waiting = False
        while self.stage in (_COMPENSATE, _COMPENSATE_PULSES, _SOLVE):
            left = budget - (solver.signal.evals - e0)
            if left < n:
                self.waiting = solver.signal.evals == e0     # no room at all in this tick
                return False
            self._measure_step(solver, S, currents, sigma, pulse_t, left)
        if not fresh or solver.signal.evals != e0:
            return False
        return self._filter_step(replay_budget)

    def _measure_step(self, solver, S, currents, sigma, pulse_t, budget: int) -> None:
        """One step of the motion-compensated re-solve, within ``budget`` evaluations."""
        stage = self.stage
        if stage == _COMPENSATE:
            self.comp_ok = False
            self.stage = _UPDATE_MAG
            if self.cfg.fusion.motion_compensation and self.compensate_begin(solver, S, currents):
                self.stage = _COMPENSATE_PULSES
        elif stage == _COMPENSATE_PULSES:
            done = self.compensate_step(solver, S, currents, pulse_t, budget)
            if done < 0:
                self.stage = _UPDATE_MAG
            elif done:
                self._begin_solve(solver, currents, sigma)
        else:
            st = solver.step(budget)
            if st & SOLVE_RUNNING:
                return
            if not st & (SOLVE_NONFINITE | SOLVE_NO_START | SOLVE_BAD_INPUT):
                np.copyto(self.comp_position, solver.position)
                np.copyto(self.comp_rotation, solver.rotation)
                np.copyto(self.comp_cov, solver.covariance)
                self.comp_ok = True
            self.stage = _UPDATE_COMP if self.comp_ok else _UPDATE_MAG

    def _begin_solve(self, solver, currents, sigma) -> None:
        """The compensated pulses solved again, started from the magnetic-only solution."""
        st = solver.begin(self.S_comp, currents, sigma, self.mag_position, self.mag_position, self.mag_rotation)
        self.stage = _SOLVE if st & SOLVE_RUNNING else _UPDATE_MAG

    def _filter_step(self, replay_budget: int) -> bool:
        """One tick of the fusion filter's part: prepare an update (restore the snapshot, evaluate the measurement),
        apply it (gain, Joseph update), or a step of its replay."""
        fus = self.fusion
        stage = self.stage
        if stage in (_UPDATE_COMP, _UPDATE_MAG):
            comp = stage == _UPDATE_COMP
            self._motion_cov(self.comp_cov if comp else self.mag_cov, comp)
            p, R = (self.comp_position, self.comp_rotation) if comp else (self.mag_position, self.mag_rotation)
            flags = fus.prepare_magnetic_update(self.t_ref, p, R, self._Cf, final=not comp)
            if flags == FUS_PREPARED:
                self.stage = _APPLY_COMP if comp else _APPLY_MAG
                return False
            return self._updated(flags)
        if stage in (_APPLY_COMP, _APPLY_MAG):
            flags = fus.apply_magnetic_update()
            if stage == _APPLY_COMP and flags & (EKF_GATED | EKF_NOT_PD | EKF_NONFINITE):
                self.comp_rejected += 1        # the inertial motion was wrong: offer the burst as measured
                self.stage = _UPDATE_MAG
                return False
            return self._updated(flags)
        if fus.step(replay_budget):
            self._done()
            return True
        return False

    def _updated(self, flags: int) -> bool:
        self.last_fuse_flags = flags
        self.fused += 1
        if self.fusion.replaying:
            self.stage = _REPLAY
            return False
        self._done()
        return True

    def _done(self) -> None:
        self.stage = _COMPENSATE
        self.pending = False

    def _motion_cov(self, C, compensated: bool) -> None:
        """``_Cf = C`` plus the motion left in the burst (see :meth:`fuse`)."""
        self.motion_cov(C, compensated, self._Cf, self.mag_position)

    def motion_cov(self, C, compensated: bool, out, p) -> None:
        """``out = C`` plus the motion left in a burst solved at ``p`` (see :meth:`fuse`)."""
        fus = self.fusion
        np.copyto(out, C)
        tr2 = self.burst_rms_s * self.burst_rms_s
        if compensated:
            sv = fus.velocity_sigma()
            ap = sv * sv * tr2
            ao = 0.0
        else:
            wl = self._wlv
            ao = (wl[0] * wl[0] + wl[1] * wl[1] + wl[2] * wl[2]) * tr2
            ap = fus.speed_squared() * tr2 if fus.initialized else 0.0
            ap += (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) * ao
        for i in range(3):
            out[i, i] += ap
            out[3 + i, 3 + i] += ao


class BurstFusionTracker(SolveTick, MagneticTracker):
    """Magnetic-only poses of each burst, fused with the inertial data
    (thesis ch. 6): the IMU samples drive each sensor's fusion filter and
    leave as fused POSEs at the IMU rate; after a burst's magnetic solve, the
    delayed update of the fusion filter at the burst's middle follows in the
    next ticks (``SensorInertial.fuse``), never in the tick of a solve."""

    def __init__(self, cfg, coils, channels, schedule, burst, supervisor, tx, solvers, core=_DEFAULT_CORE):
        super().__init__(cfg, coils, channels, schedule, burst, supervisor, tx, solvers, core)
        self.core = core
        gate = PulseGate(schedule.start, schedule.end, cfg.pulse.fall_us, cfg.orientation.compass_guard_us)
        self.source = make_source(cfg, gate, core)    # the source's IMU, or fixed: chosen once
        self.inertial = {ch.node: self._sensor_inertial(ch.node, cfg, gate) for ch in self.channels}
        self._pairs = tuple((ch, self.inertial[ch.node]) for ch in self.channels)
        for ch, ins in self._pairs:         # each sensor's kernels bound to its ring at start-up
            ins.bind_ring(self._ring_of(ch))
        # a sensor sample waits this long for the source's samples of its time (1.5 IMU_DELTA intervals)
        self.source_wait_us = int(1.5e6 / cfg.imu.imu_delta_rate_hz)
        self.imu_steps = cfg.budget.imu_steps_per_tick
        self.replay_budget = cfg.budget.replay_budget_steps
        self.deferred = 0               # ticks whose fusion step waited behind IMU samples
        self.imu_sample_evals = cfg.budget.imu_sample_evals
        self._imu_last = 0              # IMU samples processed in this tick (charged: _tick_charges)
        self._deferring = False
        # no IMU sample queued, the sensors' or the source's, since the last step drained the rings
        # (see step): cleared by every sample the tracker is given
        self._idle = False
        self._n_pending = 0             # sensors with a delayed magnetic update under way (``pending``)
        # the compensated re-solve starts from the burst's own solution: no consistency gate
        # (its sigma leaves out the compensation's error) and no fall-back to acquisition
        self.comp_solver = solvers(1.0)
        stages = (SensorInertial.fuse, SensorInertial._measure_step, SensorInertial.on_solution,
                  SensorInertial.compensate_begin, SensorInertial.compensate_step, SensorInertial._begin_solve)
        for ch, ins in self._pairs:         # the start of each sensor's fusion update: one call (compiled core)
            ins.bind_fuse(core, self.comp_solver, self.solver, ch.S, ch.pulse_mid, self.currents, (FS_INIT, FS_N),
                          stages, (_SOLVE, _UPDATE_MAG))
        self._rep_cov = np.zeros((6, 6))     # the covariance a magnetic-only POSE is sent with
        self._bind_report_chain(core)
        self._bind_burst_open(core)
        self._bind_fused_tick(core)
        self._bind_scan(core)
        self._bind_handover(core)

    def _ring_of(self, ch):
        """The magnetometer ring sensor ``ch``'s inertial part is fed from (:meth:`_process`)."""
        return ch.ring

    def _sensor_inertial(self, node: int, cfg, gate: PulseGate) -> SensorInertial:
        """The inertial part of sensor ``node`` (a pipeline of other bursts builds it with its own
        compass gate and timing: ``track.ac``)."""
        return SensorInertial(node, cfg, gate, self.source, core=self.core)

    # ------------------------------------------------------------ inputs
    def on_imu(self, msg, now_us: int) -> None:
        self._idle = False
        ins = self.inertial.get(msg.node)
        if ins is not None:
            ins.imu.push(msg)
        else:
            self.source.on_imu(msg)

    def on_mag(self, msg, lsb: float) -> None:
        """A MAG_SAMPLE of a node that is not a tracked sensor: the source's module."""
        self.source.on_mag(msg, lsb)

    def on_burst(self, t_ref: int) -> None:
        """Each sensor's :meth:`SensorInertial.schedule`; on the compiled core one call
        (:meth:`_bind_burst_open`)."""
        for ins in self.inertial.values():
            ins.schedule(t_ref)

    def _bind_burst_open(self, core) -> None:
        """On the compiled core :meth:`on_burst` is one call (``ext.Schedules``: ``ct_schedule`` for
        each sensor, the writes of :meth:`SensorInertial.schedule` with its snapshot's, bound here to
        the sensors' ``tr`` and their snapshots' ``sq``); a sensor of another kind keeps the loop."""
        ins = tuple(self.inertial.values())
        if core.ext is None or not ins or type(self).on_burst is not BurstFusionTracker.on_burst or any(type(i).schedule is not SensorInertial.schedule
                                              or type(i.fusion).schedule_snapshot is not FusionFilter.schedule_snapshot
                                              or type(i.fusion.snap).schedule is not Snapshot.schedule for i in ins):
            return
        self._sched_k = core.ext.Schedules(tuple(i.tr for i in ins), tuple(i.fusion.snap.sq for i in ins))
        self.on_burst = self._sched_k.run

    # ------------------------------------------------------------ tick
    def step(self, now_us: int) -> None:
        """Predict (drain the IMU rings: the source's first, its orientation and
        specific force feed eq 6.8), solve, fuse, and send the fused poses.

        A quiet tick returns at once: no IMU sample queued (``_idle``, set by a step that
        drained the rings, cleared by :meth:`on_imu`), no sensor fusing (``_n_pending``, kept
        as updates begin and end) and no burst to solve or solve ahead (read live). The full
        step would do nothing in it but clear ``_imu_last``, ``_waited`` and ``_deferring``.
        Nor does the full step visit the sensors for what they do not have: the rings only
        when a sample may be queued, the fused outputs only of a tick that processed IMU
        samples or fused a burst (a filter queues a pose or restarts in those calls only)."""
        if self._idle and not self._n_pending and not self.busy() and not (self.ahead and self._ahead_pending()):
            self._imu_last = 0
            self._waited = False
            self._deferring = False
            return
        self._step(now_us)

    def _step(self, now_us: int) -> None:
        """:meth:`step`'s work."""
        n = 0 if self._idle else self._process(now_us)
        self._imu_last = n
        fusing = self._n_pending > 0
        fresh = not self.busy()
        # bounded tick: a tick that propagated IMU samples (the fused tick) leaves the fusion
        # step (the update or a replay step) to the next one, at most one tick in a row (so it
        # always progresses). (Putting off the solve steps too changes the fused figures for the
        # same seed, roetenberg-fusion seed 1: 38.83 against 38.80 mm; this leaves them as they were.)
        if n and not self._deferring and fusing and fresh:
            self._deferring = True
            self.deferred += 1
            self._send_fused()
            return
        self._deferring = False
        solve = not fresh or (self.ahead and not fusing and self._ahead_pending())
        if not solve and not fusing:
            self._waited = False         # (what _fuse_step does with nothing to fuse)
            if n:
                self._send_fused()
            return
        e0 = self.solver.signal.evals
        charges = self._charges()
        if solve:
            super().step(now_us, charges)     # (a tick with nothing to fuse may solve ahead)
        fused = None
        if not self.busy():          # what the magnetic solves left of the budget goes to fusing
            fused = self._fuse_step(self.budget - charges - (self.solver.signal.evals - e0), fresh, charges)
        if n:
            self._send_fused()
        elif fused is not None:          # the one sensor whose filter was touched in this tick
            fused.send_fused(self.tx, fused.node, self.range_m, self.quality.last[fused.node])

    def _process(self, now_us: int) -> int:
        """Drain the sensors' IMU rings (and the source's, up to what no sensor sample waits
        for: at most the wait behind the clock); the samples processed. Sets ``_idle`` when
        nothing is left queued."""
        n = 0
        left = False
        wait = self.source_wait_us
        steps = self.imu_steps
        for ch, ins in self._pairs:
            n -= ins.samples
            ins.process(ch.ring, now_us, wait, steps)
            n += ins.samples
            if len(ins.imu):
                left = True
        src = self.source
        if not src.fixed:
            src.catch_up(now_us - wait, self._pairs)
            if src.queued():
                left = True
        self._idle = not left
        return n

    def _bind_fused_tick(self, core) -> None:
        """The fused tick in few calls on the compiled core with a fixed source, where every sensor
        drains through :class:`_OneCall` and sends through the reference's
        :meth:`SensorInertial.send_fused`: :meth:`_send_fused` is :meth:`_send_fused_plain` (each
        sensor's plain poses in one transmitter call) and, unless a subclass has its own step,
        :meth:`_process` is :meth:`_process_fused` (the sensors' samples in one call,
        ``ext.FusedTick.process``: each sensor's ``ImuSample.drain`` and its count,
        ``core/py_fusimu.c``) and :meth:`step` :meth:`_step_fast`. Bound once; anything else keeps
        the reference methods."""
        ins = tuple(i for _, i in self._pairs)
        if core.ext is None or not ins or not self.source.fixed or getattr(self.tx, "core", None) != "compiled" or \
                getattr(type(self), "_send_fused") is not BurstFusionTracker._send_fused or any(
                getattr(i, "_one", None) is None or i.process != i._one.run or i._one.kernel is None
                or type(i).send_fused is not SensorInertial.send_fused
                or getattr(i._send_plain, "__func__", None) is not type(i.fusion.output)._send_plain_compiled
                for i in ins):
            return
        self._ft_send = tuple((ch.node, i, i.fusion.output._ck, i._recovery) for ch, i in self._pairs)
        self._send_fused = self._send_fused_plain
        self._bind_solve_tick(BurstFusionTracker, _FUSED_VALID)
        if any(getattr(type(self), m) is not getattr(BurstFusionTracker, m)
               for m in ("step", "_step", "_process", "busy")):
            return
        self._ft_done = np.zeros(2, dtype=np.int64)
        self._ft_donev = memoryview(self._ft_done)
        self._ft_process = core.ext.FusedTick(tuple(i._one.kernel for i in ins), tuple(i.sc for i in ins),
                                              self._ft_done).process
        self._process = self._process_fused
        self.step = self._step_fast

    def _step_fast(self, now_us: int) -> None:
        """:meth:`step` (bound by :meth:`_bind_fused_tick`): a tick with IMU samples queued, no sensor
        fusing and no burst to solve or solve ahead is :meth:`_step`'s part for it, the samples drained
        (:meth:`_process` in one compiled call) and their fused poses sent; any other tick the
        reference's (:meth:`_step`, through its compiled form ``_step_solving``, or :meth:`step`'s quiet
        tick: the same tests, ``busy`` read in place)."""
        if self._n_pending or self._next >= 0 or self.burst.complete or (self.ahead and self._ahead_pending()):
            self._step_solving(now_us)
            return
        if self._idle:                   # (step's quiet tick)
            self._imu_last = 0
            self._waited = False
            self._deferring = False
            return
        r = self._ft_process(self.imu_steps)
        if r & 1:
            n = self._process_back(now_us, r >> 2)
        else:
            self._idle = not r & 2
            n = r >> 2
        self._imu_last = n
        self._deferring = False
        self._waited = False
        if n:
            self._send_fused()

    def _process_fused(self, now_us: int) -> int:
        """:meth:`_process` in one compiled call (bound by :meth:`_bind_fused_tick`: the ticks
        :meth:`_step_fast` leaves to the reference, a solve's or a fusion's, drain their samples
        through it too)."""
        r = self._ft_process(self.imu_steps)
        if r & 1:
            return self._process_back(now_us, r >> 2)
        self._idle = not r & 2
        return r >> 2

    def _process_back(self, now_us: int, n: int) -> int:
        """The rest of :meth:`_process` after ``FusedTick.process`` ran ``n`` samples and stopped at a
        sensor whose drain handed one back: the reference's loop from that sensor on."""
        k, done = self._ft_donev[0], self._ft_donev[1]
        wait, steps = self.source_wait_us, self.imu_steps
        left = False
        for j, (ch, ins) in enumerate(self._pairs):
            if j >= k:
                n += ins.process(ch.ring, now_us, wait, steps - done if j == k else steps)
            if len(ins.imu):
                left = True
        self._idle = not left
        return n

    def _send_fused_plain(self) -> None:
        """:meth:`_send_fused` (bound by :meth:`_bind_fused_tick`): each sensor's queued plain poses
        in one transmitter call (``Transmitter.fused_pose``, as ``PoseOutput.send_plain`` calls it),
        the sensor's :meth:`SensorInertial.send_fused` for what is left (a pose with an ``OUT_*``
        bit or out of range) and while a recovery or dead reckoning is to be reported."""
        tx, last, rm = self.tx, self.quality.last, self.range_m
        fused_pose = tx.fused_pose
        for node, ins, kernel, rec in self._ft_send:
            if ins.dr_state or rec.recoveries != ins.recoveries_seen or fused_pose(kernel, node, _FUSED_VALID,
                                                                                    last[node], rm):
                ins.send_fused(tx, node, rm, last[node])

    def _tick_charges(self) -> int:
        """The windows closed and ``imu_sample_evals`` per IMU sample processed in this tick."""
        return super()._tick_charges() + self.imu_sample_evals * self._imu_last

    def _ahead_wanted(self, ch) -> bool:
        """A sensor whose fusion filter runs starts from the filter's pose, not from a burst solved ahead."""
        return not self.inertial[ch.node].fusion.initialized

    def _ahead_wanted_flags(self):
        """:meth:`_ahead_wanted` as arrays for the compiled scan: each sensor's fusion filter's
        ``initialized`` entry (``FusionFilter.fs[FS_INIT]``); None before the sensors are made or
        where a filter keeps it otherwise."""
        ins = getattr(self, "inertial", None)
        if ins is None or type(self)._ahead_wanted is not BurstFusionTracker._ahead_wanted:
            return None
        fus = [ins[ch.node].fusion for ch in self.channels]
        if any(type(f).initialized is not FusionFilter.initialized or not isinstance(getattr(f, "fs", None), np.ndarray)
               for f in fus):
            return None
        return tuple((f.fs, FS_INIT) for f in fus)

    def warm_start(self, ch, tp) -> bool:
        """The fusion filter's pose at the burst's middle when it has one (it
        carries the motion since the last burst), else the last solution."""
        ins = self.inertial[ch.node]
        fus = ins.fusion
        if tp.have_pose and fus.initialized and fus.pose_at(ins.t_ref, tp.warm_p, tp.warm_R) \
                and in_range(tp.warm_p, self.range_m):
            return True
        return super().warm_start(ch, tp)

    def reported_covariance(self, ch, cov):
        """The magnetic-only POSE's covariance: the solver's plus the motion within the burst
        the IMU saw (:meth:`SensorInertial.fuse`), so a sensor turning near the source is not
        sent with the noise's 0.2 mm."""
        self.inertial[ch.node].motion_cov(cov, False, self._rep_cov, self.solver.position)
        return self._rep_cov

    _chain_covariance = reported_covariance

    def _chain_motion(self, ch):
        """The compiled report's motion (``SensorInertial.motion_cov``'s inputs: the rate, the
        fusion filter's velocity, the burst's rms time) and its output :attr:`_rep_cov`."""
        ins = self.inertial[ch.node]
        return ins.w_last, ins.fusion.st.v, self._rep_cov, ins.burst_rms_s, ins.fusion

    def _bind_report_chain(self, core) -> None:
        """Bound once the sensors' filters exist (the end of ``__init__``), with :meth:`_bind_warm`."""
        if hasattr(self, "_rep_cov"):
            super()._bind_report_chain(core)
            self._bind_warm(core)

    def _bind_warm(self, core) -> None:
        """:meth:`warm_start` on the compiled core: one ``WarmStart`` per sensor (``core/src/report.c``
        ``ct_report_warm_start``: ``PoseHistory.pose_at`` over the fusion filter's live history, the
        range check and the tracked pose's copies; the same operations, the same bits) bound to that
        history and the tracked pose; replaced on this instance. Left to the Python where a class
        overrides :meth:`warm_start` or the filter's ``pose_at``, or the history is of another kind."""
        from coiltrack.firmware.estimate.fusion_output import PoseHistory
        from coiltrack.firmware.estimate.fusion_state import HIST_P, HIST_R
        from coiltrack.firmware.estimate.magnetic_inertial import FilterView
        ext = core.ext
        if ext is None or type(self).warm_start is not self._warm_reference() or (HIST_P, HIST_R) != (0, 3):
            return
        warms = {}
        for ch in self.channels:
            ins = self.inertial[ch.node]
            tp = self.poses[ch.node]
            try:
                fus = ins.fusion
                hist = fus.history.live
                if type(fus).pose_at is not FilterView.pose_at or type(fus.history).pose_at is not PoseHistory.pose_at:
                    return
                warms[ch.node] = (ext.WarmStart(hist.capacity, hist.width, hist.t, hist.d, hist.hc, tp.position,
                                                tp.rotation, tp.warm_p, tp.warm_R), ins)
            except (AttributeError, TypeError, ValueError):
                return
        self._warms = warms
        self.warm_start = self._warm_start_compiled
        if self._warm_reference() is BurstFusionTracker.warm_start:
            self._bind_start(core, tuple((self.inertial[ch.node].fusion.history.live, self.inertial[ch.node].tr,
                                          self.inertial[ch.node].fusion.fs) for ch in self.channels))

    def _warm_reference(self):
        """The :meth:`warm_start` whose operations :meth:`_warm_start_compiled` repeats."""
        return BurstFusionTracker.warm_start

    def _warm_start_compiled(self, ch, tp) -> bool:
        w, ins = self._warms[ch.node]
        return w.warm(ins.t_ref, tp.have_pose, ins.fusion.initialized, self.range_m)

    def on_solution(self, ch, solved: bool) -> None:
        ins = self.inertial[ch.node]
        was = ins.pending
        ins.on_solution(self.solver, solved)
        self._n_pending += int(ins.pending) - int(was)

    def _fuse_step(self, budget: int, fresh: bool, charges: int = 0):
        """This tick's part of one sensor's delayed magnetic update (``charges``: what of the
        budget the tick's other work took; a re-solve that found no room waits one tick only);
        the sensor fused (:class:`SensorInertial`), None when none is pending."""
        self._waited = False
        if not self._n_pending:
            return None
        for ch, ins in self._pairs:
            if ins.pending:
                ins.fuse(self.comp_solver, ch.S, self.currents, ch.sigma, ch.pmv, budget, self.replay_budget, fresh)
                self._waited = bool(charges) and ins.waiting
                if not ins.pending:
                    self._n_pending -= 1
                return ins
        return None

    def _send_fused(self) -> None:
        """Send the fused poses queued by the fusion filters (IMU rate)."""
        for ch, ins in self._pairs:
            ins.send_fused(self.tx, ch.node, self.range_m, self.quality.last[ch.node])

    def counters(self) -> dict:
        ins = tuple(self.inertial.values())
        d = super().counters()
        d.update({
            "imu_samples": sum(i.samples for i in ins),
            "fusion_updates": sum(i.fusion.updates for i in ins),
            "fusion_rejected": sum(i.fusion.rejected for i in ins),
            "fusion_reinits": sum(i.fusion.reinits for i in ins),
            "fusion_recoveries": sum(i.fusion.recoveries for i in ins),
            "fusion_biases_kept": sum(i.fusion.biases_kept for i in ins),
            "fused_poses_dead_reckoning": sum(i.poses_dead_reckoning for i in ins),
            "fused_poses_lost": sum(i.poses_lost for i in ins),
            "fused_poses_out_of_range": sum(i.poses_out_of_range for i in ins),
            "imu_orientation_reacquired": sum(i.ori.f.reacquired for i in ins),
            "fusion_compensated": sum(i.compensated for i in ins),
            "fusion_output_dropped": sum(i.fusion.out_dropped for i in ins),
            "compass_updates": sum(i.ori.compass_used for i in ins),
        })
        d.update(self.source.counters())
        return d
