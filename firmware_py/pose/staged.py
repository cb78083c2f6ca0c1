"""Work cut into units of bounded cost, run a budget at a time.

A :class:`Staged` computation exposes its next unit of work (``next_unit``,
a callable, ``None`` when finished) and that unit's charge (``next_cost``):
an upper bound of its field evaluations, or, for a unit that evaluates no
field but takes comparable time (a closed form, the covariance), a fixed
charge in the same unit. Each unit sets its successor. :func:`run_units`
runs units while the next one's charge still fits into a budget (what they were
charged is left in the job's ``units_last``); the first unit of a call always runs, so a unit larger than the budget runs alone and
the computation always progresses. Because a unit does the same arithmetic
however the units are grouped into calls, the result does not depend on
the budget.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.linalg import float_view

__all__ = ["Staged", "StagedSolve", "SolveResult", "init_results", "run_units", "SOLVE_RUNNING"]

#: a solve's status while its units remain (one of the ``SOLVE_*`` flags of ``pose.solver``)
SOLVE_RUNNING = 16


class Staged:
    next_unit = None
    next_cost = 0
    units_last = 0          # the charges of the units the last run_units ran

    def _then(self, unit, cost: int = 0) -> None:
        self.next_unit = unit
        self.next_cost = cost

    @property
    def finished(self) -> bool:
        return self.next_unit is None


def _copy_result(src, dst) -> None:
    """``src``'s results into ``dst`` (:meth:`StagedSolve.save`, :meth:`StagedSolve.load`): the
    arrays' bytes through the views :func:`init_results` bound (``_rbytes``: the same values as
    ``np.copyto`` of float64 arrays, without a numpy call), or ``np.copyto`` where an array was
    replaced after it."""
    a, b = src._rbytes, dst._rbytes
    if a[0] is src.position and a[1] is src.rotation and a[2] is src.covariance \
            and b[0] is dst.position and b[1] is dst.rotation and b[2] is dst.covariance:
        b[3][:] = a[3]
        b[4][:] = a[4]
        b[5][:] = a[5]
    else:
        np.copyto(dst.position, src.position)
        np.copyto(dst.rotation, src.rotation)
        np.copyto(dst.covariance, src.covariance)
    dst.iterations, dst.cost, dst.converged = src.iterations, src.cost, src.converged
    dst.status, dst.solve_evals = src.status, src.solve_evals


def run_units(job: Staged, signal, budget: int) -> int:
    """Run ``job``'s units while the next one's charge fits in ``budget``;
    returns the field evaluations done (counted by ``signal.evals``), at
    most the charges."""
    start = signal.evals
    spent = 0
    while job.next_unit is not None:
        cost = job.next_cost
        if spent > 0 and spent + cost > budget:
            break
        job.next_unit()
        spent += cost
    job.units_last = spent
    return signal.evals - start


class SolveResult:
    """A finished solve's results kept aside (allocated once): ``position`` (3,) m, ``rotation``
    (3, 3), ``covariance`` (6, 6), ``iterations``, ``cost``, ``converged``, ``status`` (the
    ``SOLVE_*`` flags) and ``solve_evals`` (:meth:`StagedSolve.save`, :meth:`StagedSolve.load`)."""

    def __init__(self):
        init_results(self)


def init_results(obj) -> None:
    """Give ``obj`` (a :class:`SolveResult` or a solver) the results of a solve, zero."""
    obj.position = np.zeros(3)
    obj.rotation = np.eye(3)
    obj.covariance = np.zeros((6, 6))
    # the three arrays and their bytes, for _copy_result (the arrays kept to see one replaced)
    obj._rbytes = (obj.position, obj.rotation, obj.covariance, memoryview(obj.position).cast("B"),
                   memoryview(obj.rotation).cast("B"), memoryview(obj.covariance).cast("B"))
    obj.iterations = 0
    obj.cost = 0.0
    obj.converged = False
    obj.status = 0
    obj.solve_evals = 0


class StagedSolve(Staged):
    """A pose solve run a budget at a time (the runtime solvers :class:`PoseSolver` and
    :class:`RaabTracker`): the common ``step`` and its work counters.

    Needs ``signal`` (counting ``evals``), ``n`` (coils), ``status`` (the final ``SOLVE_*``
    flags), ``_cov`` (the 6x6 covariance, flat), the counters ``solve_evals``,
    ``evals_last_step``, ``max_evals_per_step``, and the preallocated buffers ``_Sv``, ``_wv``
    (3n, the signals and their weights ``1/sigma`` in the layout ``[3 j + i]``), ``_curv`` (n),
    ``_pcur`` (n) and ``_hp`` (3n).
    """

    def step(self, budget_evals: int) -> int:
        """Advance the solve by at most ``budget_evals`` field evaluations
        (a single unit of work larger than that runs alone); returns
        ``SOLVE_RUNNING`` or, once finished, the final status."""
        if self.next_unit is not None:
            used = self._run(budget_evals)
        else:
            used = self.units_last = 0
        self.evals_last_step = used
        self.solve_evals += used
        if used > self.max_evals_per_step:
            self.max_evals_per_step = used
        return SOLVE_RUNNING if self.next_unit is not None else self.status

    def _run(self, budget_evals: int) -> int:
        """The units of one :meth:`step` (:func:`run_units`; a solver may run a stretch of its
        units in one compiled call, charged and counted as the units would be)."""
        return run_units(self, self.signal, budget_evals)

    #: a solve's result depends on nothing but the arguments of its ``begin`` (no state is kept
    #: from one solve to the next), so a solve run early on the same arguments is the same solve
    memoryless = False

    def save(self, out: SolveResult) -> None:
        """Copy the finished solve's results into ``out`` (without allocating)."""
        _copy_result(self, out)

    def load(self, res: SolveResult) -> None:
        """Make ``res`` (a :meth:`save` of a finished solve) the solver's results."""
        self.next_unit = None            # (self._then(None))
        self.next_cost = 0
        _copy_result(res, self)

    def reset_step_stats(self) -> None:
        self.evals_last_step = 0
        self.max_evals_per_step = 0

    def predict_signals(self, p, R, currents, out) -> None:
        """Model signal matrix ``out[:, j] = R^T B_j(p)`` (3, n) for the given
        currents (used to bring pulses to a common instant, ``fusion``).
        Safe between the steps of a solve."""
        n = self.n
        cur = self._pcur
        for j in range(n):
            cur[j] = currents[j]
        hp = self._hp
        self.signal.predict(p[0], p[1], p[2], R, cur, hp)
        for j in range(n):
            out[0, j], out[1, j], out[2, j] = hp[3 * j], hp[3 * j + 1], hp[3 * j + 2]

    def _load(self, S, currents, sigma) -> bool:
        """Copy the signal matrix ``S`` (3, n), T, its standard deviations ``sigma`` (3, n) and the
        currents (n), A, into the solve's buffers (``_sigma_rms``: the rms of ``sigma``); False if a
        shape is wrong or a value is not finite (or a ``sigma`` not positive)."""
        n = self.n
        if getattr(S, "shape", None) != (3, n) or getattr(sigma, "shape", None) != (3, n) or len(currents) != n:
            return False
        S, sigma = float_view(S), float_view(sigma)
        Sv, wv, cur = self._Sv, self._wv, self._curv
        ssum = 0.0
        for i in range(3):
            for j in range(n):
                s, sg = S[i, j], sigma[i, j]
                if not (math.isfinite(s) and math.isfinite(sg) and sg > 0.0):
                    return False
                Sv[3 * j + i] = s
                wv[3 * j + i] = 1.0 / sg
                ssum += sg * sg
        for j in range(n):
            c = currents[j]
            if not math.isfinite(c):
                return False
            cur[j] = c
        self._sigma_rms = math.sqrt(ssum / (3 * n))
        return True

    def cov_diag(self, out) -> None:
        """Variances of ``(p, dtheta)`` (m^2, rad^2) into ``out`` (6,)."""
        cov = self._cov
        for k in range(6):
            out[k] = cov[7 * k]
