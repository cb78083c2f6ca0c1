"""Work cut into units of bounded cost, run a budget at a time.

A :class:`Staged` computation exposes its next unit of work (``next_unit``,
a callable, ``None`` when finished) and an upper bound of that unit's cost
in field evaluations (``next_cost``). Each unit sets its successor.
:func:`run_units` runs units while the next one still fits into a budget;
the first unit of a call always runs, so a unit larger than the budget runs
alone and the computation always progresses; units that evaluate no field
(closed forms, the covariance) run whenever they are next. Because a unit does the same
arithmetic however the units are grouped into calls, the result does not
depend on the budget.
"""
from __future__ import annotations

__all__ = ["Staged", "run_units"]


class Staged:
    next_unit = None
    next_cost = 0

    def _then(self, unit, cost: int = 0) -> None:
        self.next_unit = unit
        self.next_cost = cost

    @property
    def finished(self) -> bool:
        return self.next_unit is None


def run_units(job: Staged, signal, budget: int) -> int:
    """Run ``job``'s units while the next fits in ``budget`` field evaluations
    (counted by ``signal.evals``); returns the evaluations used."""
    start = signal.evals
    used = 0
    while job.next_unit is not None:
        cost = job.next_cost
        if cost > 0 and used > 0 and used + cost > budget:
            break
        job.next_unit()
        used = signal.evals - start
    return used
