"""The magnetic-only tracker: one 6-DOF pose per sensor from each burst.

When the measurement stage has closed every window of a burst
(:class:`coiltrack.firmware.measure.burst.BurstMeasurement`), each sensor's
signal matrix is solved by the allocation-free
:class:`coiltrack.firmware.pose.solver.PoseSolver` (warm-started from the
tracked pose; Kuipers' closed form and the grid search only to acquire), and
the pose is sent as a ``POSE`` without ``POSE_FUSED``. One sensor's solve at a
time, resumed tick after tick with at most ``track_budget_evals`` coil field
evaluations per tick (``PoseSolver.begin`` / ``step``). Handing over from one sensor
to the next (the finished sensor's POSE, the next one's burst status, warm start and
``begin``: about one LM step's time) is charged ``n`` evaluations like the solver's
closed-form units, against the same budget: a tick whose solve steps leave less than
that puts the next sensor's start off to the following tick, so with sixteen sensors a
tick never carries a full budget of solve steps and a hand-over (or sixteen hand-overs
of unusable bursts) on top; and at most ``[budget] handovers_per_tick`` sensors' solves begin
in one tick (sixteen sensors solved ahead hand over in four ticks, not two at 27 / 3 = 9 a tick:
on the compiled core a hand-over's glue costs far more than its charge of ``n`` evaluations). The first sensor's start, in the tick the burst completes,
is charged the same and the solve steps on in that tick with what is left (before, that
tick did the start alone and the solve's heaviest tick came one tick later, where an
IMU sample, at the same phase of every burst cycle, usually arrives too);
:meth:`MagneticTracker.on_solution` is the hook a fusing tracker extends.

The tick's other work can be charged against the same budget (``[budget] window_evals``
per pulse window the measurement stage closed in the tick, ``imu_sample_evals`` per IMU
sample a fusing tracker processed in it; 0 by default: not charged, and the rule above that
a unit always runs holds). Once anything is charged, a unit or hand-over that does not fit
in what is left waits for the next tick, at most one tick in a row: a tick's field
evaluations and charges together never exceed ``track_budget_evals``, but in the tick after
one that waited (which is charged nothing).
"""
from __future__ import annotations

import functools
import math

import numpy as np

from coiltrack.protocol.schema import POSE_COIL_FAULT, POSE_DEGRADED, POSE_SATURATED, POSE_VALID

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.actuate.schedule import PulseSchedule
from coiltrack.firmware.measure.pulse import PULSE_SATURATED, PULSE_UNUSABLE
from coiltrack.firmware.measure.windows import SensorChannel
from coiltrack.firmware.pose.solver import SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_NONFINITE, SOLVE_RUNNING
from coiltrack.firmware.pose.staged import SolveResult
from coiltrack.firmware.rotation import quat_tuple
from coiltrack.firmware.track.status import COIL_FATAL, input_status
from coiltrack.firmware.track.quality import PoseQuality

SOLVE_FAILED = SOLVE_BAD_INPUT | SOLVE_NO_START | SOLVE_NONFINITE
HO_VETO = 1 << 32          # HandOver.begin's veto bit
HO_REFERENCE = -1          # no HandOver bound (yet): _begin_compiled
#: :meth:`MagneticTracker._ahead_scan`'s answers besides a channel: none ready, every sensor has had
#: its turn, and (the compiled scan only) a time it does not take: ask the reference
AHEAD_NONE, AHEAD_SEEN, AHEAD_ASK = -1, -2, -3


def in_range3(x: float, y: float, z: float, range_m: float) -> bool:
    """Whether the point (x, y, z), m, lies within ``range_m`` of the source (False for NaN or inf)."""
    return math.sqrt(float(x) * x + float(y) * y + float(z) * z) <= range_m


def in_range(p, range_m: float) -> bool:
    """:func:`in_range3` of the point ``p`` (3,)."""
    return in_range3(p[0], p[1], p[2], range_m)


class TrackedPose:
    """The last magnetic solution of one sensor (position m, rotation
    sensor-to-source)."""

    def __init__(self, hemisphere):
        self.position = np.zeros(3)
        self.rotation = np.eye(3)
        self.have_pose = False
        self.hemisphere = np.array(hemisphere, dtype=float)
        self.warm_p = np.zeros(3)          # the start of the next solve
        self.warm_R = np.eye(3)


#: ``_Ahead``'s burst when it has none (a time no burst starts at)
NO_BURST = -(1 << 63)


class _Ahead:
    """One sensor's burst solved ahead (``[budget] solve_ahead``): the inputs its solve began
    with (signal matrix, sigmas, currents, hemisphere and, begun warm, the warm start, copied;
    ``warm``: whether it began from a warm start or acquired, from the sensor's hemisphere) for
    the burst that started at ``burst``, and, once finished (``done``), its results. ``burst`` and
    ``done`` live in ``st`` (int64 (2,): the burst or :data:`NO_BURST`, done 0/1; a row of the
    tracker's array, so the compiled scan over the sensors reads and writes them in place),
    ``warm`` in ``wst`` (int64 (1,), 0/1, read and written by the compiled begin and comparison)."""

    def __init__(self, n: int, st=None):
        self.S = np.zeros((3, n))
        self.sigma = np.zeros((3, n))
        self.currents = np.zeros(n)
        self.hemisphere = np.zeros(3)
        self.warm_p = np.zeros(3)
        self.warm_R = np.eye(3)
        self.amp = np.zeros(3)
        self.var = np.zeros(3)
        self.result = SolveResult()
        self.st = np.array([NO_BURST, 0], dtype=np.int64) if st is None else st
        self.wst = np.zeros(1, dtype=np.int64)
        self._wv = memoryview(self.wst)
        self._stv = memoryview(self.st)
        self.sigv = memoryview(self.sigma)
        self.curv = memoryview(self.currents)
        self._views = tuple(memoryview(a) for a in (self.S, self.sigma, self.currents, self.hemisphere,
                                                     self.warm_p, self.warm_R))

    def _get_burst(self):
        b = self._stv[0]
        return None if b == NO_BURST else b

    #: the burst whose solve this is (None: none)
    burst = property(_get_burst)
    #: the solve has finished (its results in ``result``)
    done = property(lambda self: self._stv[1] != 0)
    #: the solve began from a warm start (else it acquired, from the hemisphere)
    warm = property(lambda self: self._wv[0] != 0)

    def began(self, warm: bool) -> None:
        """The solve begins from a warm start (``warm``) or acquires."""
        self._wv[0] = 1 if warm else 0

    def take(self, burst: int) -> None:
        """This sensor's solve ahead is now that of the burst that started at ``burst``, not done."""
        self._stv[0], self._stv[1] = burst, 0

    def finish(self) -> None:
        """The solve ahead has finished (its results in ``result``)."""
        self._stv[1] = 1

    def release(self) -> None:
        """No burst is solved ahead for this sensor any more (its result was taken or refused)."""
        self._stv[0] = NO_BURST

    def same(self, views) -> bool:
        """Whether the burst's inputs ``views`` (memoryviews of S, sigma, currents, hemisphere and,
        for a warm solve, warm_p, warm_R) equal those this solve began with, element by element."""
        for a, b in zip(self._views, views):
            if a != b:
                return False
        return True


def _closed_before(done, j: int) -> bool:
    """Every window of ``done`` (a channel's closed flags) before coil ``j`` is closed."""
    for c in range(j):
        if not done[c]:
            return False
    return True


class _CompiledReport:
    """:class:`MagneticTracker`'s report on the compiled core (``core/src/finish.c``,
    ``core/src/report.c``): bound once at construction, replacing the methods on the instance, so
    no call tests the choice. The Python methods of :class:`MagneticTracker` stay the reference;
    each method here does the same operations in the same order (the same results to the bit) or
    hands inputs of another kind to them."""

    def _bind_report(self, core) -> None:
        """:meth:`_take_solution` and :meth:`_quat` on the compiled core (``core/src/finish.c``
        ``ct_report_take``, ``fusimu.c`` ``ct_quat_from_elements``: the same operations, the same
        bits) through a ``ReportPose`` bound to the solver's results; replaced on this instance."""
        ext = core.ext
        sv = self.solver
        arrays = [getattr(sv, k, None) for k in ("position", "rotation")]
        if ext is None or not all(isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous
                                  and a.size == m for a, m in zip(arrays, (3, 9))):
            return                       # results of another kind: the Python's own copies
        self._q = np.zeros(4)
        self._qv = memoryview(self._q)
        self._rp = ext.ReportPose(sv.position, sv.rotation, self._q)
        self._take_solution = self._take_solution_compiled
        self._quat = self._quat_compiled

    def _bind_begin(self, core) -> None:
        """:meth:`_begin`'s inputs and :meth:`_prepare_currents` on the compiled core: one
        ``BurstInputs`` (``core/src/begin.c``: ``ct_begin_inputs``, ``ct_prepare_currents``, the same
        operations) bound to the channels' window flags, the schedule's faults and measured currents,
        the nominal and the tracker's currents; replaced on this instance. Left to the Python where a
        class overrides them or an array is of another kind."""
        ext = core.ext
        if ext is None or type(self)._begin is not MagneticTracker._begin \
                or type(self)._prepare_currents is not MagneticTracker._prepare_currents \
                or any(type(ch).burst_flags is not SensorChannel.burst_flags for ch in self.channels) \
                or type(self.schedule).any_faults is not PulseSchedule.any_faults:
            return
        try:
            self._bk = ext.BurstInputs(tuple(ch.flags for ch in self.channels), self.schedule.faults,
                                       self.schedule.measured, self.nominal, self.currents,
                                       (PULSE_SATURATED, PULSE_UNUSABLE, COIL_FATAL, POSE_SATURATED, POSE_DEGRADED,
                                        POSE_COIL_FAULT))
        except (AttributeError, TypeError, ValueError):
            return
        self._bk_status = self._bk.status
        self._begin = self._begin_compiled
        self._prepare_currents = self._prepare_currents_compiled

    def _begin_compiled(self, ch) -> None:
        """:meth:`_begin` with the burst's flags, the faults and their bits in one compiled call."""
        r = self._bk_status(self._next)
        sup = self.supervisor
        self._status = (r & 255) | sup.pose_status(ch.node, r >> 9)
        if r & 256 or sup.veto:
            self._report(ch, False)
            return
        self._start_solve(ch)

    def _bind_start(self, core, filters, warm_ac: bool = False) -> None:
        """:meth:`_start_solve` in one compiled call where no solve ahead is to be taken over
        (``SolveStart``, ``core/src/begin.c`` ``ct_solve_start``: ``SensorChannel.fill_sigma``,
        ``BurstFusionTracker.warm_start`` and ``PoseSolver.begin``, the same operations in the same
        order), bound to each channel's variances, sigmas, signals and tracked pose and to
        ``filters``: per channel its fusion filter's live history, the sensor's ``tr`` (the instant
        of the warm start's pose) and the filter's ``fs`` with its initialised flag's index and
        length; ``warm_ac``: ``ACFusionTracker.warm_start``'s instead (no range check). Left to the
        Python where a part is of another kind (a distortion map, a solver or channel not on the
        compiled core)."""
        from coiltrack.firmware.estimate.magnetic_inertial import FS_INIT, FS_N
        ext, sv = core.ext, self.solver
        chs = self.channels
        if ext is None or getattr(sv, "_sv", None) is None or sv.signal.distortion is not None \
                or type(self)._start_solve is not MagneticTracker._start_solve \
                or getattr(sv.begin, "__func__", None) is not type(sv)._begin_compiled \
                or any(type(ch).fill_sigma is not SensorChannel.fill_sigma
                       or getattr(ch.sigma_from, "__func__", None) is not SensorChannel._sigma_from_compiled
                       or ch._sigma_floor2 != chs[0]._sigma_floor2 for ch in chs):
            return
        try:
            rows = []
            for ch, (hist, tr, fs) in zip(chs, filters):
                tp = self.poses[ch.node]
                rows.append((ch.var, ch.sigma, ch.S, hist.t, hist.d, hist.hc, tr, fs, tp.position, tp.rotation,
                             tp.warm_p, tp.warm_R, tp.hemisphere))
            k = ext.SolveStart(sv._sv, sv.n, chs[0]._sigma_floor2, self.range_m, FS_INIT, FS_N, self.currents,
                               tuple(rows), warm_ac)
        except (AttributeError, TypeError, ValueError):
            return
        self._ss, self._ss_start = k, k.start
        self._as_inputs = None               # (bound with the solve ahead's begin)
        self._ss_poses = tuple(self.poses[ch.node] for ch in chs)
        self._ahead_stv = memoryview(self._ahead_st)
        self._start_solve = self._start_solve_compiled
        self._bind_ahead_start(ext)

    def _start_solve_compiled(self, ch) -> None:
        """:meth:`_start_solve` in one compiled call (:meth:`_bind_start`); where a solve ahead may
        be taken over (``_use_ahead`` would look at the inputs), the reference."""
        k = self._next
        if self.ahead:
            bs, st = self.schedule.burst_start, self._ahead_stv      # (_Ahead.burst, .done of row k)
            if st[k, 0] == (NO_BURST if bs is None else bs) and (st[k, 1] or self._ahead_k == k):
                self._take_ahead(ch, k)
                return
        self._start_fresh(ch, k)

    def _start_fresh(self, ch, k: int) -> None:
        """:meth:`_start_solve_compiled` where no solve ahead is to be taken over (a model with a
        distortion map: the reference)."""
        sv = self.solver
        if sv.signal.distortion is not None:
            MagneticTracker._start_solve(self, ch)
            return
        self._ahead_k = -1                   # (what _use_ahead and _start_solve leave)
        r = self._ss_start(k, self._ss_poses[k].have_pose)
        if not sv.begun(r & 255, r > 255) & SOLVE_RUNNING:
            self._report(ch, False)

    def _bind_ahead_start(self, ext) -> None:
        """:meth:`_ahead_start` in one compiled call (``AheadStart``, ``core/src/begin.c``
        ``ct_ahead_start``: ``BurstFusionTracker.warm_start``, then :meth:`_begin_ahead`'s extraction
        (``PulseExtractor.extract`` on the channel's ``PulseWindow``), copies, ``sigma_from``,
        :meth:`_prepare_currents`, the record of the start's kind and ``PoseSolver.begin``, warm
        or acquiring, the same operations in the same order),
        bound with :meth:`_start_solve_compiled`'s ``SolveStart``; left to the Python where a part is
        of another kind."""
        from coiltrack.firmware.measure.pulse import PulseExtractor
        chs = self.channels
        if not self.ahead or type(self)._ahead_start is not MagneticTracker._ahead_start \
                or type(self)._begin_ahead is not MagneticTracker._begin_ahead \
                or getattr(self._prepare_currents, "__func__", None) is not _CompiledReport._prepare_currents_compiled \
                or any(getattr(ch.extractor.extract, "__func__", None) is not PulseExtractor._extract_compiled
                       for ch in chs):
            return
        try:
            rows = tuple((ch.extractor._ck, ch.extractor._ring.hc, ah.S, ah.sigma, ah.currents, ah.hemisphere,
                          ah.warm_p, ah.warm_R, ah.amp, ah.var, ah.wst) for ch, ah in zip(chs, self._ahead))
            k = ext.AheadStart(self._ss, self.schedule.measured, self.nominal, rows)
        except (AttributeError, TypeError, ValueError):
            return
        self._as_start, self._as_inputs = k.start, k.inputs
        self._as_prep = self._prepare_currents          # what ct_ahead_start repeats (see below)
        self._ahead_start = self._ahead_start_compiled

    def _take_ahead(self, ch, k: int) -> None:
        """:meth:`_start_solve` where channel ``k``'s solve ahead is of this burst and finished or
        running (:meth:`_use_ahead`'s first test, passed in the caller): on the compiled core the
        sigma, the warm start and the comparison of the start's kind and of :meth:`_Ahead.same` in
        one call (``AheadStart.inputs``, ``ct_ahead_inputs``), then the rest of :meth:`_use_ahead`
        on its answer (the same operations in the same order); else (a distortion map, no
        ``AheadStart`` bound) the reference."""
        sv = self.solver
        if self._as_inputs is None or sv.signal.distortion is not None:
            MagneticTracker._start_solve(self, ch)
            return
        tp = self._ss_poses[k]
        r = self._as_inputs(k, tp.have_pose)
        self._ahead[k].release()
        self._ahead_taken(ch, tp, k, r >= 2, r & 1 != 0)

    def _ahead_taken(self, ch, tp: TrackedPose, k: int, same: bool, warm: bool) -> None:
        """The end of :meth:`_take_ahead` once channel ``k``'s solve ahead is released
        (:meth:`_ahead_result`), its result reported if it was loaded."""
        solved = self._ahead_result(ch, tp, k, same, warm)
        if solved is not None:
            self._report(ch, solved)

    def _ahead_result(self, ch, tp: TrackedPose, k: int, same: bool, warm: bool):
        """Channel ``k``'s solve ahead released: solved again from its warm start (``warm``) or
        acquiring if its start or inputs were not the same (``same`` False), else its result
        loaded (or, still running, left to finish as the burst's own solve). Whether the loaded
        result is a solution (to be reported by the caller); None when none was loaded."""
        running = self._ahead_k
        self._ahead_k = -1
        if not same:
            self.ahead_missed += 1
            self._solve_from(ch, tp, warm)
            return None
        self.ahead_used += 1
        if running == k:
            return None
        res = self._ahead[k].result
        self.solver.load(res)
        if res.solve_evals > self.solve_evals_max:
            self.solve_evals_max = res.solve_evals
        return not (res.status & SOLVE_FAILED)

    def _ahead_start_compiled(self, k: int, start: int, end: int) -> bool:
        """:meth:`_ahead_start` in one compiled call (:meth:`_bind_ahead_start`); a model with a
        distortion map, a time the extraction does not take, or a :meth:`_prepare_currents` replaced
        since the binding (the kernel repeats the compiled one), the reference."""
        sv = self.solver
        r = AHEAD_ASK if sv.signal.distortion is not None or self._prepare_currents is not self._as_prep \
            else self._as_start(k, self._ss_poses[k].have_pose, start, end)
        if r < 0:
            return r == AHEAD_ASK and MagneticTracker._ahead_start(self, k, start, end)
        if not sv.begun(r & 255, r > 255) & SOLVE_RUNNING:
            return False
        self._ahead_k = k
        self.ahead_solves += 1
        return True

    def _prepare_currents_compiled(self, cur) -> None:
        if cur is self._curv:
            self._bk.currents()
        else:
            MagneticTracker._prepare_currents(self, cur)

    def _take_solution_compiled(self, tp: TrackedPose) -> bool:
        r = self._rp.take(tp.position, tp.rotation, self.range_m)
        return MagneticTracker._take_solution(self, tp) if r is None else r

    def _quat_compiled(self, R):
        return self._qv if self._rp.quat(R) else quat_tuple(R)

    def _report_pose_compiled(self, ch, tp: TrackedPose, t_pose: int) -> bool:
        """:meth:`_report_pose` with its numbers in one compiled call per channel (``ReportChain``,
        ``core/src/report.c`` ``ct_report_solved``: the range check and copies, the grading,
        the quaternion and the reported covariance, the same operations in the same order)."""
        chain, cov, fus, send, init = self._chains[ch.node]
        q = self.quality.grade_report(chain, ch.node, t_pose, self.solver.cost, self.range_m,
                                      fus is not None and (fus.initialized if init is None else init[0] != 0))
        if q < 0:
            return False
        tp.have_pose = True
        st = self._status | POSE_VALID
        if not self.tx.pose_built(send, ch.node, t_pose, st, q):       # the frame from the chain's buffers
            self.tx.pose_cov6(ch.node, t_pose, tp.position, self._qv, cov, st, q)
        return True

    def _bind_report_chain(self, core) -> None:
        """:meth:`_report_pose` on the compiled core: one ``ReportChain`` per channel bound to the
        solver's results, the tracked pose, the channel's signals, the schedule and the quality's
        row (``PoseQuality.report_chain``); replaced on this instance. Left to the Python where any
        part is of another kind: no compiled grading, results or inputs of another layout, or a
        :meth:`reported_covariance` whose arithmetic the chain does not repeat (a class states
        the one it does in ``_chain_covariance``)."""
        ext = core.ext
        sv = self.solver
        if ext is None or not hasattr(self, "_rp") or not hasattr(sv, "cost") \
                or type(self).reported_covariance is not type(self)._chain_covariance:
            return
        chains = {}
        for ch in self.channels:
            tp = self.poses[ch.node]
            try:
                m = self._chain_motion(ch)
                chain = self.quality.report_chain(ext, ch.node, sv.position, sv.rotation, sv.covariance, tp.position,
                                                  tp.rotation, ch.S, ch.sigma, self.schedule.start,
                                                  self.schedule.end, self._q, None if m is None else m[:4])
            except (AttributeError, TypeError, ValueError):
                chain = None
            if chain is None:
                return
            chains[ch.node] = (chain, sv.covariance, None, chain.send, None) if m is None else \
                (chain, m[2], m[4], chain.send, _initialized_flag(m[4]))
        self._chains = chains
        self._report_pose = self._report_pose_compiled


def _initialized_flag(fus):
    """A view of the fusion filter ``fus``'s initialised flag (its ``fs[FS_INIT]``, what its
    ``initialized`` reads), for :meth:`_CompiledReport._report_pose_compiled`; None where the
    filter is of another kind (its ``initialized`` is read)."""
    from coiltrack.firmware.estimate.magnetic_inertial import FS_INIT, FusionFilter
    fs = getattr(fus, "fs", None)
    if type(fus).initialized is not FusionFilter.initialized or not isinstance(fs, np.ndarray) \
            or fs.dtype != np.int64 or fus._fsv.obj is not fs:
        return None
    return memoryview(fs)[FS_INIT:FS_INIT + 1]


def _ho_reference(k: int, have_pose: bool, burst: int, running: int) -> int:
    """:meth:`MagneticTracker._begin_handover`'s kernel where none could be bound."""
    return HO_REFERENCE


class _HandOver:
    """:class:`MagneticTracker`'s hand-over on the compiled core: a burst's begin with the take-over
    of its solve ahead in one compiled call (:meth:`_begin_handover`; :meth:`_bind_handover`, its
    kernel bound once the firmware is composed: :meth:`bind_composed`). The Python methods it stands for stay the
    reference: :meth:`_begin_compiled`, :meth:`_start_solve_compiled` and :meth:`_take_ahead`."""

    def _bind_handover(self, core) -> None:
        """:meth:`_begin` replaced on this instance by :meth:`_begin_handover` where the steps it
        stands for are the compiled ones (:meth:`_bind_begin`, :meth:`_bind_start`,
        :meth:`_bind_ahead_start`) and no class overrides them; else left as it is. Its kernel is
        bound once the firmware is composed (:meth:`bind_composed`); till then, or where it cannot
        be, :meth:`_begin_handover` runs :meth:`_begin_compiled`."""
        mt = MagneticTracker
        if not self.ahead or core.ext is None or not hasattr(self.supervisor, "pose_kernel") \
                or type(self)._begin is not mt._begin or type(self)._take_ahead is not mt._take_ahead \
                or type(self)._solve_from is not mt._solve_from \
                or getattr(self._begin, "__func__", None) is not _CompiledReport._begin_compiled \
                or getattr(self._start_solve, "__func__", None) is not _CompiledReport._start_solve_compiled \
                or getattr(self, "_as_inputs", None) is None:
            return
        self._ho_ext = core.ext
        self._ho_begin = _ho_reference
        self._begin = self._begin_handover
        self._bind_report_loop()

    def bind_composed(self) -> None:
        """Called once the firmware's stages are all built (``loop.Firmware``): the hand-over's kernel
        (:meth:`_bind_handover_now`), which reads the supervisor's kernel the receive stage binds."""
        if getattr(self, "_ho_ext", None) is not None:
            self._bind_handover_now()

    def _bind_handover_now(self) -> bool:
        """``HandOver.begin`` bound where the supervisor's pose status is compiled (its
        ``pose_kernel``: the receive stage binds it after the tracker is built): one ``HandOver``
        (``core/py_begin.c``; ``core/src/begin.c`` ``ct_handover_status``, ``ct_handover_ahead``, then
        ``ct_ahead_inputs``) bound to the tracker's ``AheadStart`` and ``BurstInputs``, the
        supervisor's ``SupMag``, the channels' nodes and ``_ahead_st``; whether it was."""
        sk = self.supervisor.pose_kernel()
        if sk is None:
            return False
        try:
            ho = self._ho_ext.HandOver(self._as_inputs.__self__, self._bk, sk, tuple(c.node for c in self.channels),
                                       self._ahead_st)
        except (AttributeError, TypeError, ValueError):
            return False
        self._ho_begin = ho.begin
        return True

    def _begin_handover(self, ch) -> None:
        """:meth:`_begin_compiled` with :meth:`_start_solve_compiled`'s test for a solve ahead to take
        over and :meth:`_take_ahead`'s compiled part in one call (:meth:`_hand_over`), then the
        report it leaves to its caller."""
        solved = self._hand_over(ch)
        if solved is not None:
            self._report(ch, solved)

    def _hand_over(self, ch):
        """:meth:`_begin_handover` but its report: ``HandOver.begin`` (the burst's status, the
        supervisor's pose status, the test for a solve ahead to take over, ``AheadStart.inputs``
        and ``_Ahead.release``, the same operations in the same order), then the rest of the steps
        it stands for on its answer; a model with a distortion map, :meth:`_begin_compiled`.
        Whether the burst of ``ch`` is to be reported now as solved (a solve ahead's result
        loaded) or not (unusable or vetoed); None when nothing is to be reported yet."""
        sv = self.solver
        if sv.signal.distortion is not None:
            self._begin_compiled(ch)
            return None
        k = self._next
        tp = self._ss_poses[k]
        bs = self.schedule.burst_start
        r = self._ho_begin(k, tp.have_pose, NO_BURST if bs is None else bs, self._ahead_k)
        if r < 0:
            self._begin_compiled(ch)
            return None
        sup = self.supervisor
        self._status = r & 0xFFFFFFFF
        if r & HO_VETO or sup.veto:
            sup.vetoed((r >> 32) & 1)
        code = r >> 34
        if code == 0:
            return False
        if code == 1:
            self._start_fresh(ch, k)
            return None
        return self._ahead_result(ch, tp, k, code == 4, code == 3)

    def _bind_report_loop(self) -> None:
        """:meth:`_report` replaced on this instance by :meth:`_report_loop` where the next sensor's
        begin is :meth:`_begin_handover` and no class overrides :meth:`_report`; the hook
        :meth:`on_solution` called only where a class overrides it (``_on_solution``)."""
        mt = MagneticTracker
        if type(self)._report is not mt._report or getattr(self._begin, "__func__", None) is not _HandOver._begin_handover \
                or type(self)._hand_over is not _HandOver._hand_over:
            return
        self._on_solution = None if type(self).on_solution is mt.on_solution else self.on_solution
        self._report = self._loop_report = self._report_loop
        self._loop_begin = self._begin

    def _report_loop(self, ch, solved: bool) -> None:
        """:meth:`MagneticTracker._report` with the next sensors' begins (:meth:`_begin_handover`)
        in a loop instead of a recursion: each sensor's POSE, the hook, the move to the next
        sensor and, with room left, its begin (:meth:`_hand_over`), whose report, where it leaves
        one (a solve ahead's result taken over, an unusable burst), is the loop's next turn; the
        same operations in the same order. Where :meth:`_begin` or :meth:`_report` was replaced on
        the instance since the binding (a recorder wraps it), the next begin goes through them."""
        poses, chans, tx = self.poses, self.channels, self.tx
        hook = self.__dict__.get("on_solution", self._on_solution)       # (one set on the instance: it)
        while True:
            tp = poses[ch.node]
            t_pose = (self._startv[0] + self._endv[-1]) // 2      # the middle of the burst
            if solved and not self._report_pose(ch, tp, t_pose):
                solved = self._out_of_range(tp)
            if not solved:
                tx.pose_unknown(ch.node, t_pose, tp.position, self._quat(tp.rotation), self._status)
            if hook is not None:
                hook(ch, solved)
            if not self._next_sensor():
                return
            ch = chans[self._next]
            if self._begin is not self._loop_begin or self._report is not self._loop_report:
                self._begin(ch)              # (replaced since the binding: through them, as the reference)
                return
            solved = self._hand_over(ch)
            if solved is None:
                return


class _ScanAhead:
    """:class:`MagneticTracker`'s scan over the sensors for a burst to solve ahead
    (:meth:`MagneticTracker._solve_ahead`), with its compiled form bound at construction."""

    def _ahead_scan(self, burst: int, j: int, start: int, end: int) -> int:
        """The sensors' turns to be solved ahead for ``burst`` (its last window, coil ``j``, is
        ``[start, end]``), in their order: a sensor whose final solve would not start from it
        (:meth:`_ahead_wanted`) has had its turn; one not ready (a window before the last open,
        the last closed already, or its samples not expected in: ``expect_complete``) is marked
        with its channel's changes (:meth:`_idle_for`) and asked again only once they move. The
        first one ready is given its turn (``burst`` set, not done) and returned; else
        :data:`AHEAD_SEEN` when every sensor has had its turn, :data:`AHEAD_NONE` otherwise. On the
        compiled core one call (``ext.AheadScan``, ``core/src/ahead.c`` ``ct_ahead_scan``: the same
        tests in the same order on the same arrays), bound at construction (:meth:`_bind_scan`)."""
        idle = self._ahead_unchanged
        seen = True
        for k, ch in enumerate(self.channels):
            ah = self._ahead[k]
            if ah.burst == burst:
                continue
            if not self._ahead_wanted(ch):
                ah.take(burst)
                continue
            seen = False
            c = ch.changes
            if idle[k] == c:
                continue                 # not ready when last asked, and nothing it reads changed since
            if ch.done[j] or not _closed_before(ch.done, j) or not ch.extractor.expect_complete(start, end):
                idle[k] = c
                continue
            ah.take(burst)
            return k
        return AHEAD_SEEN if seen else AHEAD_NONE

    def _ahead_scan_compiled(self, burst: int, j: int, start: int, end: int) -> int:
        """:meth:`_ahead_scan` in one call; a time the kernel does not take (not an int64 well
        inside its range) goes to the reference."""
        k = self._scan_k(burst, j, start, end)
        return _ScanAhead._ahead_scan(self, burst, j, start, end) if k == AHEAD_ASK else k

    def _bind_scan(self, core) -> None:
        """:meth:`_ahead_scan` on the compiled core (``ext.AheadScan`` bound to every channel's
        closed flags, counters and sample ring, the turns' array and the marks): where every
        channel's extractor is a plain ``PulseExtractor`` over a ``SampleRing`` and the sensors'
        wish (:meth:`_ahead_wanted_flags`) is an array entry; replaced on this instance."""
        from coiltrack.firmware.measure.pulse import PulseExtractor, SampleRing
        ext = core.ext
        if ext is None or not self.ahead or not self.channels:
            return
        wanted = self._ahead_wanted_flags()
        chs = self.channels
        if wanted is None or any(type(ch.extractor).expect_complete is not PulseExtractor.expect_complete
                                 or not isinstance(ch.extractor._ring, SampleRing) for ch in chs):
            return
        extra = np.array([ch.extractor._fall_us + ch.extractor._baseline_us for ch in chs], dtype=np.int64)
        self._scan_extra = extra
        self._scan_k = ext.AheadScan(tuple(ch.done for ch in chs), tuple(ch.cnt for ch in chs),
                                     tuple(ch.extractor._ring.t for ch in chs),
                                     tuple(ch.extractor._ring.hc for ch in chs), extra,
                                     tuple(w[0] for w in wanted), tuple(w[1] for w in wanted),
                                     self._ahead_st, self._ahead_idle).scan
        self._ahead_scan = self._ahead_scan_compiled

    def _ahead_wanted_flags(self):
        """Hook: :meth:`_ahead_wanted` as arrays, for the compiled scan: per channel ``(a, i)``,
        the sensor wanted when ``a[i] == 0`` (int64 ``a``); None where the hook reads anything
        else (the scan stays the Python's)."""
        if type(self)._ahead_wanted is not MagneticTracker._ahead_wanted:
            return None
        zero = np.zeros(1, dtype=np.int64)
        return tuple((zero, 0) for _ in self.channels)

    def _idle_for(self, start: int, end: int):
        """The channels' :attr:`_ahead_unchanged` marks for the last window ``[start, end]``, forgotten when
        the window is another. A channel's readiness to be solved ahead reads only its windows'
        closed flags and its samples (``PulseExtractor.expect_complete``), each change of which
        counts in its ``changes``: so the idle ticks ask only the channels that changed, and a
        tick's work scales with the samples that came in, not with the sensors."""
        if self._ahead_unchanged_window != (start, end):
            self._ahead_unchanged_window = (start, end)
            idle = self._ahead_unchanged
            for k in range(len(idle)):
                idle[k] = -1
        return self._ahead_unchanged


class MagneticTracker(_CompiledReport, _ScanAhead, _HandOver):
    """Solves each burst for every sensor and reports the magnetic poses (a
    :class:`coiltrack.firmware.track.BurstTracker`).

    ``burst``: the measurement stage (a :class:`coiltrack.firmware.measure.Measurement`);
    ``solvers``: ``gate_probability -> Solver`` (``compose.solver_factory``: the configured
    pose solver with the room's distortion map); ``core``: the numeric core
    (``coiltrack.firmware.core.Core``) of the tracker's own filters, chosen at composition."""

    def __init__(self, cfg, coils, channels, schedule, burst, supervisor, tx, solvers, core=_DEFAULT_CORE):
        self.cfg = cfg
        self.channels = tuple(channels)
        self.schedule = schedule
        self.burst = burst
        self.supervisor = supervisor
        self.tx = tx
        self.solver = solvers(cfg.budget.solve_gate_probability)
        self.nominal = np.array([c.current for c in cfg.source.coils])
        self.currents = np.zeros(len(coils))
        self._curv = memoryview(self.currents)
        self._nomv = memoryview(self.nominal)
        self._measv = memoryview(schedule.measured)
        self._startv = memoryview(schedule.start)      # int64: read as Python ints
        self._endv = memoryview(schedule.end)
        self.poses = {ch.node: TrackedPose(cfg.source.hemisphere) for ch in self.channels}
        self._next = -1                  # index of the channel being solved; -1: idle
        self._handover = False           # the start of channel _next waits for the next tick
        self._units = 0                  # work charged in this tick (field evaluations)
        self._charged = 0                # of which the tick's other work (window_evals, imu_sample_evals)
        self._waited = False             # the last tick's charges left the solve no room
        self.window_evals = cfg.budget.window_evals
        self._status = 0                 # POSE_* bits of that channel's burst
        self.budget = cfg.budget.track_budget_evals
        self.handovers_max = cfg.budget.handovers_per_tick
        self._handovers = 0              # sensors' solves begun in this tick
        self._burst_ticks = 0            # ticks since the burst's last window closed
        self.range_m = cfg.pose.working_range_m
        self.out_of_range = 0            # solutions beyond the working volume, not sent as poses
        self.solve_ticks_max = 0         # the most ticks a burst's solves took after its windows closed
        self.solve_evals_max = 0         # the most field evaluations of one solve
        self.cycles = 0
        self.quality = PoseQuality(cfg, len(coils), self.channels, coils, core)    # POSE.quality (track.quality)
        self._bind_report(core)
        self._bind_begin(core)
        # solving ahead (see _solve_ahead): one sensor at a time, in ticks with no burst to solve
        self.ahead = cfg.budget.solve_ahead and cfg.ac.excitation == "pulsed" and self.solver.memoryless
        self._ahead_st = np.zeros((len(self.channels), 2), dtype=np.int64)    # per channel: burst, done
        self._ahead_st[:, 0] = NO_BURST
        self._ahead = tuple(_Ahead(len(coils), self._ahead_st[k]) for k in range(len(self.channels)))
        # per channel, the inputs of its burst's solve, acquiring (cold) and from a warm start
        self._inputs = tuple((tuple(memoryview(a) for a in (ch.S, ch.sigma, self.currents, tp.hemisphere)),
                              tuple(memoryview(a) for a in (ch.S, ch.sigma, self.currents, tp.position,
                                                            tp.warm_p, tp.warm_R)))
                             for ch, tp in ((ch, self.poses[ch.node]) for ch in self.channels))
        # per channel, cold and warm, whether its burst's inputs are those its solve ahead began with
        # (_Ahead.same; on the compiled core one ``AheadSame`` call, ``core/src/report.c`` ``ct_report_same``)
        self._same = tuple(tuple(functools.partial(ah.same, inp) for inp in io)
                           for ah, io in zip(self._ahead, self._inputs))
        if core.ext is not None:
            self._same = tuple(tuple(core.ext.AheadSame(ah._views[:len(inp)], inp).same for inp in io)
                               for ah, io in zip(self._ahead, self._inputs))
        self._ahead_k = -1               # the channel whose burst the solver is solving ahead; -1: none
        self._ahead_seen = None          # the burst every channel has had its turn to be solved ahead for
        # per channel, the SensorChannel.changes at which its burst was last found not ready to be
        # solved ahead (for the window _ahead_unchanged_window): nothing that test reads has changed while it holds
        self._ahead_idle = np.full(len(self.channels), -1, dtype=np.int64)
        self._ahead_unchanged = memoryview(self._ahead_idle)
        self._ahead_unchanged_window = (None, None)
        self.ahead_solves = 0            # bursts solved ahead
        self.ahead_used = 0              # of which the burst's solve (the same inputs)
        self.ahead_missed = 0            # of which not (a sample or a current came in late)
        self._bind_report_chain(core)
        self._bind_scan(core)
        self._bind_handover(core)

    # ------------------------------------------------------------ inputs
    def on_imu(self, msg, now_us: int) -> None:
        """IMU samples are not used by the magnetic-only tracker."""

    def on_mag(self, msg, lsb: float) -> None:
        """Samples of nodes that are not tracked sensors are not used."""

    def on_coil_status(self, msg) -> None:
        """The schedule keeps the driver's reports; nothing more to do."""

    def on_burst(self, t_ref: int) -> None:
        """A burst was commanded; its pose will refer to ``t_ref``."""

    # ------------------------------------------------------------ tick
    def step(self, now_us: int, charges: int | None = None) -> None:
        """Within ``track_budget_evals`` field evaluations: the next piece of
        the current sensor's solve, or the start of the next sensor's (``charges``: the tick's
        :meth:`_charges` where the caller has them, a fusing tracker's tick)."""
        self._units = self._charged = self._charges() if charges is None else charges
        self._waited = False
        self._handovers = 0
        if self._next < 0:
            if not self.burst.complete:
                if self.ahead:
                    self._solve_ahead()
                return
            self._burst_ticks = 0
            self._next = 0
            self._prepare_currents(self._curv)
            self._handover = True        # the first sensor's start: charged as a hand-over
        else:
            self._burst_ticks += 1
        if self._handover:               # (or the hand-over the last tick's budget had no room for)
            if self._charged and self._units + self.solver.n > self.budget:
                self._waited = True
                return                   # no room beside the tick's other work
            self._handover = False
            self._units += self.solver.n
            self._handovers += 1
            self._begin(self.channels[self._next])
            if self._next < 0 or self._handover or self._units >= self.budget:
                return
        st = self._step_solver()
        if st & SOLVE_RUNNING:
            return
        if self.solver.solve_evals > self.solve_evals_max:
            self.solve_evals_max = self.solver.solve_evals
        self._report(self.channels[self._next], not (st & SOLVE_FAILED))

    def _charges(self) -> int:
        """This tick's charges: none in a tick after one whose charges left the solve no room, so
        the solve waits at most one tick in a row (with an IMU sample in every tick it would
        never run; that tick's work may then exceed the budget by one unit)."""
        return 0 if self._waited else self._tick_charges()

    def _tick_charges(self) -> int:
        """The tick's other work, in field evaluations."""
        return self._window_charges()

    def _window_charges(self) -> int:
        """``window_evals`` per pulse window the measurement stage closed in this tick."""
        return self.window_evals * self.burst.closed_last

    def _step_solver(self) -> int:
        """The solve's steps with what is left of the tick's budget; its status."""
        left = self.budget - self._units
        if self._charged and self.solver.next_unit is not None and self.solver.next_cost > left:
            self._waited = True
            return SOLVE_RUNNING         # the next unit does not fit beside the tick's other work
        st = self.solver.step(left)
        self._units += self.solver.units_last
        return st

    # ------------------------------------------------------------ solving ahead
    def _solve_ahead(self) -> None:
        """Within the budget, in a tick with no burst to solve: the open burst of a sensor whose
        windows are closed but the last coil's, and whose last window has every sample it reads
        in (the next sample is expected after it: ``PulseExtractor.expect_complete``), solved
        on the inputs its own solve will have, from the start that solve will take
        (:meth:`warm_start`). At 120 Hz that is one sample interval (8.3 ms) before the window
        is ready and the burst completes, time for the whole warm solve. The burst's solve
        then uses it if its inputs are the same element by element (:meth:`_use_ahead`), so
        every pose is the one solved in turn, and it leaves in the tick the burst completes."""
        sched = self.schedule
        if self._ahead_k >= 0:
            st = self._step_solver()
            if not st & SOLVE_RUNNING:
                ah = self._ahead[self._ahead_k]
                self.solver.save(ah.result)
                ah.finish()
                self._ahead_k = -1
            return
        burst = sched.burst_start
        if burst is None or burst == self._ahead_seen or sched.commanded < sched.n:
            return
        if self._charged and self._units + self.solver.n > self.budget:
            return                       # no room to begin beside the tick's other work
        j = sched.n - 1
        start, end = int(sched.start[j]), int(sched.end[j])
        self._idle_for(start, end)
        k = self._ahead_scan(burst, j, start, end)
        if k == AHEAD_SEEN:
            self._ahead_seen = burst
        elif k >= 0 and self._ahead_start(k, start, end):
            self._units += self.solver.n             # the start, charged as a hand-over
            self._solve_ahead()

    def _ahead_start(self, k: int, start: int, end: int) -> bool:
        """The begin of channel ``k``'s solve ahead on its last window ``[start, end]`` from the
        start its own solve will take: its warm start (:meth:`warm_start`) or, without one, the
        acquisition from the sensor's hemisphere (:meth:`_begin_ahead`); False if none was begun.
        On the compiled core of the fused tracker one call (:meth:`_bind_ahead_start`)."""
        ch = self.channels[k]
        tp = self.poses[ch.node]
        return self._begin_ahead(k, ch, tp, start, end, self.warm_start(ch, tp))

    def _ahead_pending(self) -> bool:
        """A solve ahead runs, or sensors of the open burst have not had their turn yet."""
        b = self.schedule.burst_start
        return self._ahead_k >= 0 or (b is not None and b != self._ahead_seen)

    def _begin_ahead(self, k: int, ch, tp: TrackedPose, start: int, end: int, warm: bool) -> bool:
        """Begin the solve of ``ch``'s burst on its last window extracted now, from the warm start in
        ``tp`` (``warm``) or acquiring from its hemisphere, as :meth:`_solve_from`; False if none."""
        ah = self._ahead[k]
        j = ah.S.shape[1] - 1
        _, n_used, n_base = ch.extractor.extract(start, end, ah.amp, ah.var)
        if n_used == 0 or n_base == 0:
            return False
        np.copyto(ah.S, ch.S)
        np.copyto(ah.sigma, ch.var)
        for i in range(3):
            ah.S[i, j] = ah.amp[i]
            ah.sigma[i, j] = ah.var[i]
        ch.sigma_from(ah.sigv, ah.sigv)
        self._prepare_currents(ah.curv)
        ah.began(warm)
        if warm:
            np.copyto(ah.hemisphere, tp.position)
            np.copyto(ah.warm_p, tp.warm_p)
            np.copyto(ah.warm_R, tp.warm_R)
            st = self.solver.begin(ah.S, ah.currents, ah.sigma, ah.hemisphere, ah.warm_p, ah.warm_R)
        else:
            np.copyto(ah.hemisphere, tp.hemisphere)
            st = self.solver.begin(ah.S, ah.currents, ah.sigma, ah.hemisphere)
        if not st & SOLVE_RUNNING:
            return False
        self._ahead_k = k
        self.ahead_solves += 1
        return True

    def _use_ahead(self, ch, warm: bool) -> bool:
        """In the burst's own turn (:meth:`_begin`, sigmas and, ``warm``, warm start in place):
        whether its solve is the one begun ahead from the same kind of start (warm or acquiring)
        on the same inputs, still running (it goes on as this burst's) or finished (its pose is
        reported now). Otherwise a solve ahead still running gives way (False: solve as usual)."""
        k = self._next
        ah = self._ahead[k]
        running = self._ahead_k
        self._ahead_k = -1
        if ah.burst != self.schedule.burst_start or not (ah.done or running == k):
            return False
        ah.release()
        if ah.warm != warm or not self._same[k][warm]():
            self.ahead_missed += 1
            return False
        self.ahead_used += 1
        if running == k:
            return True
        self.solver.load(ah.result)
        if ah.result.solve_evals > self.solve_evals_max:
            self.solve_evals_max = ah.result.solve_evals
        self._report(ch, not (ah.result.status & SOLVE_FAILED))
        return True

    def _ahead_wanted(self, ch) -> bool:
        """Hook: whether the final solve of ``ch`` would start from a burst solved ahead."""
        return True

    def _prepare_currents(self, cur) -> None:
        """Into ``cur`` (memoryview (n,)): the driver's measured current where it reported one,
        else the nominal."""
        mc, nom = self._measv, self._nomv
        for j in range(len(cur)):
            cur[j] = mc[j] if mc[j] != 0.0 else nom[j]

    def _begin(self, ch) -> None:
        """Status of the burst on ``ch`` and, if usable, the start of its solve
        (:meth:`_start_solve`)."""
        sched = self.schedule
        flags = ch.burst_flags()
        faults = sched.any_faults()
        self._status = input_status(flags, faults) | self.supervisor.pose_status(ch.node, flags)
        usable = not (flags & PULSE_UNUSABLE) and not (faults & COIL_FATAL) and not self.supervisor.veto
        if not usable:
            self._report(ch, False)
            return
        self._start_solve(ch)

    def _start_solve(self, ch) -> None:
        """The start of the solve of the usable burst on ``ch`` (warm from the tracked pose once
        there is one), or the take-over of its solve ahead (:meth:`_use_ahead`)."""
        ch.fill_sigma()
        tp = self.poses[ch.node]
        warm = self.warm_start(ch, tp)
        if self.ahead and self._use_ahead(ch, warm):
            return
        self._solve_from(ch, tp, warm)

    def _solve_from(self, ch, tp: TrackedPose, warm: bool) -> None:
        """:meth:`_start_solve`'s begin of the solve of ``ch`` (its sigma and, ``warm``, its start
        in place), no solve ahead taken over."""
        self._ahead_k = -1                   # a solve ahead still running gives way
        if warm:
            st = self.solver.begin(ch.S, self.currents, ch.sigma, tp.position, tp.warm_p, tp.warm_R)
        else:
            st = self.solver.begin(ch.S, self.currents, ch.sigma, tp.hemisphere)
        if not st & SOLVE_RUNNING:
            self._report(ch, False)

    def _report(self, ch, solved: bool) -> None:
        """Send the burst's magnetic POSE of ``ch`` (without ``POSE_FUSED``),
        hand a solution to :meth:`on_solution`, move on to the next sensor."""
        tp = self.poses[ch.node]
        t_pose = (self._startv[0] + self._endv[-1]) // 2      # the middle of the burst
        if solved and not self._report_pose(ch, tp, t_pose):
            solved = self._out_of_range(tp)
        if not solved:
            self.tx.pose_unknown(ch.node, t_pose, tp.position, self._quat(tp.rotation), self._status)
        self.on_solution(ch, solved)
        if self._next_sensor():
            self._begin(self.channels[self._next])

    def _next_sensor(self) -> bool:
        """After a sensor's report, the move to the next one: True when its begin is due in this
        tick (charged: ``solver.n`` units, one hand-over); False at the cycle's end (the burst
        released) or with no room left in this tick's budget or hand-overs (``_handover``)."""
        self._next += 1
        if self._next == len(self.channels):
            self._next = -1
            self.cycles += 1
            if self._burst_ticks > self.solve_ticks_max:
                self.solve_ticks_max = self._burst_ticks
            self.burst.release()
            return False
        if self._units + self.solver.n > self.budget or self._handovers >= self.handovers_max:
            self._handover = True            # no room left in this tick's budget or hand-overs
            return False
        self._units += self.solver.n
        self._handovers += 1
        return True

    def _out_of_range(self, tp: TrackedPose) -> bool:
        """A diverged start led the solve out of the working volume: no pose; acquire again
        (False: the burst is reported as not solved)."""
        tp.have_pose = False
        self.out_of_range += 1
        return False

    def _report_pose(self, ch, tp: TrackedPose, t_pose: int) -> bool:
        """The solved burst's magnetic POSE of ``ch`` whose middle is ``t_pose``: the solution
        taken into ``tp``, graded (``PoseQuality.grade_burst``) and sent with
        :meth:`reported_covariance`; False when it lies beyond the working volume (nothing
        taken, nothing sent)."""
        if not self._take_solution(tp):
            return False
        sched = self.schedule
        sv = self.solver
        tp.have_pose = True
        cov = sv.covariance
        q = self.quality.grade_burst(ch.node, t_pose, getattr(sv, "cost", 0.0), cov, tp.position, tp.rotation,
                                     ch.S, ch.sigma, sched.start, sched.end)
        self.tx.pose_cov6(ch.node, t_pose, tp.position, self._quat(tp.rotation),
                          self.reported_covariance(ch, cov), self._status | POSE_VALID, q)
        return True

    def _chain_motion(self, ch):
        """Hook: what :meth:`reported_covariance` adds for ``ch``, for the compiled report: None
        (the solver's covariance as it is), or ``(w_last, velocity, out, burst_rms_s, fusion)``
        (``SensorInertial.motion_cov``'s inputs, its output and the filter whose ``initialized``
        it reads)."""
        return None

    def _take_solution(self, tp: TrackedPose) -> bool:
        """The solver's pose into ``tp`` when it lies in the working volume (False: not taken)."""
        sv = self.solver
        if not in_range(sv.position, self.range_m):
            return False
        np.copyto(tp.position, sv.position)
        np.copyto(tp.rotation, sv.rotation)
        return True

    def _quat(self, R):
        """The POSE's quaternion of ``R`` (``rotation.quat_tuple``)."""
        return quat_tuple(R)

    def warm_start(self, ch, tp: TrackedPose) -> bool:
        """Put the solve's start into ``tp.warm_p``, ``tp.warm_R``: the last
        magnetic solution (False before there is one: acquire)."""
        if not tp.have_pose:
            return False
        np.copyto(tp.warm_p, tp.position)
        np.copyto(tp.warm_R, tp.rotation)
        return True

    def busy(self) -> bool:
        """A burst is being solved (or waits to be)."""
        return self._next >= 0 or self.burst.complete

    def reported_covariance(self, ch, cov):
        """Hook: the covariance the magnetic-only POSE of ``ch`` is sent with (the solver's
        ``cov``; a tracker that sees the motion within the burst adds it)."""
        return cov

    _chain_covariance = reported_covariance     # what the compiled report repeats (_bind_report_chain)

    def on_solution(self, ch, solved: bool) -> None:
        """Hook: the burst of ``ch`` was solved (``self.solver`` holds it) or not."""

    def counters(self) -> dict:
        d = {"cycles": self.cycles, "solve_ticks_max": self.solve_ticks_max,
             "solve_evals_max": self.solve_evals_max, "solutions_out_of_range": self.out_of_range}
        if self.ahead:
            d.update({"ahead_solves": self.ahead_solves, "ahead_used": self.ahead_used,
                      "ahead_missed": self.ahead_missed})
        return d
