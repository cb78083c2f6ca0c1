"""The fusing trackers' solve ticks on the compiled core, in fewer Python frames.

A tick that solves or fuses a burst (``BurstFusionTracker._step``; ``track.ac.ACFusionTracker.step``)
ran some twenty small Python methods around its compiled calls: the tick's charges through three
hooks (``_charges``, ``_tick_charges``, ``_window_charges``), computed twice, ``busy`` three times,
``_fuse_step`` with no sensor pending, the fused sensor's poses through ``send_fused`` and
``PoseOutput.send_plain``. :class:`SolveTick` binds, once at composition and only where the class
runs the reference hooks, their forms in one frame: the same tests and the same values in the same
order (the hooks stay the reference and the specification; on the Python core nothing is bound).
"""
from __future__ import annotations

from coiltrack.firmware.track.magnetic import MagneticTracker


class SolveTick:
    """Mixin of ``BurstFusionTracker``: the compiled core's solve tick (:meth:`_step_solving`) and
    the tick's charges in one frame (:meth:`_charges_fused`, :meth:`_charges_imu`)."""

    def _bind_solve_tick(self, ref, fused_valid: int) -> None:
        """Bound by ``BurstFusionTracker._bind_fused_tick`` (the compiled core, the fused tick's
        kernels bound; ``ref``: ``BurstFusionTracker``, whose ``_step`` :meth:`_step_solving` stands
        for; ``fused_valid``: a plain fused pose's status): :meth:`_step_solving` where the class
        runs the reference's ``_step``, ``busy`` and ``_fuse_step``, and the charges in one frame
        where it runs the reference's hooks (:meth:`_bind_charges`)."""
        cls = type(self)
        self._bind_charges(ref)
        self._step_solving = self._step
        if cls._step is not ref._step or cls.busy is not MagneticTracker.busy or cls._fuse_step is not ref._fuse_step \
                or getattr(self._charges, "__func__", None) is not SolveTick._charges_fused:
            return
        self._st_rows = {ins: row for row in self._ft_send for ins in row[1:2]}
        self._st_valid = fused_valid
        self._step_solving = self._step_solve_compiled

    def _bind_charges(self, ref, windowless=None) -> None:
        """:meth:`_charges` in one frame where the class's hooks are the reference's
        (``MagneticTracker._charges`` over ``ref._tick_charges`` over ``_window_charges``: the
        windows' (``MagneticTracker``'s, :meth:`_charges_fused`) or ``windowless``, a hook that
        charges none (an AC tracker's, :meth:`_charges_imu`))."""
        cls = type(self)
        if cls._charges is not MagneticTracker._charges or cls._tick_charges is not ref._tick_charges:
            return
        if cls._window_charges is MagneticTracker._window_charges:
            self._charges = self._charges_fused
        elif windowless is not None and cls._window_charges is windowless:
            self._charges = self._charges_imu

    def _charges_fused(self) -> int:
        """:meth:`_charges` of a fusing tracker (``BurstFusionTracker._tick_charges`` over
        ``MagneticTracker._window_charges``)."""
        return 0 if self._waited else self.window_evals * self.burst.closed_last + self.imu_sample_evals * self._imu_last

    def _charges_imu(self) -> int:
        """:meth:`_charges` of a fusing tracker whose stage closes no windows (AC blocks)."""
        return 0 if self._waited else 0 + self.imu_sample_evals * self._imu_last

    def _step_solve_compiled(self, now_us: int) -> None:
        """``BurstFusionTracker._step`` (the ticks ``_step_fast`` does not take: a solve's, a
        fusion's): the same steps in the same order, ``busy`` read in place, the charges
        (:meth:`_charges_fused`) in place and given to ``MagneticTracker.step``, ``_fuse_step`` in
        place (:meth:`_fuse_pending`), the fused sensor's poses through :meth:`send_fused_one`."""
        n = 0 if self._idle else self._process(now_us)
        self._imu_last = n
        fusing = self._n_pending > 0
        burst = self.burst
        fresh = self._next < 0 and not burst.complete
        if n and not self._deferring and fusing and fresh:
            self._deferring = True
            self.deferred += 1
            self._send_fused()
            return
        self._deferring = False
        solve = not fresh or (self.ahead and not fusing and self._ahead_pending())
        if not solve and not fusing:
            self._waited = False
            if n:
                self._send_fused()
            return
        signal = self.solver.signal
        e0 = signal.evals
        charges = 0 if self._waited else self.window_evals * burst.closed_last + self.imu_sample_evals * n
        if solve:
            MagneticTracker.step(self, now_us, charges)
        fused = None
        if self._next < 0 and not burst.complete:
            self._waited = False
            if self._n_pending:
                fused = self._fuse_pending(self.budget - charges - (signal.evals - e0), fresh, charges)
        if n:
            self._send_fused()
        elif fused is not None:
            self.send_fused_one(fused)

    def _fuse_pending(self, budget: int, fresh: bool, charges: int):
        """``BurstFusionTracker._fuse_step`` after its first line, with a sensor pending."""
        for ch, ins in self._pairs:
            if ins.pending:
                ins.fuse(self.comp_solver, ch.S, self.currents, ch.sigma, ch.pmv, budget, self.replay_budget, fresh)
                self._waited = bool(charges) and ins.waiting
                if not ins.pending:
                    self._n_pending -= 1
                return ins
        return None

    def send_fused_one(self, ins) -> None:
        """``ins.send_fused`` of the one sensor a tick fused (its plain poses in one transmitter call,
        as ``BurstFusionTracker._send_fused_plain`` sends each sensor's)."""
        node, _, kernel, rec = self._st_rows[ins]
        q, rm = self.quality.last[node], self.range_m
        if ins.dr_state or rec.recoveries != ins.recoveries_seen or self.tx.fused_pose(kernel, node, self._st_valid,
                                                                                        q, rm):
            ins.send_fused(self.tx, node, rm, q)
