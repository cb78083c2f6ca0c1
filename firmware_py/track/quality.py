"""The quality figure of every POSE: 0-255, 255 best (like Polhemus Viper's distortion level and
trakSTAR's quality number), from three consistency tests computed in the track stage:

* the fit's residual: the pose solver's weighted cost ``chi2 = sum ((S - h) / sigma)^2`` against
  its ``dof = 3 n - 6`` degrees of freedom (``pose.solver``; Schepers & Veltink
  ``seeds/000_e46ec0e8bf7ea271.txt`` eq 5 is the model ``h``): ``x_fit = chi2 / dof``, ~1 when the
  model fits to the noise, larger when metal, a wrong calibration or motion within the burst
  leave a residual the pose cannot absorb;
* the fusion filter's normalised innovation squared, ``x_nis = NIS / m`` (``m`` the innovation's
  dimension; ``estimate.ekf``), when the tracker has one (0 otherwise);
* the quiet field's consistency: the newest magnetometer sample after the burst (coils off, the
  trailing baseline of the last pulse) has ``|B|`` the earth field's magnitude ``earth_field_t``
  in a clean room: ``x_quiet = ((|B| - earth_field_t) / quality_quiet_sigma_t)^2`` (0 when the
  sigma is 0 or no sample is there).

``x = x_fit + x_nis + x_quiet`` is the pose's inconsistency (~1 when everything fits to the
noise). It scales the solve's own position covariance ``P_pos`` (the Cramer-Rao-like
``(H^T W H)^-1`` of ``pose.covariance``: how far the noise alone moves the pose there), the usual
inflation of a least-squares covariance by its reduced chi-square, into an estimated position
error

    ``e = sqrt(trace(P_pos) max(1, x))``  (m)

and ``quality = round(255 e0 / (e0 + e))`` with ``e0 = quality_error_scale_m`` (128 at
``e = e0``): 255 for a perfectly determined pose, falling strictly with the residual (beyond its
noise level, ``x > 1``), with the NIS, with the quiet field's deviation and with the pose's
geometric uncertainty (far from the source, where the noise moves the pose most); 0 for a
non-finite input. Allocation-free: Python floats only.
"""
from __future__ import annotations

import math

__all__ = ["quality_from", "PoseQuality"]


def quality_from(var_trace_m2: float, x: float, scale_m: float) -> int:
    """``round(255 e0 / (e0 + e))``, ``e = sqrt(var_trace max(1, x))`` (module docstring); 0 if
    an input is not finite or the variance is negative."""
    if not (math.isfinite(x) and math.isfinite(var_trace_m2)) or var_trace_m2 < 0.0:
        return 0
    e = math.sqrt(var_trace_m2 * (x if x > 1.0 else 1.0))
    q = int(255.0 * scale_m / (scale_m + e) + 0.5)
    return 255 if q > 255 else q


class PoseQuality:
    """Grades a solved pose (module docstring). ``n_coils``: the solver's coils;
    ``channels``: the sensor channels whose newest sample is the quiet field."""

    def __init__(self, cfg, n_coils: int, channels=()):
        self.scale = float(cfg.quality_error_scale_m)
        self.earth = float(cfg.earth_field_t)
        self.quiet_sigma = float(cfg.quality_quiet_sigma_t)
        self.dof = 3 * int(n_coils) - 6
        self._rings = {ch.node: (ch.ring, ch.ring.bv) for ch in channels
                       if hasattr(ch, "ring")}
        self.last = {ch.node: 0 for ch in channels}     # the last quality per node (0 before any)

    def fit_term(self, cost: float) -> float:
        """``chi2 / dof`` (0 without residual freedom)."""
        return cost / self.dof if self.dof > 0 else 0.0

    def quiet_term(self, node: int) -> float:
        """``((|B| - earth_field_t) / sigma)^2`` of the newest sample of ``node`` (0 if unused)."""
        if self.quiet_sigma <= 0.0 or self.earth <= 0.0:
            return 0.0
        rv = self._rings.get(node)
        if rv is None or len(rv[0]) == 0:
            return 0.0
        p = 3 * rv[0].peek(0)
        b = rv[1]
        m = math.sqrt(b[p] * b[p] + b[p + 1] * b[p + 1] + b[p + 2] * b[p + 2])
        z = (m - self.earth) / self.quiet_sigma
        return z * z

    def consistency(self, node: int, cost: float, nis_per_dim: float = 0.0) -> float:
        """``x = x_fit + x_nis + x_quiet`` (module docstring)."""
        return self.fit_term(cost) + nis_per_dim + self.quiet_term(node)

    def grade(self, node: int, cost: float, var_trace_m2: float, nis_per_dim: float = 0.0) -> int:
        """The quality of a pose of ``node``: the fit's ``cost``, the trace of its position
        covariance (m^2) and the filter's NIS per dimension (0: none); kept in ``last[node]``."""
        q = quality_from(var_trace_m2, self.consistency(node, cost, nis_per_dim), self.scale)
        self.last[node] = q
        return q
