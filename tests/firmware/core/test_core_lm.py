"""The compiled Levenberg-Marquardt step with its cost (firmware_py/core/src/lm.c, linalg_gen.c)
against its Python reference (pose/lm.py LevenbergMarquardt on pose/solver.py _PoseFit).

The C does the same floating-point operations in the same order (the damped Cholesky solve is
generated from the same straight-line source as the Python's, ``linalg.generated_c``), compiled
with -ffp-contract=off, so every comparison is bit for bit: cost, normal equations, the solved
pose, the iteration count and the evaluations charged. Seeded; skips without the extension."""
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.linalg import damped_spd_solve, generated_c
from coiltrack.firmware.model.distortion import DistortionMap
from coiltrack.firmware.model.field import Coil, orthogonal_source
from coiltrack.firmware.pose.solver import SOLVE_BAD_INPUT, PoseSolver
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

ORTHO = orthogonal_source(0.055, 50)
SKEWED = [Coil([0.01, 0, 0], [1, 0.2, 0], 0.05, 40), Coil([0, 0.012, 0], [0, 1, 0.3], 0.06, 50),
          Coil([0, 0, 0.01], [0.1, 0, 1], 0.055, 45), Coil([-0.01, 0, 0], [1, 1, 1], 0.04, 30)]


def test_generated_c_is_the_generators_output():
    """core/src/linalg_gen.c is exactly what linalg.generated_c() emits (an edit of the generator
    or of the file alone is caught)."""
    src = Path(core.__file__).resolve().parent / "src" / "linalg_gen.c"
    assert src.read_text() == generated_c()


def test_pair_binds_the_compiled_lm():
    ref = PoseSolver(ORTHO, "exact", core=core.PYTHON)
    got = PoseSolver(ORTHO, "exact", core=core.load("compiled"))
    assert ref._lm_c is None and got._lm_c is not None


#: the solve's phases (core/include/ct_solve.h CT_PH_*): the LM's start, one of its steps
_PH_LM_START, _PH_LM_STEPS = 1, 2


def _one_unit(solver, phase: int) -> None:
    """One compiled unit of the solve on the solver's bound fit and LM (``SolveRun.run`` with no
    budget runs exactly one, ``ct_solve_run``): the LM's start (``ct_lm_pose_start``) or one of
    its steps (``ct_lm_pose_iterate``)."""
    solver._svv[0] = phase
    solver._sv.run(0, 0)


def _spd(rng, k, cond):
    q, _ = np.linalg.qr(rng.normal(size=(k, k)))
    return (q * np.geomspace(1.0, 1.0 / cond, k)) @ q.T


def test_damped_solve_matches_the_generated_python():
    """The LM's damped solve alone (through a cost-free start: the normal equations set by hand):
    ``ct_damped_spd_solve_6`` against ``linalg.damped_spd_solve(6)`` on well-conditioned,
    near-singular (cond 1e15), indefinite and non-positive-diagonal matrices, lam from 0 to
    1e10: the same step d to the bit and the same refusals."""
    rng = np.random.default_rng(11)
    py = damped_spd_solve(6)
    solver = PoseSolver(ORTHO, "exact", core=core.load("compiled"))
    lm = solver._lm_c
    for trial in range(300):
        kind = trial % 4
        a = _spd(rng, 6, (1e3, 1e15, 1e8, 10.0)[kind])
        if kind == 2:
            a[5, 5] = -abs(a[5, 5])                 # indefinite
        if kind == 3:
            a[2, 2] = 0.0                           # a zero diagonal: damped by lam alone
        b = rng.normal(size=6)
        lam = 10.0 ** rng.uniform(-12, 10) if trial % 7 else 0.0
        x_ref = memoryview(np.zeros(6))
        ok_ref = py(memoryview(a.reshape(-1).copy()), memoryview(b.copy()), x_ref, lam)
        # the compiled LM solves A[cur] d = g[cur] at its lambda (one step of the solve's units):
        # set the state by hand and read d
        lm._A[0][:] = memoryview(a.reshape(-1).copy())
        lm._g[0][:] = memoryview(b.copy())
        st = lm._stv
        st[0], st[1], st[2], st[3], st[4] = 0.0, math.inf, lam, 0.0, 0.0
        for i in range(6):
            lm.d[i] = 0.0
        _one_unit(solver, _PH_LM_STEPS)
        if ok_ref:
            assert list(lm.d) == list(x_ref), trial
        else:
            assert list(lm.d) == [0.0] * 6 and st[2] == lam * 10.0, trial


def _pose_cases(rng):
    """(p, R) of ordinary poses and the reference's edge cases: on a coil axis, near the
    source (1.5 radii), far (2 m), and rotations near pi."""
    cases = [((0.3, 0.0, 0.0), np.eye(3)), ((0.0, 0.0, 0.25), np.eye(3)), ((0.0, -0.4, 0.0), np.eye(3)),
             ((0.08, 0.02, -0.01), Rotation.from_rotvec([0, 0, math.pi - 1e-9]).as_matrix()),
             ((2.0, 0.5, -0.3), Rotation.from_rotvec([math.pi, 0, 0]).as_matrix())]
    for _ in range(40):
        u = rng.normal(size=3)
        cases.append((tuple(u / np.linalg.norm(u) * rng.uniform(0.1, 0.8)),
                      Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()))
    return cases


@pytest.mark.parametrize("coils,model", [(ORTHO, "exact"), (ORTHO, "dipole"), (SKEWED, "exact")])
def test_cost_and_normal_equations_bit_identical(coils, model):
    """ct_pose_cost (through the LM's start, one compiled unit of the solve) against
    _PoseFit._cost: cost, the 36 entries of H^T W H and the 6 of H^T W (S - h), on 45 poses with
    random signals and weights spread over four decades (a weight of 1e-12 makes the normal matrix
    nearly singular)."""
    rng = np.random.default_rng(5)
    s = PoseSolver(coils, model, core=core.load("compiled"))
    n = len(coils)
    for p, R in _pose_cases(rng):
        s._S[:] = rng.normal(0.0, 1e-5, (n, 3))
        s._w[:] = 10.0 ** rng.uniform(6, 10, (n, 3))
        if rng.random() < 0.3:
            s._w[0, :] = 1e-12
        s._cur[:] = rng.uniform(-2, 2, n)
        s._fit.set(p, R)
        s._lm_py.start(s._fit)
        _one_unit(s, _PH_LM_START)
        assert s._lm_c.cost == s._lm_py.cost
        assert list(s._lm_c.A) == list(s._lm_py.A)
        assert list(s._lm_c.g) == list(s._lm_py.g)


def _signals(coils, model, p, R, cur, rng, noise):
    gen = PoseSolver(coils, model, core=core.PYTHON)
    h = memoryview(np.zeros(3 * len(coils)))
    gen.signal.predict(p[0], p[1], p[2], R, cur, h)
    return np.array(h).reshape(len(coils), 3).T + rng.normal(0.0, noise, (3, len(coils)))


def _same(ref, got, st_ref, st_got, case):
    assert st_got == st_ref, case
    np.testing.assert_array_equal(got.position, ref.position, err_msg=str(case))
    np.testing.assert_array_equal(got.rotation, ref.rotation, err_msg=str(case))
    np.testing.assert_array_equal(got.covariance, ref.covariance, err_msg=str(case))
    assert (got.iterations, got.cost, got.converged) == (ref.iterations, ref.cost, ref.converged), case
    assert got.signal.evals == ref.signal.evals, case


@pytest.mark.parametrize("coils,model,step_sigma", [(ORTHO, "exact", 0.0), (ORTHO, "dipole", 0.0),
                                                    (SKEWED, "exact", 0.0), (ORTHO, "exact", 0.05)])
def test_whole_solves_bit_identical(coils, model, step_sigma):
    """Whole solves, warm (x0 off by 1 cm and 3 deg, and by 30 cm and 60 deg: the LM climbs its
    damping and may fall back to acquisition) and cold, with the sensor on a coil axis among the
    poses: the same status, pose, covariance, iteration count, cost and evaluations on both
    cores. ``step_sigma``: the metric stop (``_metric2``) in play."""
    rng = np.random.default_rng(9)
    n = len(coils)
    ref = PoseSolver(coils, model, step_sigma=step_sigma, core=core.PYTHON)
    got = PoseSolver(coils, model, step_sigma=step_sigma, core=core.load("compiled"))
    sigma = np.full((3, n), 2e-9)
    for k, (p, R) in enumerate(_pose_cases(rng)[:25]):
        cur = rng.uniform(0.5, 2.0, n)
        S = _signals(coils, model, p, R, cur, rng, 2e-9)
        off = (0.01, 0.05) if k % 3 else (0.3, 1.0)
        x0p = np.asarray(p) + rng.normal(0.0, off[0], 3)
        x0R = R @ Rotation.from_rotvec(rng.normal(0.0, off[1], 3)).as_matrix()
        for args in ((x0p, x0R), (None, None)):
            st_ref = ref.solve(S, cur, sigma, None, *args)
            st_got = got.solve(S, cur, sigma, None, *args)
            _same(ref, got, st_ref, st_got, (k, args[0] is None))


def test_iteration_limit_and_bad_input_bit_identical():
    """One LM step allowed (stopped, not converged) and a non-finite x0 (refused): the same on
    both cores."""
    rng = np.random.default_rng(2)
    ref = PoseSolver(ORTHO, "exact", iters=1, core=core.PYTHON)
    got = PoseSolver(ORTHO, "exact", iters=1, core=core.load("compiled"))
    p, R = (0.2, 0.1, -0.15), Rotation.from_rotvec([0.2, -0.4, 1.0]).as_matrix()
    S = _signals(ORTHO, "exact", p, R, np.ones(3), rng, 1e-9)
    sigma = np.full((3, 3), 1e-9)
    x0p = np.array(p) + 0.02
    _same(ref, got, ref.solve(S, np.ones(3), sigma, None, x0p, R), got.solve(S, np.ones(3), sigma, None, x0p, R),
          "iters=1")
    assert not got.converged
    bad = x0p.copy()
    bad[1] = math.nan
    assert ref.solve(S, np.ones(3), sigma, None, bad, R) == got.solve(S, np.ones(3), sigma, None, bad, R) \
        == SOLVE_BAD_INPUT


def test_distortion_map_runs_the_python_lm_and_stays_equal():
    """With the room's distortion map in the signal model (added in Python between the compiled
    fields and projection) the solver runs the Python LM on its compiled signal model: the same
    result as the Python core."""
    dm = DistortionMap([[[0.05, 0.02, -1.1]], [[0.1, 0.0, -1.2]], [[-0.2, 0.3, -1.0]]],
                       [[[-0.08, 0.01, -0.005]], [[0.0, -0.1, -0.004]], [[0.0, -0.04, 0.18]]])
    rng = np.random.default_rng(4)
    ref = PoseSolver(ORTHO, "exact", core=core.PYTHON)
    got = PoseSolver(ORTHO, "exact", core=core.load("compiled"))
    ref.signal.set_distortion(dm)
    got.signal.set_distortion(dm)
    p, R = (0.25, -0.1, 0.05), Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    S = _signals(ORTHO, "exact", p, R, np.ones(3), rng, 1e-9)
    sigma = np.full((3, 3), 1e-9)
    _same(ref, got, ref.solve(S, np.ones(3), sigma, None, np.array(p), R),
          got.solve(S, np.ones(3), sigma, None, np.array(p), R), "distortion")
    assert got._lm is got._lm_py


@pytest.mark.skipif(not available(), reason="needs numpy's allocation hook")
def test_compiled_warm_solve_allocates_no_array():
    """A warm solve on the compiled LM allocates no numpy array."""
    rng = np.random.default_rng(8)
    s = PoseSolver(ORTHO, "exact", core=core.load("compiled"))
    p, R = (0.2, 0.1, -0.15), Rotation.from_rotvec([0.2, -0.4, 1.0]).as_matrix()
    S = _signals(ORTHO, "exact", p, R, np.ones(3), rng, 1e-9)
    sigma, cur, x0p = np.full((3, 3), 1e-9), np.ones(3), np.array(p) + 0.01
    s.solve(S, cur, sigma, None, x0p, R)
    with NumpyAllocationCounter() as c:
        for _ in range(5):
            s.solve(S, cur, sigma, None, x0p, R)
    assert c.count == 0
