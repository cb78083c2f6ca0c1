"""The fixed cycle's accuracy held as a running mean: a deficit is carried, not forgotten.

``[adaptive] reference_hold = "mean"`` (with ``accuracy_target = "fixed"``).

The accuracy asked of the adaptive policy is the fixed cycle's RMS error over a run
(Schepers & Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt`` sec. 2.1 and Fig. 1 hold a
bound ``sigma_x,max``; here that bound is the fixed cycle's own accuracy,
``accuracy.FixedCycleReference``). An RMS is a time mean of squared errors, so what has to
match is the *mean* of the policy's pose variance against the mean of the fixed cycle's,
not the variance at every pose. ``accuracy.fixed_cycle_bounds`` turns the reference's mean
``avg`` into a bound at each decision, assuming the policy's variance then follows the
sawtooth it plans (from ``sigma_min`` up to ``sigma_max``). Where it cannot (far from the
source the bound asks for more information than the driver's current cap gives: the
variance stays above ``sigma_max`` however often the policy pulses), the excess is lost:
nothing in the bounds makes up for it elsewhere, and the run's RMS exceeds the fixed
cycle's while the policy spends at full current.

:class:`MeanBudgetReference` keeps, beside the reference's mean variances ``avg``, the mean
of the live filter's own pose variances, ``own`` (the traces of the position and of the
orientation blocks of ``P``, Schepers eq 4 covariance), with the same weights at the same
instants (the mean since the reference settled, then exponential over
``reference_avg_s``). The mean it holds for group ``g`` (position, orientation) is the
reference's times

    f_g = 2 - own_g / (ratio^2 avg_g)        (clamped to [``HOLD_MIN``, ``HOLD_MAX``])

so the next averaging window repays the last one's deficit (``own_g > ratio^2 avg_g``:
tighter bounds) or spends its surplus (looser). With the policy's variance following its
bound within a window, the mean obeys ``d own / dt = (2 T - 2 own) / W`` (``T`` the
target, ``W`` the averaging window): it converges to ``T`` with time constant ``W / 2``,
without overshoot. Where the deficit was made matters only through the range law: the
bound stays ``law(r)`` times the held mean (``FixedCycleReference.law_now``), so a deficit
made at far range is repaid mostly where information is cheap, near the source.

Work: two 3-term traces and two multiply-adds per IMU sample beside the reference's own
propagation; no allocation after ``__init__``.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.actuate.accuracy import FixedCycleReference
from coiltrack.firmware.estimate.layout import ORI, POS

__all__ = ["MeanBudgetReference", "hold_factor", "HOLD_MIN", "HOLD_MAX"]

#: the held mean never falls below this fraction of the reference's (a deficit is repaid over
#: several averaging windows rather than by bounds the driver cannot reach) ...
HOLD_MIN = 0.25
#: ... nor rises above this multiple (a surplus is not spent at once)
HOLD_MAX = 4.0


def hold_factor(own: float, target: float) -> float:
    """``2 - own / target`` within [``HOLD_MIN``, ``HOLD_MAX``] (1 for no target)."""
    if not target > 0.0:
        return 1.0
    f = 2.0 - own / target
    if not f > HOLD_MIN:          # also NaN
        return HOLD_MIN
    return f if f < HOLD_MAX else HOLD_MAX


class MeanBudgetReference(FixedCycleReference):
    """:class:`accuracy.FixedCycleReference` whose held mean carries the live filter's deficit
    (module docstring). Same parameters."""

    def __init__(self, *args, **kw):
        #: mean of the live filter's position and orientation variance traces (m^2, rad^2)
        self.own = np.zeros(2)
        super().__init__(*args, **kw)
        self._held = np.zeros(6)
        #: the factors of the latest ``held_avg`` (position, orientation)
        self.factor = np.ones(2)

    def start(self, P_core, t_us: int) -> None:
        super().start(P_core, t_us)
        P = self.P
        self.own[0] = float(P[POS.start, POS.start] + P[POS.start + 1, POS.start + 1] + P[POS.start + 2, POS.start + 2])
        self.own[1] = float(P[ORI.start, ORI.start] + P[ORI.start + 1, ORI.start + 1] + P[ORI.start + 2, ORI.start + 2])

    def _propagate(self, ekf, dt: float, dt_us: int) -> None:
        super()._propagate(ekf, dt, dt_us)
        P = ekf.P
        a = self._a
        x = float(P[POS.start, POS.start]) + float(P[POS.start + 1, POS.start + 1]) + float(P[POS.start + 2, POS.start + 2])
        self.own[0] += a * (x - float(self.own[0]))
        x = float(P[ORI.start, ORI.start]) + float(P[ORI.start + 1, ORI.start + 1]) + float(P[ORI.start + 2, ORI.start + 2])
        self.own[1] += a * (x - float(self.own[1]))

    def _own_means(self):
        return self.own

    def held_arrays(self):
        return (self.avg, self.law, self.P), (self.own, self.factor, self._held)

    def held_avg(self, ratio: float):
        """The reference's mean variances, each group times its ``hold_factor`` against
        ``ratio^2`` times the reference's mean trace (``ratio``: ``fixed_accuracy_ratio``)."""
        avg = self.avg
        k2 = ratio * ratio
        for g in range(2):
            b = 3 * g
            t = float(avg[b]) + float(avg[b + 1]) + float(avg[b + 2])
            f = hold_factor(float(self.own[g]), k2 * t)
            self.factor[g] = f
            for k in range(b, b + 3):
                self._held[k] = float(avg[k]) * f
        return self._held
