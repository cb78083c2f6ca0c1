"""Work cut into units of bounded cost, run a budget at a time.

A :class:`Staged` computation exposes its next unit of work (``next_unit``,
a callable, ``None`` when finished) and that unit's charge (``next_cost``):
an upper bound of its field evaluations, or, for a unit that evaluates no
field but takes comparable time (a closed form, the covariance), a fixed
charge in the same unit. Each unit sets its successor. :func:`run_units`
runs units while the next one's charge still fits into a budget; the first
unit of a call always runs, so a unit larger than the budget runs alone and
the computation always progresses. Because a unit does the same arithmetic
however the units are grouped into calls, the result does not depend on
the budget.
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
    return signal.evals - start
