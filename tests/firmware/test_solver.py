"""The allocation-free PoseSolver against the functional reference solve.solve_pose,
and the small linear algebra it is built on."""
import math

import numpy as np
import pytest

from coiltrack.firmware.model.field import Coil, orthogonal_source
from coiltrack.firmware.linalg import (Rot3, chol_inverse, chol_solve, cholesky, exp_rotvec, flat, jacobi_eigh,
                                nearest_rotation, rotvec_from_matrix)
from coiltrack.firmware.pose.reference import kuipers, measurement_model, solve_pose
from coiltrack.firmware.pose.solver import SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_OK, PoseSolver
from coiltrack.tools.alloc import NumpyAllocationCounter

COILS = orthogonal_source(0.055, 50)
CUR = np.array([1.5, 1.49, 1.51])


def random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def random_pose(rng, rmin, rmax):
    u = rng.normal(size=3)
    u[0] = abs(u[0]) + 0.1
    u /= np.linalg.norm(u)
    return rng.uniform(rmin, rmax) * u, random_rotation(rng)


# ------------------------------------------------------------------ linalg
def test_small_linear_algebra_matches_numpy():
    rng = np.random.default_rng(0)
    for n in (3, 4, 6, 9):
        A = rng.normal(size=(n, n))
        A = A @ A.T + n * np.eye(n)
        L = np.zeros((n, n))
        inv = np.zeros((n, n))
        assert chol_inverse(flat(A), n, flat(inv), flat(L))
        np.testing.assert_allclose(inv, np.linalg.inv(A), rtol=1e-12, atol=1e-14)
        assert cholesky(flat(A), n, flat(L))
        np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=1e-12, atol=1e-14)
        b = rng.normal(size=n)
        x = np.zeros(n)
        chol_solve(flat(L), n, memoryview(b), memoryview(x))
        np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-11)
        a = A.copy()
        w = np.zeros(n)
        V = np.zeros((n, n))
        jacobi_eigh(flat(a), n, memoryview(w), flat(V))
        np.testing.assert_allclose(w, np.linalg.eigvalsh(A), rtol=1e-12)
        np.testing.assert_allclose(V @ np.diag(w) @ V.T, A, rtol=1e-11, atol=1e-11)
    not_pd = -np.eye(3)
    assert not chol_inverse(flat(not_pd), 3, flat(np.zeros((3, 3))), flat(np.zeros((3, 3))))


def test_nearest_rotation_equals_svd_projection_and_rotvec_roundtrip():
    rng = np.random.default_rng(1)
    work = Rot3()
    out = np.zeros((3, 3))
    for _ in range(50):
        M = random_rotation(rng) + 0.3 * rng.normal(size=(3, 3))
        U, _, Vt = np.linalg.svd(M)
        if np.linalg.det(U) * np.linalg.det(Vt) < 0:
            U[:, 2] = -U[:, 2]
        nearest_rotation(M.reshape(9), out, work)
        np.testing.assert_allclose(out, U @ Vt, atol=1e-12)
    for angle in (1e-9, 1e-3, 0.5, 2.0, math.pi - 1e-6):
        w = rng.normal(size=3)
        w *= angle / np.linalg.norm(w)
        R = np.zeros((3, 3))
        exp_rotvec(*w, R)
        back = np.array(rotvec_from_matrix(*R.reshape(9)))
        np.testing.assert_allclose(back, w, atol=1e-9)


# ------------------------------------------------------------------ solver
@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_pose_solver_matches_solve_pose(model):
    """Same start (Kuipers, near-field refinement), same LM, same covariance:
    the two agree to the LM's own stopping tolerance (1e-9 relative)."""
    rng = np.random.default_rng(7 if model == "exact" else 8)
    ps = PoseSolver(COILS, model)
    hemi = np.array([1.0, 0.0, 0.0])
    sig = np.full((3, 3), 2e-8)
    for _ in range(60):
        p, R = random_pose(rng, 0.08, 0.9)
        S = measurement_model(p, R, COILS, CUR, model) + rng.normal(0.0, 2e-8, (3, 3))
        pr, Rr, cr = solve_pose(S, COILS, CUR, sig, hemisphere=hemi, model=model)
        assert ps.solve(S, CUR, sig, hemi) & ~4 == SOLVE_OK
        assert np.linalg.norm(ps.position - pr) <= 1e-7 * np.linalg.norm(pr)
        np.testing.assert_allclose(ps.rotation, Rr, atol=1e-7)
        np.testing.assert_allclose(ps.covariance, cr, rtol=1e-5, atol=1e-6 * np.abs(cr).max())


def test_pose_solver_near_field_and_x0_and_non_orthogonal_source():
    rng = np.random.default_rng(3)
    # near the source the invariant refinement / grid search decide the start
    ps = PoseSolver(COILS, "exact")
    for _ in range(10):
        p, R = random_pose(rng, 0.09, 0.2)
        S = measurement_model(p, R, COILS, CUR)
        pr, Rr, _ = solve_pose(S, COILS, CUR, 1e-9)
        ps.solve(S, CUR, np.full((3, 3), 1e-9))
        np.testing.assert_allclose(ps.position, pr, atol=1e-8)
        np.testing.assert_allclose(ps.position, p, atol=1e-6)
    # four tilted, offset coils, started from x0
    coils = [Coil((0.0, 0.0, 0.0), (1, 0, 0), 0.05, 40), Coil((0.01, 0, 0), (0, 1, 0.2), 0.05, 40),
             Coil((0, 0.01, 0), (0.1, 0, 1), 0.04, 60), Coil((0, 0, 0.01), (1, 1, 1), 0.05, 40)]
    cur = np.array([1.0, 1.2, 0.9, 1.1])
    ps4 = PoseSolver(coils, "exact")
    p, R = np.array([0.3, 0.1, -0.05]), random_rotation(rng)
    S = measurement_model(p, R, coils, cur)
    sig = np.full((3, 4), 1e-9)
    x0p, x0R = p + 0.01, R
    pr, Rr, cr = solve_pose(S, coils, cur, sig, x0=(x0p, x0R))
    ps4.solve(S, cur, sig, x0_position=x0p, x0_rotation=x0R)
    np.testing.assert_allclose(ps4.position, pr, atol=1e-9)
    np.testing.assert_allclose(ps4.rotation, Rr, atol=1e-9)
    # Kuipers start with four coils as well
    ps4.solve(S, cur, sig)
    np.testing.assert_allclose(ps4.position, p, atol=1e-7)


def test_kuipers_start_matches_reference_closed_form():
    rng = np.random.default_rng(5)
    p, R = np.array([0.5, 0.2, -0.1]), random_rotation(rng)
    m = COILS[0].moment_magnitude(1.5)
    S = measurement_model(p, R, COILS, np.full(3, 1.5), "dipole")
    kp, kR = kuipers(S, m)
    ps = PoseSolver(COILS, "dipole")
    acq = ps._acq
    ps._cur[:] = 1.5
    ps._S[:] = S.T                      # the solver's layout: [coil, component]
    acq.begin(1.0, 0.0, 0.0, 1e-9)
    acq.next_unit()                     # the Kuipers unit; the dipole model stops there
    assert acq.finished and acq.ok and ps.signal.evals == 0
    np.testing.assert_allclose(acq.p, kp, atol=1e-12)
    np.testing.assert_allclose(acq.R, kR, atol=1e-10)


def test_bad_input_is_reported_not_raised():
    ps = PoseSolver(COILS, "exact")
    S = measurement_model(np.array([0.3, 0.0, 0.0]), np.eye(3), COILS, CUR)
    bad = S.copy()
    bad[0, 0] = np.nan
    assert ps.solve(bad, CUR, np.full((3, 3), 1e-8)) == SOLVE_BAD_INPUT
    assert ps.solve(S, CUR, np.zeros((3, 3))) == SOLVE_BAD_INPUT
    two = PoseSolver(COILS[:2], "exact")
    assert two.solve(S[:, :2], CUR[:2], np.full((3, 2), 1e-8)) == SOLVE_NO_START


def test_solve_allocates_no_numpy_array():
    ps = PoseSolver(COILS, "exact")
    hemi = np.array([1.0, 0.0, 0.0])
    sig = np.full((3, 3), 2e-8)
    out = np.zeros((3, 3))
    counter = NumpyAllocationCounter()
    rng = np.random.default_rng(2)
    cases = [measurement_model(*random_pose(rng, 0.1, 0.8), COILS, CUR) for _ in range(8)]
    ps.solve(cases[0], CUR, sig, hemi)
    with counter:
        for S in cases:
            ps.solve(S, CUR, sig, hemi)
            ps.solve(S, CUR, sig, x0_position=ps.position, x0_rotation=ps.rotation)
            ps.predict_signals(ps.position, ps.rotation, CUR, out)
    assert counter.count == 0
