"""Trackers and pipeline of AC excitation.

The AC pipeline (``excitation = "ac"``, composed by :mod:`coiltrack.firmware.compose`):
actuate :class:`coiltrack.firmware.actuate.ac.ACActuation` (the drive plan),
measure :class:`coiltrack.firmware.measure.ac_blocks.ACBlockMeasurement`
(synchronous demodulation into blocks), track the pulsed-DC trackers behind
the same interface: each block is a burst whose signal matrix ``S`` (3, n),
``sigma`` (3, n) and currents (n,) go to the pose solver
(``PoseSolver.begin(S, currents, sigma, ...)``), so any solver with that
interface serves AC blocks as it serves pulse windows.

* :class:`ACMagneticTracker`: a magnetic pose per block (111 Hz at the
  default 9 ms hop), ``POSE_DISTORTED`` when the block's quadrature exceeds
  ``ac_distortion_ratio`` of its in-phase part and its chi-square quantile
  at ``ac_distortion_probability``.
* :class:`ACFusionTracker`: the thesis ch. 6 fusion filter
  (:class:`coiltrack.firmware.track.burst_fusion.BurstFusionTracker`) fed
  with the blocks' solutions, fused poses at the IMU rate. The filter keeps
  one snapshot for a delayed update: it is scheduled for the middle of the
  next block not yet begun, and the blocks solved while an update and its
  replay run are sent as magnetic poses without updating the filter. The
  orientation filter's compass is the blocks' DC term (the earth field
  without the coils' fields); no motion compensation (a block is an average
  over ``ac_window_us``; the motion left enters the covariance with the rms
  time ``T_w / sqrt(12)`` of a uniform block).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from coiltrack.protocol.schema import AC_FAULT_REFUSED, COIL_FAULT_REFUSED, POSE_DISTORTED

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.actuate.ac import AC_STATUS_ID, ACActuation
from coiltrack.firmware.measure.ac_blocks import ACBlockMeasurement
from coiltrack.firmware.track.burst_fusion import ALL_STEPS as _ALL_STEPS
from coiltrack.firmware.track.burst_fusion import BurstFusionTracker, PulseGate, SensorInertial
from coiltrack.firmware.track.magnetic import MagneticTracker
from coiltrack.firmware.track.solve_tick import SolveTick


class _AlwaysQuiet(PulseGate):
    """The compass gate of AC excitation: the earth-field ring holds only DC terms, so no sample
    is inside a pulse (a :class:`PulseGate` over an empty schedule: quiet at every time, and on
    the compiled core the same one-call sample as a pulsed source's)."""

    def __init__(self):
        super().__init__(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), 0, 0)


class _ACMixin:
    measure: ACBlockMeasurement

    def _report(self, ch, solved: bool) -> None:
        i = self.channels.index(ch)
        if self.measure.distorted[i]:
            self._status |= POSE_DISTORTED
        super()._report(ch, solved)

    def _window_charges(self) -> int:
        """AC blocks close no pulse windows."""
        return 0

    def counters(self) -> dict:
        d = super().counters()
        d.update(self.measure.counters())
        d.update(self.act.counters())
        return d


class ACMagneticTracker(_ACMixin, MagneticTracker):
    """A magnetic-only pose per AC block."""

    def __init__(self, cfg, coils, channels, schedule, measure, act, supervisor, tx, solvers, core=_DEFAULT_CORE):
        super().__init__(cfg, coils, channels, schedule, measure, supervisor, tx, solvers, core)
        self.measure, self.act = measure, act


class ACFusionTracker(_ACMixin, BurstFusionTracker):
    """AC blocks fused with the IMU (see module docstring)."""

    def __init__(self, cfg, coils, channels, schedule, measure, act, supervisor, tx, solvers, core=_DEFAULT_CORE):
        cfg = cfg.with_(fusion={"motion_compensation": False})
        super().__init__(cfg, coils, channels, schedule, measure, supervisor, tx, solvers, core)
        self.measure, self.act = measure, act
        #: each sensor's channel, inertial part and earth-field ring (the blocks' DC terms: its compass)
        self._ac_pairs = tuple((ch, ins, measure.earth[ch.node]) for ch, ins in self._pairs)
        self._fuse_mid = {ch.node: -1 for ch in self.channels}
        self.blocks_fused = 0
        self._bind_ac_tick(core)

    def _bind_ac_tick(self, core) -> None:
        """On the compiled core: :meth:`_charges` in one frame (``SolveTick._charges_imu``), the
        solve's start in one call (``MagneticTracker._bind_start`` with this tracker's warm start:
        the filter's pose at the block's ``t_ref``, no range check) and, with a fixed source and
        every sensor's samples through the compiled loop, :meth:`step` as :meth:`_step_compiled`;
        each only where the class runs the reference's methods."""
        ext = core.ext
        if ext is None:
            return
        self._bind_charges(BurstFusionTracker, _ACMixin._window_charges)
        if getattr(self, "_warms", None) is not None and type(self).warm_start is ACFusionTracker.warm_start:
            tref = self.measure.t_ref_view
            self._bind_start(core, tuple((ins.fusion.history.live, tref, ins.fusion.fs) for _, ins in self._pairs),
                             warm_ac=True)
        cls = type(self)
        if not self.source.fixed or getattr(self, "_ft_send", None) is None or cls.step is not ACFusionTracker.step \
                or cls.busy is not MagneticTracker.busy or cls._fuse_step is not BurstFusionTracker._fuse_step \
                or self.burst is not self.measure or getattr(self._charges, "__func__", None) is not SolveTick._charges_imu:
            return
        self._ac_done = np.zeros(2, dtype=np.int64)
        self._ac_donev = memoryview(self._ac_done)
        self._ac_process = ext.FusedTick(tuple(i._one.kernel for _, i, _ in self._ac_pairs),
                                         tuple(i.sc for _, i, _ in self._ac_pairs), self._ac_done).process
        self._ac_complete = self.measure.complete_view
        self.step = self._step_compiled

    def _ring_of(self, ch):
        """The ring a sensor's inertial part is fed from: its earth-field ring (the blocks' DC
        terms, ``_ac_pairs``)."""
        return self.burst.earth[ch.node]

    def _sensor_inertial(self, node: int, cfg, gate) -> SensorInertial:
        """A sensor's inertial part for AC blocks: the compass always quiet (the earth-field ring
        holds only the blocks' DC terms), a compass sample up to a block and three hops old, and
        the motion within a block the rms time ``T_w / sqrt(12)`` of a uniform block."""
        return SensorInertial(node, cfg, _AlwaysQuiet(), self.source,
                              compass_max_age_us=cfg.ac.ac_window_us + 3 * cfg.ac.ac_hop_us,
                              burst_rms_s=cfg.ac.ac_window_us * 1e-6 / math.sqrt(12.0), core=self.core)

    def _plan_snapshots(self, now_us: int) -> None:
        """Each sensor without an update under way: its snapshot at the middle of the next block not begun."""
        m = self.measure
        if not m.started:
            return
        d = m.demods[0]
        for ch, ins in self._pairs:
            fm = self._fuse_mid[ch.node]
            if ins.pending or (fm >= 0 and fm >= m.t_ref_view[0]):      # (t_ref, read in place)
                continue
            k = (now_us + 1000 - d.t0) // d.hop_us + 1
            if k < 0:
                k = 0
            mid = d.block_mid(k)
            self._fuse_mid[ch.node] = mid
            ins.schedule(mid)

    def step(self, now_us: int) -> None:
        self._plan_snapshots(now_us)
        if self.source is not None:
            self.source.process()
        n = 0
        for _ch, ins, earth in self._ac_pairs:
            n -= ins.samples
            ins.process(earth)
            n += ins.samples
        self._imu_last = n
        e0 = self.solver.signal.evals
        fresh = not self.busy()
        charges = self._charges()
        if not fresh:
            MagneticTracker.step(self, now_us, charges)
        if not self.busy():
            self._fuse_step(self.budget - charges - (self.solver.signal.evals - e0), fresh, charges)
        self._send_fused()

    def _step_compiled(self, now_us: int) -> None:
        """:meth:`step` on the compiled core (:meth:`_bind_ac_tick`): the same steps in the same order,
        the fixed source's process (nothing) left out, the sensors' samples in one call
        (``ext.FusedTick.process``: each sensor's ``ImuSample.drain`` and its count; from a sensor
        that handed a sample back on, :meth:`_process_back_ac`), ``busy`` and the charges
        (``SolveTick._charges_imu``) in place, the charges given to ``MagneticTracker.step``,
        ``_fuse_step`` in place (``SolveTick._fuse_pending``)."""
        self._plan_snapshots(now_us)
        r = self._ac_process(_ALL_STEPS)
        n = self._process_back_ac(r >> 2) if r & 1 else r >> 2
        self._imu_last = n
        signal = self.solver.signal
        e0 = signal.evals
        complete = self._ac_complete
        fresh = self._next < 0 and not complete[0]
        charges = 0 if self._waited else 0 + self.imu_sample_evals * n        # (SolveTick._charges_imu)
        if not fresh:
            MagneticTracker.step(self, now_us, charges)
        if self._next < 0 and not complete[0]:
            self._waited = False
            if self._n_pending:
                self._fuse_pending(self.budget - charges - (signal.evals - e0), fresh, charges)
        self._send_fused()

    def _process_back_ac(self, n: int) -> int:
        """The rest of :meth:`step`'s samples after ``FusedTick.process`` ran ``n`` and stopped at a
        sensor whose drain handed one back: each sensor's ``process`` from that one on."""
        k, done = self._ac_donev[0], self._ac_donev[1]
        pairs = self._ac_pairs
        for j in range(k, len(pairs)):
            _, ins, earth = pairs[j]
            n += ins.process(earth, 0, 0, _ALL_STEPS - done if j == k else _ALL_STEPS)
        return n

    def warm_start(self, ch, tp) -> bool:
        ins = self.inertial[ch.node]
        fus = ins.fusion
        if tp.have_pose and fus.initialized and fus.pose_at(self.measure.t_ref, tp.warm_p, tp.warm_R):
            return True
        return MagneticTracker.warm_start(self, ch, tp)

    def _warm_reference(self):
        return ACFusionTracker.warm_start

    def _warm_start_compiled(self, ch, tp) -> bool:
        """:meth:`warm_start` on the compiled core (``WarmStart.warm_ac``, ``core/src/report.c``
        ``ct_report_warm_start_ac``: the filter's pose at the block's ``t_ref``, no range check, or
        the tracked pose; the same operations, the same bits)."""
        w, ins = self._warms[ch.node]
        return w.warm_ac(self.measure.t_ref, tp.have_pose, ins.fusion.initialized)

    def on_solution(self, ch, solved: bool) -> None:
        ins = self.inertial[ch.node]
        if self._fuse_mid[ch.node] == self.measure.t_ref_view[0] and not ins.pending:     # (t_ref, in place)
            self._fuse_mid[ch.node] = -1
            if solved:
                self.blocks_fused += 1
            super().on_solution(ch, solved)

    def counters(self) -> dict:
        d = super().counters()
        d["ac_blocks_fused"] = self.blocks_fused
        return d


assert AC_FAULT_REFUSED == COIL_FAULT_REFUSED


class StatusRouter:
    """The AC pipeline's messages the receiver does not route: ``AC_DRIVE_STATUS`` goes to the
    actuation (:meth:`ACActuation.on_status`) and, as the driver's word on a coil of the running
    plan, to the supervisor (a refusal is the one fatal AC fault; the same bit as
    ``COIL_FAULT_REFUSED``)."""

    def __init__(self, act: ACActuation, supervisor):
        self.act = act
        self.supervisor = supervisor

    def on_message(self, msg, now_us: int) -> None:
        if msg.ID == AC_STATUS_ID:
            act = self.act
            act.on_status(msg, now_us)
            self.supervisor.driver_heard(now_us)
            if msg.coil < act.n and msg.plan_id == act.plan_id:
                self.supervisor.coil_report(msg.coil, msg.faults & AC_FAULT_REFUSED)
