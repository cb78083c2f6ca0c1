"""The allocation-free PoseSolver against the functional reference solve.solve_pose,
and the small linear algebra it is built on."""
import math

import numpy as np
import pytest

from coiltrack.firmware.model.field import Coil, orthogonal_source
from coiltrack.firmware.linalg import (Rot3, chol_inverse, chol_solve, cholesky, exp_rotvec, flat, jacobi_eigh,
                                       lu_factor, lu_solve,
                                       nearest_rotation, rotvec_from_matrix)
from coiltrack.firmware.pose.reference import kuipers, measurement_model, solve_pose
from coiltrack.firmware.pose.reference import so3_exp
from coiltrack.firmware.pose.solver import (SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_NOT_CONVERGED, SOLVE_OK,
                                            SOLVE_REACQUIRED, SOLVE_RUNNING, PoseSolver)
from coiltrack.tools.bench.alloc import NumpyAllocationCounter

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


def test_nearest_rotation_fast_path_only_for_proper_rotations():
    """A rotation (to rounding) is copied; one off by 1e-9, a reflection, a NaN matrix and the
    identity's negative go through the projection (against the SVD's to 1e-12). Catches a
    tolerance so loose that a drifted matrix is returned unprojected, or a missing det check."""
    rng = np.random.default_rng(4)
    work = Rot3()
    out = np.zeros((3, 3))
    R = random_rotation(rng)
    nearest_rotation(R.reshape(9), out, work)
    assert np.array_equal(out, R)
    M = R + 1e-9 * rng.normal(size=(3, 3))
    U, _, Vt = np.linalg.svd(M)
    nearest_rotation(M.reshape(9), out, work)
    np.testing.assert_allclose(out, U @ Vt, atol=1e-12)
    assert not np.array_equal(out, M)
    for M in (R @ np.diag([1.0, 1.0, -1.0]), -np.eye(3)):      # reflections: a proper rotation comes out
        nearest_rotation(M.reshape(9), out, work)
        np.testing.assert_allclose(out.T @ out, np.eye(3), atol=1e-12)
        assert np.linalg.det(out) > 0.0
    M = R.copy()
    M[1, 2] = np.nan
    nearest_rotation(M.reshape(9), out, work)          # the projection's path: NaN stays visible
    assert not np.isfinite(out).all()


def test_lu_solve_matches_numpy_on_unsymmetric_matrices():
    """Against numpy.linalg.solve to 1e-10 (relative), including a matrix whose first pivot is zero:
    catches a missing row swap or a permutation applied to the wrong side; a singular matrix is refused."""
    rng = np.random.default_rng(5)
    for k in range(20):
        A = rng.normal(size=(6, 6))
        if k == 0:
            A[0, 0] = 0.0
        b = rng.normal(size=6)
        K, perm, e, y = list(A.reshape(36)), [0] * 6, list(b), [0.0] * 6
        assert lu_factor(K, 6, perm)
        lu_solve(K, 6, perm, e, y)
        np.testing.assert_allclose(e, np.linalg.solve(A, b), rtol=1e-10, atol=1e-12)
    S = np.ones((6, 6))
    assert not lu_factor(list(S.reshape(36)), 6, [0] * 6)


def test_exp_rotvec_of_a_diverged_step_is_nan_not_an_exception():
    """A step of infinite angle (a solve run away from a diverged warm start) must give NaN for the
    solver's finiteness check, not raise 'math domain error' inside the tick (it did, on a body-worn run
    without eq 6.8)."""
    R = np.zeros((3, 3))
    exp_rotvec(1e200, 0.0, 0.0, R)
    assert np.isnan(R).any()
    exp_rotvec(0.3, -0.2, 0.1, R)
    assert np.all(np.isfinite(R))


#: the reference's stopping tolerances (the firmware's default stops at noise level)
TIGHT = dict(step_tol=1e-9, cost_tol=1e-12)


# ------------------------------------------------------------------ solver
@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_pose_solver_matches_solve_pose(model):
    """Same start (Kuipers, near-field refinement), same LM, same covariance:
    with the reference's stopping tolerances the two agree to them (1e-9
    relative); with the firmware's default noise-level ones (1e-5 relative
    step, 1e-6 relative cost) to within 2 % of the solution's own position
    standard deviation, which is what stopping at noise level means."""
    rng = np.random.default_rng(7 if model == "exact" else 8)
    ps = PoseSolver(COILS, model, step_tol=1e-9, cost_tol=1e-12)
    fast = PoseSolver(COILS, model)
    hemi = np.array([1.0, 0.0, 0.0])
    sig = np.full((3, 3), 2e-8)
    for _ in range(60):
        p, R = random_pose(rng, 0.08, 0.9)
        S = measurement_model(p, R, COILS, CUR, model) + rng.normal(0.0, 2e-8, (3, 3))
        pr, Rr, cr = solve_pose(S, COILS, CUR, sig, hemisphere=hemi, model=model)
        assert ps.solve(S, CUR, sig, hemi) & ~4 == SOLVE_OK
        assert np.linalg.norm(ps.position - pr) <= 1e-7 * np.linalg.norm(pr)
        assert fast.solve(S, CUR, sig, hemi) & ~4 == SOLVE_OK
        assert np.linalg.norm(fast.position - pr) <= 0.02 * math.sqrt(np.trace(cr[:3, :3]))
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
    acq.next_unit()                     # M^+
    acq.next_unit()                     # Kuipers position
    acq.next_unit()                     # Kuipers orientation; the dipole model stops there
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


# ------------------------------------------------------- staged solving
def _cases():
    """(S, hemisphere, x0) covering every stage: far field (Kuipers + LM),
    near field (invariant fit, grid search), warm start, warm start that
    falls back to acquisition."""
    rng = np.random.default_rng(21)
    hemi = np.array([1.0, 0.0, 0.0])
    out = []
    for r in (0.09, 0.12, 0.3, 0.7):
        p = r * np.array([0.8, 0.5, -0.33]) / np.linalg.norm([0.8, 0.5, -0.33])
        R = random_rotation(rng)
        S = measurement_model(p, R, COILS, CUR) + rng.normal(0.0, 2e-8, (3, 3))
        out.append((S, hemi, None))
        out.append((S, None, (p + 0.002, R @ so3_exp([0.01, -0.02, 0.01]))))
        out.append((S, hemi, (-p, R)))                 # mirror: falls back
    # near the source where the invariant fit misses: the grid search
    rng = np.random.default_rng(23)
    p = 0.1 * np.array([0.9, 0.4, -0.2]) / np.linalg.norm([0.9, 0.4, -0.2])
    R = random_rotation(rng)
    out.append((measurement_model(p, R, COILS, CUR) + rng.normal(0.0, 2e-8, (3, 3)), hemi, None))
    return out


def _result(ps):
    return (ps.status, ps.position.tobytes(), ps.rotation.tobytes(), ps.covariance.tobytes(),
            ps.cost, ps.iterations, ps.solve_evals)


SIG = np.full((3, 3), 2e-8)


def _run(ps, S, hemi, x0, budget):
    x0p, x0R = x0 if x0 is not None else (None, None)
    st = ps.begin(S, CUR, SIG, hemi, x0p, x0R)
    steps = []
    while st == SOLVE_RUNNING:
        st = ps.step(budget)
        steps.append(ps.evals_last_step)
    return st, steps


@pytest.mark.parametrize("budget", [1, 3, 7, 9, 20, 50])
def test_a_resumed_solve_equals_the_uninterrupted_one_bit_for_bit(budget):
    """Any budget splits the same units differently and nothing else: a
    unit that kept state in a local variable across steps, or re-evaluated
    on resumption, changes the bits (or the evaluation count)."""
    ps = PoseSolver(COILS, "exact")
    ref = PoseSolver(COILS, "exact")
    for S, hemi, x0 in _cases():
        x0p, x0R = x0 if x0 is not None else (None, None)
        ref.solve(S, CUR, np.full((3, 3), 2e-8), hemi, x0p, x0R)
        st, steps = _run(ps, S, hemi, x0, budget)
        assert st == ref.status and _result(ps) == _result(ref)
        assert sum(steps) == ref.solve_evals
    assert ref.solve_evals > 1000                # the last case went through the grid search


@pytest.mark.parametrize("budget", [1, 2, 3, 5, 9, 12, 30])
def test_no_step_exceeds_its_budget_and_none_stops_early(budget):
    """At most ``budget`` evaluations per step, except one unit (n = 3
    evaluations) alone when the budget is smaller; and a step stops only
    when the next unit would not fit: each unit is charged n, closed forms
    included (at most four of those, which evaluate nothing, share a
    step), so a full step does more than ``budget - 2 - 4 n`` evaluations."""
    ps = PoseSolver(COILS, "exact")
    ps.reset_step_stats()
    n = 3
    for S, hemi, x0 in _cases():
        _, steps = _run(ps, S, hemi, x0, budget)
        assert all(0 <= e <= max(budget, n) for e in steps)
        assert all(e > budget - 2 - 4 * n for e in steps[:-1])
        assert ps.max_evals_per_step >= max(steps)
    assert ps.max_evals_per_step == max(budget - budget % n, n)


def test_predict_between_steps_does_not_change_the_solve():
    ps = PoseSolver(COILS, "exact")
    ref = PoseSolver(COILS, "exact")
    out = np.zeros((3, 3))
    sig = np.full((3, 3), 2e-8)
    for S, hemi, x0 in _cases()[:6]:
        x0p, x0R = x0 if x0 is not None else (None, None)
        ref.solve(S, CUR, sig, hemi, x0p, x0R)
        st = ps.begin(S, CUR, sig, hemi, x0p, x0R)
        while st == SOLVE_RUNNING:
            ps.predict_signals(np.array([0.2, 0.1, 0.0]), np.eye(3), 2.0 * CUR, out)
            st = ps.step(6)
        assert _result(ps)[:6] == _result(ref)[:6]


def test_begin_and_steps_allocate_no_numpy_array():
    ps = PoseSolver(COILS, "exact")
    cases = _cases()
    for S, hemi, x0 in cases:
        _run(ps, S, hemi, x0, 8)
    counter = NumpyAllocationCounter()
    with counter:
        for S, hemi, x0 in cases:
            _run(ps, S, hemi, x0, 8)
            _run(ps, S, hemi, x0, 1)
    assert counter.count == 0


# ------------------------------------------------------------ warm start
def test_warm_start_near_the_truth_is_the_cold_solution_in_fewer_evaluations():
    """From the tracked pose (the solution of the previous frame, the sensor
    moved by 0.5 mm and 0.2 deg since), the LM alone reaches the cold
    solution. Near the source (< 4 coil radii) acquisition fits the
    invariants and may search a grid, and the warm start is cheaper in every
    case; farther out the Kuipers start is about as close as the tracked pose
    and the warm start costs at most one LM step (n evaluations) more."""
    rng = np.random.default_rng(22)
    ps = PoseSolver(COILS, "exact", **TIGHT)        # converged to the rounding level: same minimum
    sig = np.full((3, 3), 2e-8)
    hemi = np.array([1.0, 0.0, 0.0])
    total_cold = total_warm = 0
    for k in range(16):
        p, R = random_pose(rng, 0.09, 0.2) if k % 2 else random_pose(rng, 0.25, 0.6)
        S = measurement_model(p, R, COILS, CUR) + rng.normal(0.0, 2e-8, (3, 3))
        assert ps.solve(S, CUR, sig, hemi) == SOLVE_OK
        pc, Rc, cold = ps.position.copy(), ps.rotation.copy(), ps.solve_evals
        d = rng.normal(size=3)
        x0p = pc + 5e-4 * d / np.linalg.norm(d)
        x0R = Rc @ so3_exp(rng.normal(size=3) * 0.002)
        assert ps.solve(S, CUR, sig, hemi, x0p, x0R) == SOLVE_OK        # no SOLVE_REACQUIRED
        assert ps.solve_evals < cold if k % 2 else ps.solve_evals <= cold + 3
        total_cold += cold
        total_warm += ps.solve_evals
        assert np.linalg.norm(ps.position - pc) <= 1e-8 * np.linalg.norm(pc)
        np.testing.assert_allclose(ps.rotation, Rc, atol=1e-8)
    assert total_warm < 0.6 * total_cold


def test_warm_start_on_the_mirror_or_far_away_falls_back_and_finds_the_truth():
    """The mirror pose (-p, R) fits the signals exactly as well (B(-p) =
    B(p) for co-centred coils), so only the hemisphere test catches it; a
    far start (90 deg away, orientation 1.5 rad off) either converges to
    the truth by itself or ends beyond the gate or unconverged and is
    reacquired. Every case ends at the cold solution."""
    rng = np.random.default_rng(23)
    ps = PoseSolver(COILS, "exact", **TIGHT)        # converged to the rounding level: same minimum
    sig = np.full((3, 3), 2e-8)
    hemi = np.array([1.0, 0.0, 0.0])
    far_reacquired = 0
    for r in (0.1, 0.25, 0.6):
        p = r * np.array([0.9, 0.4, -0.2]) / np.linalg.norm([0.9, 0.4, -0.2])
        R = random_rotation(rng)
        S = measurement_model(p, R, COILS, CUR) + rng.normal(0.0, 2e-8, (3, 3))
        ps.solve(S, CUR, sig, hemi)
        pc = ps.position.copy()
        st = ps.solve(S, CUR, sig, hemi, -p, R)
        assert st == SOLVE_REACQUIRED
        assert np.linalg.norm(ps.position - pc) <= 1e-8 * r
        far = r * np.array([-0.2, 0.9, 0.4]) / np.linalg.norm([-0.2, 0.9, 0.4])
        st = ps.solve(S, CUR, sig, hemi, far, R @ so3_exp([1.5, 0.0, 0.0]))
        assert st & ~SOLVE_REACQUIRED == SOLVE_OK
        far_reacquired += bool(st & SOLVE_REACQUIRED)
        assert np.linalg.norm(ps.position - pc) <= 1e-8 * r
        # without a hemisphere the mirror is a valid answer: no fallback
        assert ps.solve(S, CUR, sig, None, -p, R) == SOLVE_OK
        np.testing.assert_allclose(ps.position, -pc, atol=1e-6 * r)
    assert far_reacquired == 2                  # 0.1 m and 0.6 m; at 0.25 m the LM finds it alone
    # 3 deg beyond the hemisphere plane is within its margin: the warm result stands
    p = 0.3 * np.array([-0.05, 0.9, 0.4]) / np.linalg.norm([-0.05, 0.9, 0.4])
    R = random_rotation(rng)
    S = measurement_model(p, R, COILS, CUR) + rng.normal(0.0, 2e-8, (3, 3))
    assert ps.solve(S, CUR, sig, hemi, p, R) == SOLVE_OK
    pw = ps.position.copy()
    assert ps.solve(S, CUR, sig, None, p, R) == SOLVE_OK
    np.testing.assert_array_equal(ps.position, pw)
    assert pw @ hemi < 0.0


def test_warm_start_beyond_the_chi_square_gate_is_reacquired():
    """Signals 30 sigma off the model (a disturbed frame) converge from the
    truth but fail the chi-square gate (3 dof, p = 0.999: 16.27), so the
    solver reacquires; a gate of probability 1 accepts the warm result."""
    rng = np.random.default_rng(24)
    p, R = np.array([0.3, 0.1, -0.05]), random_rotation(rng)
    S = measurement_model(p, R, COILS, CUR)
    S[1, 2] += 30 * 2e-8
    sig = np.full((3, 3), 2e-8)
    gated = PoseSolver(COILS, "exact")
    st = gated.solve(S, CUR, sig, None, p, R)
    assert st & SOLVE_REACQUIRED and gated.cost > gated.gate
    assert gated.gate == pytest.approx(16.2662)
    open_gate = PoseSolver(COILS, "exact", gate_probability=1.0)
    assert open_gate.solve(S, CUR, sig, None, p, R) == SOLVE_OK


def test_begin_rejects_bad_arguments_before_any_work():
    ps = PoseSolver(COILS, "exact")
    S = measurement_model(np.array([0.3, 0.0, 0.0]), np.eye(3), COILS, CUR)
    sig = np.full((3, 3), 1e-8)
    bad_hemi = np.array([np.nan, 0.0, 0.0])
    assert ps.begin(S, CUR, sig, bad_hemi) == SOLVE_BAD_INPUT
    assert ps.begin(S, CUR, sig, x0_position=np.zeros(3)) == SOLVE_BAD_INPUT          # no rotation
    assert ps.begin(S, CUR, sig, x0_position=np.full(3, np.inf), x0_rotation=np.eye(3)) == SOLVE_BAD_INPUT
    assert ps.begin(S[:, :2], CUR, sig) == SOLVE_BAD_INPUT
    assert ps.begin(S, CUR[:2], sig) == SOLVE_BAD_INPUT
    assert ps.step(100) == SOLVE_BAD_INPUT and ps.evals_last_step == 0
    assert ps.signal.evals == 0
    assert ps.begin(S, CUR, sig) == SOLVE_RUNNING
    while ps.step(4) == SOLVE_RUNNING:
        pass
    assert ps.status & ~SOLVE_NOT_CONVERGED == SOLVE_OK
    out = np.zeros(6)
    ps.cov_diag(out)
    np.testing.assert_array_equal(out, np.diag(ps.covariance))
