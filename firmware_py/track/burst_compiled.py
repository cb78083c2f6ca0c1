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


class CompiledBurst:
    """The compiled forms of ``SensorInertial``'s burst methods (bound by :meth:`_bind_burst_kernels`)."""

    def _bind_burst_kernels(self, core, max_vel_sigma: float) -> None:
        """On the compiled core (the fusion filter's live state carries its kernels): ``motion_cov``
        (``ct_fusion_motion_cov``, bound to the live state and ``w_last``) and ``compensate_begin`` /
        ``compensate_step`` (``ct_fusion_comp_begin``, ``ct_fusion_pose_at``, ``ct_fusion_comp_add``,
        bound to this sensor's buffers and the filter's live covariance and history; ``max_vel_sigma``:
        the velocity uncertainty above which no compensation is tried)."""
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
