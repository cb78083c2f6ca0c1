"""The compiled core's side of a sensor's burst fusion (``burst_fusion.SensorInertial``).

:class:`CompiledBurst` is the base of ``SensorInertial``: on the compiled core it binds, once,
``core/src/fusion.c``'s kernels of a burst's motion compensation (thesis ``002_cd7f1fdb7fc67471.txt``
sec 6.5: the pulses brought to the burst's reference instant with the inertial pose history) and
of the motion covariance added to a burst's solution, and puts its methods in place of the
reference's (``SensorInertial.compensate_begin``, ``compensate_step``, ``motion_cov``, which stay
the specification; the same operations in the same order, the same bits). On the Python core
nothing is bound.

All buffers are the sensor's, bound at construction; a call allocates no numpy array.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.pose.staged import SOLVE_RUNNING

#: ``SensorInertial.fz`` (int64): the stage of ``fuse``, the next pulse to compensate, the compensated
#: re-solve's success, the bursts compensated (``core/include/ct_fuse.h`` ``CT_FZ_*``)
FZ_STAGE, FZ_COMP_J, FZ_COMP_OK, FZ_COMPENSATED, FZ_N = range(5)


def _fz_int(i: int, as_bool: bool = False):
    """A property over entry ``i`` of ``self._fzv`` (0/1 for a bool)."""
    def fset(self, v) -> None:
        self._fzv[i] = (1 if v else 0) if as_bool else v
    if as_bool:
        return property(lambda self: self._fzv[i] != 0, fset)
    return property(lambda self: self._fzv[i], fset)


class CompiledBurst:
    """The compiled forms of ``SensorInertial``'s burst methods (bound by :meth:`_bind_burst_kernels`,
    :meth:`bind_fuse`), and the sensor's state the kernels read and write in place: start-up int64
    arrays (``sc``, ``tr``, ``fz``, made by ``SensorInertial``) read through properties under the
    reference's names."""

    def _set_samples(self, v: int) -> None:
        self._scv[0] = v

    samples = property(lambda self: self._scv[0], _set_samples)     # IMU samples processed

    def _set_t_ref(self, v: int) -> None:
        self._trv[0] = v

    #: the burst's reference instant (us), in a start-up int64 array (``tr``) a burst's compiled
    #: opening writes (``BurstFusionTracker.on_burst``, ``core/src/burst_open.c`` ``ct_schedule``)
    t_ref = property(lambda self: self._trv[0], _set_t_ref)

    stage = _fz_int(FZ_STAGE)                  # the stage of ``fuse`` (burst_fusion._COMPENSATE, ...)
    _comp_j = _fz_int(FZ_COMP_J)               # the next pulse to compensate
    comp_ok = _fz_int(FZ_COMP_OK, True)        # the compensated re-solve succeeded
    compensated = _fz_int(FZ_COMPENSATED)      # bursts whose pulses were all compensated

    def _bind_burst_kernels(self, core, max_vel_sigma: float) -> None:
        """On the compiled core (the fusion filter's live state carries its kernels): ``motion_cov``
        (``ct_fusion_motion_cov``, bound to the live state and ``w_last``) and ``compensate_begin`` /
        ``compensate_step`` (``ct_fusion_comp_begin``, ``ct_fusion_pose_at``, ``ct_fusion_comp_add``,
        bound to this sensor's buffers and the filter's live covariance and history; ``max_vel_sigma``:
        the velocity uncertainty above which no compensation is tried)."""
        self._max_vel_sigma = max_vel_sigma
        st = self.fusion.st
        if st.ck is None:
            return
        self._mc = core.ext.MotionCov(st.P.shape[0], self.burst_rms_s * self.burst_rms_s, st.P, st.v,
                                      self.w_last).into
        self.motion_cov = self._motion_cov_compiled
        hist = self.fusion.history.live
        self._comp = core.ext.Compensate(self.S_comp.shape[1], st.P.shape[0], max_vel_sigma, self.S_comp,
                                         self._h_ref, self._h_j, self._p_ref, self._R_ref, self._p_j, self._R_j,
                                         st.P, hist.t, hist.d, hist.hc)
        self.compensate_begin = self._compensate_begin_compiled
        self.compensate_step = self._compensate_step_compiled

    def bind_fuse(self, core, comp_solver, solver, S, pulse_t, currents, fs_at: tuple, stages,
                  codes: tuple) -> None:
        """On the compiled core, the start of a burst's fusion update (:meth:`fuse`'s compensation
        stages) in one call, and :meth:`on_solution`'s copies in one more (``ext.FuseComp``,
        ``core/src/fuse.c``: the same operations in the same order, the same bits), bound once to this
        sensor's buffers, its channel's signals ``S`` (3, n) and pulse times ``pulse_t`` (int64, n),
        the tracker's ``currents``, ``comp_solver``'s model (the re-solve's: its predictions) and
        ``solver``'s results (the burst's magnetic-only solution); ``fs_at``: the fusion filter's
        initialised flag's index and the length of its ``fs``; ``stages``: the reference's methods
        (``fuse``, ``_measure_step``, ``on_solution``, ``compensate_begin``, ``compensate_step``,
        ``_begin_solve``), the compiled forms replace them only where this instance runs those;
        ``codes``: the update's stage codes of the re-solve and of the magnetic update (``_SOLVE``,
        ``_UPDATE_MAG``), which the re-solve's begin in place sets as ``_begin_solve`` does. Left to the Python
        where any part is of another kind (no compiled solver or filter, a distortion map)."""
        st = self.fusion.st
        ext = core.ext
        if ext is None or st.ck is None or getattr(comp_solver, "_sv", None) is None \
                or comp_solver.signal.distortion is not None or not hasattr(self, "_comp") \
                or tuple(getattr(type(self), k) for k in ("fuse", "_measure_step", "on_solution")) != stages[:3] \
                or type(self).compensate_begin is not stages[3] or type(self).compensate_step is not stages[4]:
            return
        sig = comp_solver.signal
        hist = self.fusion.history.live
        try:
            k = ext.FuseComp(self.S_comp.shape[1], st.P.shape[0], self._max_vel_sigma,
                             bool(self.cfg.fusion.motion_compensation), fs_at[0], fs_at[1],
                             (S, self.S_comp, self._h_ref, self._h_j, self._p_ref, self._R_ref, self._p_j, self._R_j,
                              st.P, hist.t, hist.d, hist.hc, self.fusion.fs, self.tr, pulse_t, sig._geom, sig.B, sig.J,
                              currents, self.fz, solver.position, solver.rotation, solver.covariance,
                              self.mag_position, self.mag_rotation, self.mag_cov))
        except (AttributeError, TypeError, ValueError):
            return
        self._fz_run = k.run
        self._fz_solution = k.solution
        self._fz_solve, self._fz_n = codes[0], self.S_comp.shape[1]
        #: the re-solve's begin in place where this class's is the reference's (``_begin_solve``)
        self._fz_begin = codes if type(self)._begin_solve is stages[5] else None
        self._fz_solvers = (comp_solver, solver)
        self._fuse_reference = stages[0]
        self._on_solution_reference = stages[2]
        self.fuse = self._fuse_compiled
        self.on_solution = self._on_solution_compiled

    def _fuse_compiled(self, solver, S, currents, sigma, pulse_t, budget: int, replay_budget: int, fresh: bool,
                       e0: int | None = None) -> bool:
        """:meth:`fuse` on the compiled core: its compensation stages in one call (``FuseComp.run``,
        ``ct_fuse_compensate``), the evaluations charged to ``solver``'s model; the re-solve's begin
        where the pulses are all compensated, then :meth:`fuse`'s first test in place (no room left for
        a step of the re-solve: the usual case in the tick a burst is solved) and what follows in the
        reference (from ``e0``)."""
        signal = solver.signal
        if solver is not self._fz_solvers[0] or signal.distortion is not None or e0 is not None:
            return self._fuse_reference(self, solver, S, currents, sigma, pulse_t, budget, replay_budget, fresh, e0)
        e0 = signal.evals
        r = self._fz_run(budget)
        if r >= 8:
            signal.add_evals(r >> 3)
        code = r & 3
        if code == 0:                  # no room for the next step in this tick
            self.waiting = (r & 4) != 0
            return False
        if code == 1:                  # every pulse compensated: the re-solve begins
            if self._fz_begin is None:
                self._begin_solve(solver, currents, sigma)
            else:                      # (_begin_solve's lines, the stage written in place)
                st = solver.begin(self.S_comp, currents, sigma, self.mag_position, self.mag_position,
                                  self.mag_rotation)
                self._fzv[FZ_STAGE] = self._fz_begin[0] if st & SOLVE_RUNNING else self._fz_begin[1]
            if self._fzv[FZ_STAGE] == self._fz_solve and budget - (signal.evals - e0) < self._fz_n:
                self.waiting = signal.evals == e0
                return False
        return self._fuse_reference(self, solver, S, currents, sigma, pulse_t, budget, replay_budget, fresh, e0)

    def _on_solution_compiled(self, solver, solved: bool) -> None:
        """:meth:`on_solution` on the compiled core (``FuseComp.solution``: the copies, the stage)."""
        if solver is not self._fz_solvers[1]:
            self._on_solution_reference(self, solver, solved)
            return
        self.pending = self._fz_solution(solved)

    def _motion_cov_compiled(self, C, compensated: bool, out, p) -> None:
        """:meth:`motion_cov` on the compiled core (``C``, ``out``, ``p``: C-contiguous float64 arrays)."""
        self._mc(C, compensated, out, p, self.fusion.initialized)

    def _compensate_begin_compiled(self, solver, S, currents) -> bool:
        """:meth:`compensate_begin` on the compiled core (``ext.Compensate.begin``: the copy, the
        checks and the pose at ``t_ref`` in one call; ``S`` a C-contiguous float64 array)."""
        if not self._comp.begin(S, self.fusion.initialized, self.t_ref):
            return False
        solver.predict_signals(self._pr, self._Rr, currents, self._h_ref)
        self._comp_j = 0
        return True

    def _compensate_step_compiled(self, solver, S, currents, pulse_t, budget: int) -> int:
        """:meth:`compensate_step` on the compiled core (``ext.Compensate.pulse`` and ``add``)."""
        n = self.S_comp.shape[1]
        comp = self._comp
        used = 0
        j = self._comp_j
        while j < n and (used == 0 or used + n <= budget):
            if not comp.pulse(pulse_t[j]):
                np.copyto(self.S_comp, S)
                return -1
            solver.predict_signals(self._pj, self._Rj, currents, self._h_j)
            comp.add(j)
            used += n
            j += 1
            self._comp_j = j
        if j < n:
            return 0
        self.compensated += 1
        return 1
