"""The one Levenberg-Marquardt iteration of the firmware, resumable.

Both least-squares fits of the pose solver use it: the 6-DOF pose fit
(``pose.solver``, residual ``(S - h(p, R)) / sigma``) and the 3-DOF
position fit on the rotation invariant ``S^T S`` during acquisition
(``pose.acquire``). They differ only in the residual, the parameter update
and the settings, so the problem is a callback object:

``problem.evaluate(A, g) -> cost``
    at the current parameters: the weighted cost ``r^T r`` and the normal
    equations ``A = Jr^T Jr`` (k x k, row-major), ``g = -Jr^T r`` (k);
``problem.trial(d, A, g) -> cost``
    the same at the trial parameters ``x (+) d`` (kept aside);
``problem.accept()``
    the trial parameters become the current ones;
``problem.small(d) -> bool``
    the step is below the problem's resolution (converged).

Each step solves ``(A + lambda diag A) d = g`` (Marquardt's scaling, a
non-positive diagonal element damped by ``lambda`` itself), accepts it if
the cost does not grow (``lambda /= 10``, floor 1e-12) and otherwise rejects
it (``lambda *= 10``). It stops converged on a small step or a relative cost
change below ``cost_tol`` (a decrease accepted or an increase rejected: the
cost is flat at its rounding level), and unconverged when ``lambda`` exceeds
``lam_max``, the step is not finite, or after ``iters`` steps. A matrix that
is not positive definite raises the damping and counts as a step.

:meth:`LevenbergMarquardt.start` evaluates once and :meth:`iterate` does one
step with one trial evaluation, so a caller can spread a fit over several
ticks. The normal equations of the accepted point stay in :attr:`A` and
:attr:`g` (double-buffered with the trial's). Nothing is allocated.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.linalg import damped_spd_solve

__all__ = ["LevenbergMarquardt", "LM_RUNNING", "LM_CONVERGED", "LM_STOPPED", "damped"]

LM_RUNNING = 0
LM_CONVERGED = 1
LM_STOPPED = 2   # iteration or damping limit, or a non-finite step

_LAM_MIN = 1e-12


def damped(a, m, k: int, lam: float) -> None:
    """``m = a + lam * diag(a)`` for a k x k row-major ``a`` (a non-positive
    diagonal element is damped by ``lam``)."""
    for i in range(k * k):
        m[i] = a[i]
    for i in range(0, k * k, k + 1):
        da = a[i]
        if da <= 0.0:
            da = 1.0
        m[i] += lam * da


class LevenbergMarquardt:
    """Preallocated LM of dimension ``k``.

    Parameters
    ----------
    k : int
        Number of parameters.
    lam0, lam_max : float
        Initial damping and the damping at which the fit gives up.
    iters : int
        Step limit.
    cost_tol : float
        Converged when an accepted step lowers the cost by less than this
        fraction (0 disables).
    step_sigma : float
        Converged when an accepted step's length in the metric of ``A`` is
        below this (0 disables): ``sqrt(d^T A d)``, which for a weighted fit
        (``A = J^T W J``, ``A^-1`` the covariance of the parameters) is the
        step in standard deviations of the estimate, whatever the units and
        the size of the cost. From ``(A + lambda D) d = g``:
        ``d^T A d = d^T g - lambda d^T D d`` (``D`` the damped diagonal).

    After a run: ``state`` (``LM_*``), ``cost``, ``it`` (steps taken) and
    :attr:`A` / :attr:`g`, the normal equations at the solution.
    """

    def __init__(self, k: int, lam0: float, lam_max: float, iters: int, cost_tol: float, step_sigma: float = 0.0):
        self.k = k
        self.lam0 = lam0
        self.lam_max = lam_max
        self.iters = iters
        self.cost_tol = cost_tol
        self.step_sigma2 = step_sigma * step_sigma
        self._A = [memoryview(np.zeros(k * k)), memoryview(np.zeros(k * k))]
        self._g = [memoryview(np.zeros(k)), memoryview(np.zeros(k))]
        self._solve = damped_spd_solve(k)
        self.d = memoryview(np.zeros(k))
        self._cur = 0
        self.problem = None
        self.state = LM_STOPPED
        self.cost = math.inf
        self.lam = lam0
        self.it = 0

    @property
    def A(self):
        return self._A[self._cur]

    @property
    def g(self):
        return self._g[self._cur]

    def start(self, problem) -> None:
        """Evaluate ``problem`` at its current parameters (one evaluation)."""
        self.problem = problem
        self._cur = 0
        self.cost = problem.evaluate(self._A[0], self._g[0])
        self.lam = self.lam0
        self.it = 0
        self.state = LM_RUNNING if self.iters > 0 else LM_STOPPED

    def iterate(self) -> int:
        """One damped step (at most one trial evaluation); returns ``state``."""
        self.it += 1
        c = self._cur
        # damped, cholesky and chol_solve in one straight-line call (linalg)
        if self._solve(self._A[c], self._g[c], self.d, self.lam):
            self._step(c)
        else:
            self._raise_damping()
        if self.state == LM_RUNNING and self.it >= self.iters:
            self.state = LM_STOPPED
        return self.state

    def _step(self, c: int) -> None:
        d = self.d
        for i in range(self.k):
            if not math.isfinite(d[i]):
                self.state = LM_STOPPED
                return
        problem = self.problem
        cost_t = problem.trial(d, self._A[1 - c], self._g[1 - c])
        small = problem.small(d) or (self.step_sigma2 > 0.0 and self._metric2(c) < self.step_sigma2)
        if math.isfinite(cost_t) and cost_t <= self.cost:
            problem.accept()
            self._cur = 1 - c
            rel = (self.cost - cost_t) / max(self.cost, 1e-300)
            self.cost = cost_t
            self.lam = max(self.lam * 0.1, _LAM_MIN)
            if small or rel < self.cost_tol:
                self.state = LM_CONVERGED
        elif small or (cost_t - self.cost) < self.cost_tol * max(self.cost, 1e-300):
            self.state = LM_CONVERGED          # the cost is flat to its rounding level
        else:
            self._raise_damping()

    def _metric2(self, c: int) -> float:
        """``d^T A d`` of the step just solved, from ``d^T g - lambda d^T D d`` (see ``step_sigma``)."""
        d, g, a, k, lam = self.d, self._g[c], self._A[c], self.k, self.lam
        dg = dd = 0.0
        for i in range(k):
            di = d[i]
            dg += di * g[i]
            da = a[i * (k + 1)]
            dd += (da if da > 0.0 else 1.0) * di * di
        return dg - lam * dd

    def _raise_damping(self) -> None:
        self.lam *= 10.0
        if self.lam > self.lam_max:
            self.state = LM_STOPPED
