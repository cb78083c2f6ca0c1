"""Pose solvers: a burst's signal matrix to a 6-DOF pose.

The solvers, one chosen by ``[pose] pose_solver`` in :mod:`coiltrack.firmware.compose`
(its table ``SOLVERS``):

* :mod:`.solver` (``"lm"``): Kuipers' closed form and the grid search to acquire
  (:mod:`.acquire`), Levenberg-Marquardt least squares (:mod:`.lm`) on the one signal model
  (:mod:`coiltrack.firmware.model.signal`; Schepers & Veltink ``000_e46ec0e8bf7ea271.txt``
  eqs 5-11, thesis ``002_cd7f1fdb7fc67471.txt`` App. 5.A);
* :mod:`.raab` (``"raab"``): Raab et al. 1979's iterative tracker
  (``004_86267342cd7488ce.txt`` eqs 7-31).

Both run a budget at a time (:mod:`.staged`); their contract is :class:`Solver`.
:mod:`.reference` is the allocating reference implementation the tests compare with.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

__all__ = ["Solver"]


@runtime_checkable
class Solver(Protocol):
    """A resumable pose solver.

    Reads: the arguments of :meth:`begin` (signal matrix ``S`` (3, n) T, ``currents`` (n,) A,
    ``sigma`` (3, n) T, the hemisphere or a warm start), copied into its own buffers.
    Owns: its signal model (``signal``, whose ``evals`` counts every coil field evaluation),
    its results and work counters.
    Returns: a status of ``SOLVE_*`` bits (``SOLVE_RUNNING`` while units remain); after it,
    ``position`` (3,) m, ``rotation`` (3, 3) sensor to source, ``covariance`` (6, 6).
    Work bound: :meth:`step` runs units while their charges fit in ``budget_evals`` field
    evaluations (a single larger unit runs alone); ``next_unit`` / ``next_cost`` say what
    the next unit would charge, ``units_last`` what the last step was charged.
    """

    n: int
    signal: object
    position: object
    rotation: object
    covariance: object
    status: int
    solve_evals: int
    next_unit: object
    next_cost: int
    units_last: int
    memoryless: bool

    def begin(self, S, currents, sigma, hemisphere=None, x0_position=None, x0_rotation=None) -> int:
        """Start a solve (warm from ``x0_position``, ``x0_rotation`` when given)."""

    def step(self, budget_evals: int) -> int:
        """Advance the solve within ``budget_evals`` field evaluations."""

    def solve(self, S, currents, sigma, hemisphere=None, x0_position=None, x0_rotation=None) -> int:
        """:meth:`begin` and :meth:`step` until done (tools and tests)."""

    def predict_signals(self, p, R, currents, out) -> None:
        """The model's signal matrix at pose (``p``, ``R``) into ``out`` (3, n)."""

    def save(self, out) -> None:
        """Copy the finished solve's results into ``out`` (a ``staged.SolveResult``)."""

    def load(self, res) -> None:
        """Make ``res`` (a :meth:`save`) the solver's results."""
