"""``[pose]`` lm_step_tol / lm_cost_tol / lm_step_sigma reach the pose solver; a looser
cost tolerance, or a stop on a step shorter than a fraction of the solution's standard
deviation, ends the LM earlier at a pose that differs from the tight one by a small
fraction of that standard deviation."""
import dataclasses

import numpy as np
import pytest

from coiltrack.firmware.config import ConfigError, FirmwareConfig
from coiltrack.firmware.model.field import orthogonal_source
from coiltrack.firmware.compose import make_pose_solver
from coiltrack.firmware.pose.reference import measurement_model, so3_exp
from coiltrack.firmware.pose.solver import SOLVE_OK

COILS = orthogonal_source(0.055, 50)
CUR = np.array([1.5, 1.49, 1.51])
SIGMA_T = 5e-8


def _solves(cfg, cases):
    ps = make_pose_solver(cfg, COILS, cfg.budget.solve_gate_probability)
    sig = np.full((3, 3), SIGMA_T)
    out = []
    for S, x0p, x0R in cases:
        assert ps.solve(S, CUR, sig, np.array([1.0, 0.0, 0.0]), x0p, x0R) == SOLVE_OK
        out.append((ps.position.copy(), ps.iterations, ps.covariance[:3, :3].copy()))
    return out


def _cases(seed: int, n: int, offset_m: float):
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(n):
        u = rng.normal(size=3)
        u[0] = abs(u[0]) + 0.3
        p = rng.uniform(0.3, 0.6) * u / np.linalg.norm(u)
        R = so3_exp(rng.normal(size=3))
        S = measurement_model(p, R, COILS, CUR) + rng.normal(0.0, SIGMA_T, (3, 3))
        d = rng.normal(size=3)
        cases.append((S, p + offset_m * d / np.linalg.norm(d), R @ so3_exp(rng.normal(size=3) * 0.03)))
    return cases


def test_a_looser_cost_tolerance_stops_earlier_within_a_tenth_of_a_sigma():
    """Catches the keys not reaching the solver (the same iterations with both) and an
    early stop that leaves the solve far from its minimum: 24 seeded warm solves at
    0.3-0.6 m, 2 cm and 3 deg from the truth, noise 50 nT. The loose solution lies within
    0.1 of the tight one's position std (the Mahalanobis distance of the 3-vector)."""
    cases = _cases(5, 24, 0.02)
    base = FirmwareConfig().validate()
    tight = _solves(base, cases)
    loose = _solves(base.with_(pose={"lm_cost_tol": 1e-2}).validate(), cases)
    assert sum(t[1] for t in tight) > sum(q[1] for q in loose)
    for (pt, _, C), (pl, _, _) in zip(tight, loose):
        e = pl - pt
        assert float(e @ np.linalg.solve(C, e)) ** 0.5 < 0.1


def test_a_step_shorter_than_a_fraction_of_a_sigma_stops_the_lm_there():
    """``lm_step_sigma = 0.1``: 24 seeded warm solves at 0.3-0.6 m, 5 cm and 3 deg from the
    truth, noise 50 nT. Each ends within 0.1 position std (Mahalanobis, 3-vector) of the
    tightly converged solve, in fewer iterations in all; with ``lm_step_sigma = 0`` the
    iterations are those of the default. Catches the step measured in metres instead of
    standard deviations (it stops after the first step, ~5 sigma off: the 5 cm start is
    ~100 sigma away) and the key not reaching the solver (the default's iterations)."""
    cases = _cases(7, 24, 0.05)
    base = FirmwareConfig().validate()
    tight = _solves(base.with_(pose={"lm_cost_tol": 1e-9, "lm_step_tol": 1e-9}).validate(), cases)
    default = _solves(base, cases)
    assert [q[1] for q in _solves(base.with_(pose={"lm_step_sigma": 0.0}).validate(), cases)] == \
        [q[1] for q in default]
    sig = _solves(base.with_(pose={"lm_step_sigma": 0.1}).validate(), cases)
    assert sum(q[1] for q in sig) < sum(q[1] for q in default)
    for (pt, _, C), (ps, _, _) in zip(tight, sig):
        e = ps - pt
        assert float(e @ np.linalg.solve(C, e)) ** 0.5 < 0.1


@pytest.mark.parametrize("key,value", [("lm_cost_tol", 0.0), ("lm_step_tol", 1.0), ("lm_cost_tol", float("nan")),
                                       ("lm_step_tol", True), ("lm_step_sigma", -0.1), ("lm_step_sigma", 2.0),
                                       ("lm_step_sigma", float("inf"))])
def test_bad_tolerances_are_refused_naming_the_key(key, value):
    """Catches a missing check (a zero tolerance never stops on the cost, NaN never compares)."""
    with pytest.raises(ConfigError, match=rf"pose\.{key}"):
        FirmwareConfig().with_keys(**{key: value}).validate()
