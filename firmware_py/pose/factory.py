"""The one place a burst tracker's pose solver is built from the configuration.

``pose_solver = "lm"``: :class:`coiltrack.firmware.pose.solver.PoseSolver`
(Kuipers' closed form, least squares); ``"raab"``:
:class:`coiltrack.firmware.pose.raab.RaabTracker` (Raab et al. 1979,
``seeds/004_86267342cd7488ce.txt`` eqs 7-31). Both have the same interface
(``begin``, ``step``, ``solve``, ``predict_signals``, ``position``,
``rotation``, ``covariance``, ``status``, the work counters).
"""
from __future__ import annotations

import math

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE

__all__ = ["make_pose_solver", "POSE_SOLVERS"]

POSE_SOLVERS = ("lm", "raab")


def make_pose_solver(cfg, coils, gate_probability: float, core=_DEFAULT_CORE):
    """The solver ``cfg.pose_solver`` for ``coils`` (``field.Coil``), with the
    signal model ``cfg.field_model``, a warm start's chi-square gate and the LM's
    stopping tolerances ``cfg.lm_step_tol``, ``cfg.lm_cost_tol``, ``cfg.lm_step_sigma``, on the
    numeric core ``core`` (``coiltrack.firmware.core.Core``, chosen at composition)."""
    if cfg.pose_solver == "raab":
        from coiltrack.firmware.pose.raab import RaabTracker

        start = cfg.raab_start_position
        return RaabTracker(coils, cfg.field_model, iters=cfg.raab_iterations,
                           acquire_iters=cfg.raab_acquire_iterations, gate_probability=gate_probability,
                           step_tol=cfg.raab_step_tol, refresh=cfg.raab_refresh, correction=cfg.raab_correction,
                           start_position=start if any(v != 0.0 for v in start) else None,
                           start_euler=tuple(math.radians(v) for v in cfg.raab_start_euler_deg),
                           hemisphere=cfg.hemisphere, step_sigma=cfg.raab_step_sigma, core=core)
    from coiltrack.firmware.pose.solver import PoseSolver

    return PoseSolver(coils, cfg.field_model, gate_probability=gate_probability,
                      step_tol=cfg.lm_step_tol, cost_tol=cfg.lm_cost_tol, step_sigma=cfg.lm_step_sigma,
                      core=core)
