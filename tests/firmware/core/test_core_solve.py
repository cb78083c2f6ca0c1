"""The pose solve's warm path in two compiled calls (firmware_py/core/src/solve.c, py_solve.c)
against its Python reference (pose/solver.py PoseSolver.begin with _load, _load_hemisphere and
_load_x0; the units _unit_lm_start, _unit_lm_step and _unit_finish run by staged.run_units;
pose/staged.py StagedSolve.predict_signals).

The C does the same floating-point operations in the same order (-ffp-contract=off), so every
comparison with the reference is bit for bit: status, position, rotation, covariance,
iterations, cost and the evaluations and charges of every budgeted step, through cold starts
(the acquisition's units in the compiled run too, test_core_acquire.py), warm starts that fail their checks and fall
back to it, refused inputs and a model with a distortion map (the Python's way). The predicted
signals are also checked against pose.reference.measurement_model (numpy, 1e-12 relative).
Seeded; skips without the extension."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.model.distortion import DistortionMap
from coiltrack.firmware.model.field import Coil, orthogonal_source
from coiltrack.firmware.pose.reference import measurement_model
from coiltrack.firmware.pose.solver import SOLVE_BAD_INPUT, SOLVE_REACQUIRED, SOLVE_RUNNING, PoseSolver
from coiltrack.firmware.pose.staged import SolveResult
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
ORTHO = orthogonal_source(0.055, 50)
SKEWED = [Coil([0.01, 0, 0], [1, 0.2, 0], 0.05, 40), Coil([0, 0.012, 0], [0, 1, 0.3], 0.06, 50),
          Coil([0, 0, 0.01], [0.1, 0, 1], 0.055, 45), Coil([-0.01, 0, 0], [1, 1, 1], 0.04, 30)]


def _pair(coils, **kw):
    ref = PoseSolver(coils, "exact", core=core.PYTHON, **kw)
    got = PoseSolver(coils, "exact", core=COMPILED, **kw)
    assert got.begin.__func__ is PoseSolver._begin_compiled and got._run.__func__ is PoseSolver._run_compiled
    return ref, got


def _signals(coils, p, R, cur, rng, noise, model="exact"):
    """The (3, n) signals of ``coils`` at pose ``(p, R)`` with currents ``cur`` (the reference's
    signal model ``model``), plus Gaussian noise of std ``noise``."""
    gen = PoseSolver(coils, model, core=core.PYTHON)
    h = memoryview(np.zeros(3 * len(coils)))
    gen.signal.predict(p[0], p[1], p[2], R, cur, h)
    return np.array(h).reshape(len(coils), 3).T + rng.normal(0.0, noise, (3, len(coils)))


def _run(s, args, budgets):
    st = s.begin(*args)
    trace = [st]
    k = 0
    while st == SOLVE_RUNNING:
        st = s.step(budgets[k % len(budgets)])
        trace.append((st, s.evals_last_step, s.units_last, s.signal.evals))
        k += 1
    return trace


def _same(ref, got, args, budgets, case):
    tr_ref, tr_got = _run(ref, args, budgets), _run(got, args, budgets)
    assert tr_got == tr_ref, case
    np.testing.assert_array_equal(got.position, ref.position, err_msg=str(case))
    np.testing.assert_array_equal(got.rotation, ref.rotation, err_msg=str(case))
    np.testing.assert_array_equal(got.covariance, ref.covariance, err_msg=str(case))
    assert (got.iterations, got.cost, got.converged, got.status, got.solve_evals) == \
        (ref.iterations, ref.cost, ref.converged, ref.status, ref.solve_evals), case
    return ref.status


@pytest.mark.parametrize("coils", [ORTHO, SKEWED, ORTHO[:2]])
def test_warm_cold_and_reacquired_solves_bit_identical(coils):
    """Warm solves near the truth, far from it (the damping climbs, the checks fail and the solve
    falls back to the acquisition, then to the compiled LM again), on the wrong side of the
    hemisphere, with an outlier the gate refuses, and cold ones, each stepped at budgets of 1, 3,
    9, 27 evaluations and a mix; a two-coil solver (no acquisition to fall back to): every step's
    status, evaluations and charges and the results are the reference's."""
    rng = np.random.default_rng(30)
    n = len(coils)
    ref, got = _pair(coils)
    sigma = np.full((3, n), 2e-9)
    statuses = set()
    for k in range(20):
        u = rng.normal(size=3)
        p = u / np.linalg.norm(u) * rng.uniform(0.15, 0.6)
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        cur = rng.uniform(0.5, 2.0, n)
        S = _signals(coils, p, R, cur, rng, 2e-9)
        if k % 5 == 4:
            S[1, 0] += 1e-6                                  # an outlier: the gate fails
        off = (0.01, 0.05) if k % 3 else (0.3, 1.0)
        x0p = p + rng.normal(0.0, off[0], 3)
        x0R = R @ Rotation.from_rotvec(rng.normal(0.0, off[1], 3)).as_matrix()
        hemi = (-p if k % 4 == 1 else p) / np.linalg.norm(p)
        budgets = ((1,), (3,), (9,), (27,), (9, 3, 27))[k % 5]
        for args in ((S, cur, sigma, hemi, x0p, x0R), (S, cur, sigma, None, x0p, x0R), (S, cur, sigma, hemi)):
            statuses.add(_same(ref, got, args, budgets, (k, len(args), budgets)))
    if n >= 3:
        assert any(s & SOLVE_REACQUIRED for s in statuses)


def test_refused_inputs_and_inputs_of_another_kind():
    """Non-finite signals, a sigma of zero, a non-finite hemisphere or warm start, a warm start
    given half: SOLVE_BAD_INPUT as the reference, nothing running after it; a hemisphere given as
    a tuple, the signals in a transposed view and a warm rotation that is no rotation (projected):
    the same solve as the reference (the begin the kernel does not take goes to the Python)."""
    rng = np.random.default_rng(31)
    ref, got = _pair(ORTHO)
    p, R = np.array([0.2, -0.15, 0.25]), Rotation.from_rotvec([0.4, -0.3, 1.1]).as_matrix()
    cur = np.array([1.0, 1.2, 0.8])
    S = _signals(ORTHO, p, R, cur, rng, 1e-9)
    sigma = np.full((3, 3), 1e-9)
    bad = []
    for i, (what, val) in enumerate((("S", math.nan), ("S", math.inf), ("sigma", 0.0), ("sigma", -1e-9),
                                     ("sigma", math.nan), ("cur", math.nan))):
        S2, sg2, c2 = S.copy(), sigma.copy(), cur.copy()
        {"S": S2, "sigma": sg2, "cur": c2}[what].flat[i % 3] = val
        bad.append((S2, c2, sg2, p, p + 0.01, R))
    bad += [(S, cur, sigma, np.array([math.nan, 0.0, 1.0]), p + 0.01, R),
            (S, cur, sigma, p, np.array([0.1, math.inf, 0.0]), R),
            (S, cur, sigma, p, p + 0.01, np.where(np.eye(3) > 0, math.nan, R)),
            (S, cur, sigma, p, p + 0.01, None), (S, cur, sigma, p, None, R)]
    for k, args in enumerate(bad):
        assert _same(ref, got, args, (9,), ("bad", k)) == SOLVE_BAD_INPUT
        assert got.finished and got.status == SOLVE_BAD_INPUT
    skew = R @ np.diag([1.0, 1.0 + 1e-6, 1.0])               # not orthonormal: projected
    ST = np.asfortranarray(S)
    for k, args in enumerate(((S, cur, sigma, tuple(p), p + 0.01, R), (ST, cur, np.asfortranarray(sigma), p, p, R),
                              (S, list(cur), sigma, p, p, R), (S, cur, sigma, p, p + 0.005, skew))):
        _same(ref, got, args, (9, 3), ("kind", k))


def test_distortion_map_and_solving_ahead():
    """A model with a distortion map takes the Python LM (the compiled finish) and gives the
    reference's results; a finished solve saved and loaded (the tracker's solving ahead) brings
    back the same results and leaves nothing to run."""
    rng = np.random.default_rng(32)
    ref, got = _pair(ORTHO)
    p, R = np.array([0.25, 0.1, -0.2]), Rotation.from_rotvec([-0.5, 0.2, 0.7]).as_matrix()
    cur = np.ones(3)
    S = _signals(ORTHO, p, R, cur, rng, 1e-9)
    sigma = np.full((3, 3), 1e-9)
    _same(ref, got, (S, cur, sigma, p, p + 0.01, R), (9,), "plain")
    saved = SolveResult()
    got.save(saved)
    _same(ref, got, (S, cur, sigma, p), (9,), "cold")
    got.load(saved)
    assert got.finished and got.step(9) == saved.status
    np.testing.assert_array_equal(got.position, saved.position)
    dmap = DistortionMap([[(0.4, 0.1, -0.2)]] * 3, [[(1e-3, -2e-3, 5e-4)]] * 3)
    for sv in (ref, got):
        sv.signal.set_distortion(dmap)
    _same(ref, got, (S, cur, sigma, p, p + 0.01, R), (9,), "distortion")
    _same(ref, got, (S, cur, sigma, p), (9,), "distortion, cold")
    assert got._lm is got._lm_py


@pytest.mark.parametrize("coils", [ORTHO, SKEWED])
def test_predict_signals_bit_identical_and_against_numpy(coils):
    """StagedSolve.predict_signals compiled: the reference's signals to the bit (into a
    (3, n) array and into a transposed view, from memoryviews and arrays) and its evaluations
    counted; against pose.reference.measurement_model to 1e-12 relative."""
    rng = np.random.default_rng(33)
    n = len(coils)
    ref, got = _pair(coils)
    for k in range(12):
        u = rng.normal(size=3)
        p = u / np.linalg.norm(u) * rng.uniform(0.1, 0.8)
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        cur = rng.uniform(-2.0, 2.0, n)
        a, b = np.zeros((3, n)), np.zeros((n, 3)).T
        pv = memoryview(p.copy()) if k % 2 else p
        ref.predict_signals(pv, R, cur, a)
        got.predict_signals(pv, R, memoryview(cur) if k % 3 else cur, b)
        np.testing.assert_array_equal(b, a)
        assert got.signal.evals == ref.signal.evals
        want = measurement_model(p, R, coils, cur, "exact")
        np.testing.assert_allclose(b, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())


@pytest.mark.skipif(not available(), reason="numpy allocation counter unavailable")
def test_compiled_warm_solves_allocate_nothing():
    rng = np.random.default_rng(34)
    _, s = _pair(ORTHO)
    p, R = np.array([0.2, 0.1, 0.3]), np.eye(3)
    cur = np.ones(3)
    S = _signals(ORTHO, p, R, cur, rng, 1e-9)
    sigma = np.full((3, 3), 1e-9)
    out = np.zeros((3, 3))
    args = (S, cur, sigma, p, p + 0.01, R)
    _run(s, args, (9,))
    with NumpyAllocationCounter() as c:
        for _ in range(5):
            _run(s, args, (9,))
            s.predict_signals(p, R, cur, out)
    assert c.count == 0
