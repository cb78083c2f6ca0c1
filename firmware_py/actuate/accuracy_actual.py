"""The fixed cycle's actual error, not its filter's belief: a sensitivity covariance beside the reference.

``[adaptive] reference_error = "actual"`` (with ``accuracy_target = "fixed"``; default ``"filter"``).

``accuracy.FixedCycleReference`` predicts the covariance the fixed cycle's *filter* would report.
That filter weighs each pulse with ``R_f = var_amp + ((rho_f I)^2 + tau^2) |h|^2``, and
``rho_f`` (``field_model_rel_sigma``) is a cover for model errors whose true size the filter does
not know; at the fixed cycle's 0.91 A near the source the term dominates ``R``, so where the real
model error is smaller the fixed cycle's errors are smaller than its covariance says (orientation
NEES 0.58-0.88 on seeds 5 and 6, ``docs/adaptive.md``). The policy works at lower currents, where
the honest white noise dominates its own ``R``: holding its covariance equal to the fixed cycle's
*belief* gives it larger errors than the fixed cycle's.

**The actual covariance** (the sensitivity of a Kalman filter to a wrong ``R``; Gelb, *Applied
Optimal Estimation*, sec. 7.2): beside the reference's ``P`` (the belief, which sets the fixed
cycle's gains) a second 15x15 covariance ``P_a`` is propagated with the same transition and process
noise (thesis eq 6.17), and at each virtual fixed-cycle pulse, with the gain ``K`` the filter
takes from ``P`` and ``R_f`` (Schepers & Veltink 2010 eq 4, the reference's own Joseph update),

    P_a <- (I - K H) P_a (I - K H)^T + K R_a K^T,   R_a = var_amp + ((rho_a I)^2 + tau^2) |h|^2,

the covariance of the errors a filter with gain ``K`` makes when the measurements' errors have
covariance ``R_a``. With ``rho_a = rho_f``, ``P_a = P`` (the Joseph form of the optimal gain).
The policy's bounds then hold the time mean of ``P_a`` (``avg``) instead of ``P``'s.

**``rho_a`` from the firmware's own innovations** (no truth): the live filter's nominal NIS of each
pulse (3 dof), ``nis_i``, has the expectation ``3 (c + a + q b) / (c + a + b)`` per axis, with
``a`` the amplitude's white variance, ``b = rho_f^2 |y|^2`` the model term the filter assumed
(``|y| = I |h|``, the measured amplitude), ``c`` the prior's share and ``q = rho_a^2 / rho_f^2``.
With ``x_i = b_i / (a_i + b_i)`` (``c`` left out: it pulls ``x`` up and the estimate towards 1,
i.e. towards less correction) this is ``nis_i / 3 - 1 + x_i = q x_i``, and the least-squares
``q = sum x_i (nis_i / 3 - 1 + x_i) / sum x_i^2`` over the pulses since the start, used once
``sum x_i^2`` reaches ``MIN_WEIGHT`` (about 30 pulses half saturated), clamped to ``[Q_MIN, 1]``
(a filter whose innovations exceed ``R_f`` is the NIS feedback's business, ``nis_feedback``).

Work: two more 15x15 products per IMU sample and four per reference pulse (Python reference
only; the compiled core runs this class's propagation through the Python one). All arrays are
allocated in ``__init__``.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.actuate.accuracy import FixedCycleReference
from coiltrack.firmware.actuate.accuracy_budget import MeanBudgetReference
from coiltrack.firmware.estimate.layout import ORI, POS

__all__ = ["ActualCycleReference", "ActualBudgetReference", "ModelErrorEstimate", "actual_reference"]

#: ``sum x_i^2`` before the estimate is used (30 pulses with half their variance model error: 7.5)
MIN_WEIGHT = 7.5
#: the estimate's floor: the model error is never taken as below this share of the assumed one
Q_MIN = 0.01


class ModelErrorEstimate:
    """``q = rho_a^2 / rho_f^2`` from the live filter's pulses (module docstring)."""

    def __init__(self):
        self.sxx = 0.0
        self.sxy = 0.0
        self.n = 0

    def reset(self) -> None:
        self.sxx = self.sxy = 0.0
        self.n = 0

    def add(self, nis_nominal: float, y0: float, y1: float, y2: float, a: float, rho_f: float) -> None:
        """One pulse: its nominal NIS (3 dof), measured amplitude ``y`` (T), the white variance per
        axis ``a`` (T^2) and the assumed relative model error ``rho_f``."""
        b = rho_f * rho_f * (y0 * y0 + y1 * y1 + y2 * y2)
        if not (a + b > 0.0) or not nis_nominal >= 0.0 or nis_nominal > 1e6:
            return
        x = b / (a + b)
        self.sxx += x * x
        self.sxy += x * (nis_nominal / 3.0 - 1.0 + x)
        self.n += 1

    def q(self) -> float:
        """The estimate, 1 (the filter's own ``rho_f``) until ``MIN_WEIGHT`` is reached."""
        if self.sxx < MIN_WEIGHT:
            return 1.0
        v = self.sxy / self.sxx
        if not v > Q_MIN:          # also NaN
            return Q_MIN
        return v if v < 1.0 else 1.0


class _ActualError:
    """The actual covariance ``Pa`` beside a reference's ``P`` (module docstring); mixed in before
    :class:`accuracy.FixedCycleReference` or :class:`accuracy_budget.MeanBudgetReference`."""

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        n = self.P.shape[0]
        self.Pa = np.zeros((n, n))
        self._Pad = self.Pa.reshape(-1)[::n + 1]
        self._A = np.zeros((n, n))
        self._At = self._A.T
        self._Ad = self._A.reshape(-1)[::n + 1]
        self._B = np.zeros((n, n))
        self._KKt = np.zeros((n, n))
        self._Kt = self.upd.K.T
        self.est = ModelErrorEstimate()

    def start(self, P_core, t_us: int) -> None:
        super().start(P_core, t_us)
        self.Pa[:] = P_core

    def note_pulse(self, nis_nominal: float, y, var) -> None:
        """The live filter's pulse: its nominal NIS, amplitude (3,) and white variances (3,)."""
        a = (float(var[0]) + float(var[1]) + float(var[2])) / 3.0
        self.est.add(nis_nominal, float(y[0]), float(y[1]), float(y[2]), a, self.rel_model)

    def _propagate(self, ekf, dt: float, dt_us: int) -> None:
        super()._propagate(ekf, dt, dt_us)        # P, F, q and the means of P's diagonal
        np.matmul(self.F, self.Pa, out=self._A)
        np.matmul(self._A, self._Ft, out=self.Pa)
        self._Pad += self.q
        # the means follow Pa's diagonal instead: avg + a (Pa - avg) = [avg + a (P - avg)] + a (Pa - P)
        a = self._a
        P, Pa, avg = self.P, self.Pa, self.avg
        for k in range(3):
            i = POS.start + k
            j = ORI.start + k
            avg[k] += a * (float(Pa[i, i]) - float(P[i, i]))
            avg[3 + k] += a * (float(Pa[j, j]) - float(P[j, j]))

    def _pulse(self, ekf, model, coil: int) -> None:
        super()._pulse(ekf, model, coil)          # P's Joseph update; upd.H, upd.R, upd.K its gain
        upd = self.upd
        K, H = upd.K, upd.H
        # R_a = R_f - (rho_f^2 - rho_a^2) I^2 |h|^2 on each axis (R_f is diagonal)
        c = self.currents[coil]
        hu = model.h[coil]
        hn2 = float(hu[0] * hu[0] + hu[1] * hu[1] + hu[2] * hu[2])
        ra = float(upd.R[0, 0]) - (1.0 - self.est.q()) * self.rel_model * self.rel_model * c * c * hn2
        A, B = self._A, self._B
        np.matmul(K, H, out=A)                    # K H
        np.negative(A, out=A)
        self._Ad += 1.0                           # I - K H
        np.matmul(A, self.Pa, out=B)
        np.matmul(B, self._At, out=self.Pa)
        np.matmul(K, self._Kt, out=self._KKt)
        self._KKt *= ra
        self.Pa += self._KKt


class ActualCycleReference(_ActualError, FixedCycleReference):
    """:class:`accuracy.FixedCycleReference` holding the fixed cycle's actual error (module docstring)."""


class ActualBudgetReference(_ActualError, MeanBudgetReference):
    """:class:`accuracy_budget.MeanBudgetReference` holding the fixed cycle's actual error."""


def actual_reference(hold: str):
    """The reference class of ``reference_error = "actual"`` for ``reference_hold``."""
    return ActualBudgetReference if hold == "mean" else ActualCycleReference
