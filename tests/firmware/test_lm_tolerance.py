"""``[lm]`` lm_step_tol / lm_cost_tol reach the pose solver, and a looser cost
tolerance stops the LM earlier at a pose that differs from the tight one by a
small fraction of the solution's own standard deviation."""
import dataclasses

import numpy as np
import pytest

from coiltrack.firmware.config import ConfigError, FirmwareConfig
from coiltrack.firmware.model.field import orthogonal_source
from coiltrack.firmware.pose.factory import make_pose_solver
from coiltrack.firmware.pose.reference import measurement_model, so3_exp
from coiltrack.firmware.pose.solver import SOLVE_OK

COILS = orthogonal_source(0.055, 50)
CUR = np.array([1.5, 1.49, 1.51])
SIGMA_T = 5e-8


def _solves(cfg, cases):
    ps = make_pose_solver(cfg, COILS, cfg.solve_gate_probability)
    sig = np.full((3, 3), SIGMA_T)
    out = []
    for S, x0p, x0R in cases:
        assert ps.solve(S, CUR, sig, np.array([1.0, 0.0, 0.0]), x0p, x0R) == SOLVE_OK
        out.append((ps.position.copy(), ps.iterations, ps.covariance[:3, :3].copy()))
    return out


def test_a_looser_cost_tolerance_stops_earlier_within_a_tenth_of_a_sigma():
    """Catches the keys not reaching the solver (the same iterations with both) and an
    early stop that leaves the solve far from its minimum: 24 seeded warm solves at
    0.3-0.6 m, 2 cm and 3 deg from the truth, noise 50 nT. The loose solution lies within
    0.1 of the tight one's position std (the Mahalanobis distance of the 3-vector)."""
    rng = np.random.default_rng(5)
    cases = []
    for _ in range(24):
        u = rng.normal(size=3)
        u[0] = abs(u[0]) + 0.3
        p = rng.uniform(0.3, 0.6) * u / np.linalg.norm(u)
        R = so3_exp(rng.normal(size=3))
        S = measurement_model(p, R, COILS, CUR) + rng.normal(0.0, SIGMA_T, (3, 3))
        d = rng.normal(size=3)
        cases.append((S, p + 0.02 * d / np.linalg.norm(d), R @ so3_exp(rng.normal(size=3) * 0.03)))
    base = FirmwareConfig().validate()
    tight = _solves(base, cases)
    loose = _solves(dataclasses.replace(base, lm_cost_tol=1e-2).validate(), cases)
    assert sum(t[1] for t in tight) > sum(q[1] for q in loose)
    for (pt, _, C), (pl, _, _) in zip(tight, loose):
        e = pl - pt
        assert float(e @ np.linalg.solve(C, e)) ** 0.5 < 0.1


@pytest.mark.parametrize("key,value", [("lm_cost_tol", 0.0), ("lm_step_tol", 1.0), ("lm_cost_tol", float("nan")),
                                       ("lm_step_tol", True)])
def test_bad_tolerances_are_refused_naming_the_key(key, value):
    """Catches a missing check (a zero tolerance never stops on the cost, NaN never compares)."""
    with pytest.raises(ConfigError, match=rf"lm\.{key}"):
        dataclasses.replace(FirmwareConfig(), **{key: value}).validate()
