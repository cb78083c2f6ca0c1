"""The compiled end of a pulsed-DC solve and its grading (firmware_py/core/src/finish.c,
py_finish.c) against their Python references: linalg.jacobi_eigh, pose/covariance.py
RobustInverse6 and RotationMargin, pose/solver.py PoseSolver._unit_finish (the warm-start checks,
the covariance, the status), track/quality.py quality_from and PoseQuality.grade_burst.

The C does the same floating-point operations in the same order (-ffp-contract=off), so the
comparisons with the references are bit for bit. Independent references beside them: numpy's
eigh, inv and pinv, pose.reference._robust_inverse and rotation_margin (numpy's closed forms),
and the quality's motion term written here with numpy matrices (1e-9 relative: other sums).
Seeded; skips without the extension."""
import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.linalg import Rot3, jacobi_eigh, nearest_rotation
from coiltrack.firmware.model.distortion import DistortionMap
from coiltrack.firmware.model.field import Coil, orthogonal_source
from coiltrack.firmware.pose.covariance import MAX_VARIANCE, RobustInverse6, RotationMargin
from coiltrack.firmware.pose.reference import _robust_inverse, rotation_margin
from coiltrack.firmware.pose.solver import (SOLVE_NONFINITE, SOLVE_REACQUIRED, SOLVE_RUNNING, PoseSolver)
from coiltrack.firmware.track.quality import PoseQuality, quality_from
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
EXT = COMPILED.ext
ORTHO = orthogonal_source(0.055, 50)
SKEWED = [Coil([0.01, 0, 0], [1, 0.2, 0], 0.05, 40), Coil([0, 0.012, 0], [0, 1, 0.3], 0.06, 50),
          Coil([0, 0, 0.01], [0.1, 0, 1], 0.055, 45), Coil([-0.01, 0, 0], [1, 1, 1], 0.04, 30)]


def _finisher():
    """A SolveFinish bound to its own buffers (the covariance it writes: ``cov``)."""
    cov = np.zeros((6, 6))
    fin = EXT.SolveFinish(3, math.inf, 0.0, 0.0, 0.0, np.zeros(4), np.zeros(3), cov, np.zeros(EXT.FINISH_WORK))
    return fin, cov


def _spd(rng, n, cond):
    """A random symmetric positive definite n x n matrix of condition number ``cond``, at a
    random scale."""
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    w = np.geomspace(1.0, cond, n) * 10.0 ** rng.uniform(-6, 12)
    return (Q * w) @ Q.T


# ------------------------------------------------------------------ Jacobi
def test_jacobi_bit_identical_and_against_numpy_eigh():
    """400 random symmetric matrices (n 2-6: definite, indefinite, repeated eigenvalues, rank
    deficient, a zero matrix): eigenvalues and vectors the same to the bit as linalg.jacobi_eigh;
    against numpy.linalg.eigh the eigenvalues to 1e-12 of the largest and V diag(w) V^T = A."""
    rng = np.random.default_rng(1)
    for k in range(400):
        n = int(rng.integers(2, 7))
        kind = k % 4
        if kind == 0:
            A = _spd(rng, n, 10.0 ** rng.uniform(0, 14))
        elif kind == 1:
            B = rng.normal(size=(n, n))
            A = B + B.T
        elif kind == 2:
            B = rng.normal(size=(n, max(1, n - 2)))
            A = B @ B.T                                     # rank deficient
        else:
            Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
            A = (Q * np.array([2.0] * (n - 1) + [5.0])) @ Q.T   # a repeated eigenvalue
        if k == 7:
            A = np.zeros((n, n))
        a_ref, a_got = A.flatten(), A.flatten()
        w_ref, w_got = np.zeros(n), np.zeros(n)
        v_ref, v_got = np.zeros(n * n), np.zeros(n * n)
        jacobi_eigh(memoryview(a_ref), n, memoryview(w_ref), memoryview(v_ref))
        EXT.finish_jacobi_eigh(a_got, n, w_got, v_got, 60)
        np.testing.assert_array_equal(w_got, w_ref, err_msg=str(k))
        np.testing.assert_array_equal(v_got, v_ref, err_msg=str(k))
        np.testing.assert_array_equal(a_got, a_ref, err_msg=str(k))
        scale = max(np.abs(A).max(), 1e-300)
        np.testing.assert_allclose(w_got, np.linalg.eigh(A)[0], rtol=0, atol=1e-12 * scale, err_msg=str(k))
        V = v_got.reshape(n, n)
        np.testing.assert_allclose((V * w_got) @ V.T, A, rtol=0, atol=1e-12 * scale, err_msg=str(k))


# --------------------------------------------------------------- covariance
def _inverse_pair(A):
    ref, got = np.zeros(36), None
    RobustInverse6().into(memoryview(A.flatten()), memoryview(ref))
    fin, cov = _finisher()
    fin.inverse(A.flatten())
    got = cov.flatten()
    return ref, got


def test_robust_inverse_bit_identical_and_against_numpy():
    """Well-conditioned information matrices take the Cholesky inverse (= numpy.linalg.inv to
    1e-8 of its largest element), near-singular and singular ones the floored
    eigen-decomposition (= the numpy reference pose.reference._robust_inverse, numpy's eigh, to
    1e-9 of the largest element; the floor alone at condition numbers of 1e15-1e20, where the
    floored directions are rounding noise), indefinite ones and
    non-finite ones their own branches: the compiled inverse is the reference's to the bit in
    each."""
    rng = np.random.default_rng(2)
    branches = set()
    for k in range(300):
        kind = k % 5
        if kind in (0, 1):
            A = _spd(rng, 6, 10.0 ** rng.uniform(0, 8))
        elif kind == 2:
            A = _spd(rng, 6, 10.0 ** rng.uniform(15, 20))                  # beyond the eigenvalue floor
        elif kind == 3:
            B = rng.normal(size=(6, int(rng.integers(1, 6)))) * 10.0 ** rng.uniform(-3, 6)
            A = B @ B.T                                                     # unobservable directions
        else:
            B = rng.normal(size=(6, 6))
            A = B + B.T                                                     # indefinite
        A = 0.5 * (A + A.T)
        ref, got = _inverse_pair(A)
        np.testing.assert_array_equal(got, ref, err_msg=str(k))
        C = got.reshape(6, 6)
        w = np.linalg.eigvalsh(A)
        if kind in (0, 1):
            branches.add("cholesky")
            Ainv = np.linalg.inv(A)
            np.testing.assert_allclose(C, Ainv, rtol=0, atol=1e-8 * np.abs(Ainv).max(), err_msg=str(k))
        else:
            ind = _robust_inverse(A)
            floor = max(1e-15 * max(w.max(), 0.0), 1.0 / MAX_VARIANCE)
            assert np.linalg.eigvalsh(C).max() <= (1.0 + 1e-6) / floor, k     # the floor holds
            if kind != 2:
                # (at condition numbers of 1e15-1e20 the floored directions are rounding noise in
                # any eigen-solver: there only the floor and the reference's bits are checked)
                np.testing.assert_allclose(C, ind, rtol=0, atol=1e-9 * np.abs(ind).max(), err_msg=str(k))
            if kind == 3:
                branches.add("floored")
    assert branches == {"cholesky", "floored"}
    for bad in (math.nan, math.inf):
        A = _spd(rng, 6, 10.0)
        A[2, 4] = bad
        ref, got = _inverse_pair(A)
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(got.reshape(6, 6), np.eye(6) * MAX_VARIANCE)


def _cov6(rng, ori_var):
    """A pose covariance (6, 6) with an orientation block of trace about ``ori_var`` rad^2."""
    C = _spd(rng, 6, 10.0 ** rng.uniform(0, 6))
    s = np.sqrt(np.concatenate([np.full(3, 10.0 ** rng.uniform(-8, -2)), np.full(3, ori_var / 3.0)])
                / np.diag(C))
    return C * np.outer(s, s)


def test_rotation_margin_bit_identical_and_against_the_numpy_form():
    """Orientation variances from 1e-6 to 10 rad^2 (the scaled branch beyond 1), a degenerate
    and a non-finite orientation block: the compiled margin is RotationMargin.into's to the bit
    and pose.reference.rotation_margin's closed form to 1e-9."""
    rng = np.random.default_rng(3)
    for k in range(200):
        C = _cov6(rng, 10.0 ** rng.uniform(-6, 1))
        if k == 5:
            C[3:, 3:] = 0.0
        if k == 6:
            C[4, 4] = math.nan
        ref, got = C.flatten(), C.flatten()
        RotationMargin().into(memoryview(ref))
        EXT.finish_rotation_margin(got)
        np.testing.assert_array_equal(got, ref, err_msg=str(k))
        if k not in (5, 6):
            want = rotation_margin(C)
            np.testing.assert_allclose(got.reshape(6, 6), want, rtol=1e-9, atol=1e-9 * np.abs(want[:3, :3]).max(),
                                       err_msg=str(k))
            assert np.all(np.diag(got.reshape(6, 6))[:3] >= np.diag(C)[:3])


# -------------------------------------------------------------------- solver
def _signals(coils, p, R, cur, rng, noise):
    gen = PoseSolver(coils, "exact", core=core.PYTHON)
    h = memoryview(np.zeros(3 * len(coils)))
    gen.signal.predict(p[0], p[1], p[2], R, cur, h)
    return np.array(h).reshape(len(coils), 3).T + rng.normal(0.0, noise, (3, len(coils)))


def _same_solve(ref, got, args, case):
    st_ref, st_got = ref.solve(*args), got.solve(*args)
    assert st_got == st_ref, case
    np.testing.assert_array_equal(got.position, ref.position, err_msg=str(case))
    np.testing.assert_array_equal(got.rotation, ref.rotation, err_msg=str(case))
    np.testing.assert_array_equal(got.covariance, ref.covariance, err_msg=str(case))
    assert (got.iterations, got.cost, got.converged, got.solve_evals) == \
        (ref.iterations, ref.cost, ref.converged, ref.solve_evals), case
    return st_ref


@pytest.mark.parametrize("coils", [ORTHO, SKEWED, ORTHO[:2]])
def test_solve_finish_bit_identical(coils):
    """Warm solves whose checks pass, whose start lies on the wrong side of the hemisphere
    (reacquired), whose cost fails the gate (a strong outlier), whose LM stops unconverged (one
    iteration allowed) and a two-coil solver (no acquisition to fall back to): the compiled finish
    takes every decision of the reference and writes the same covariance and status."""
    rng = np.random.default_rng(4)
    n = len(coils)
    statuses = set()
    for iters in (20, 1):
        ref = PoseSolver(coils, "exact", iters=iters, core=core.PYTHON)
        got = PoseSolver(coils, "exact", iters=iters, core=COMPILED)
        assert got._unit_finish.__func__ is PoseSolver._unit_finish_compiled
        for k in range(16):
            u = rng.normal(size=3)
            p = u / np.linalg.norm(u) * rng.uniform(0.15, 0.5)
            R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
            cur = rng.uniform(0.5, 2.0, n)
            S = _signals(coils, p, R, cur, rng, 2e-9)
            if k % 4 == 3:
                S[1, 0] += 1e-6                                 # an outlier: the gate fails
            sigma = np.full((3, n), 2e-9)
            hemi = -p if k % 4 == 1 else p                      # k % 4 == 1: the wrong side
            x0p = p + rng.normal(0.0, 0.005, 3)
            st = _same_solve(ref, got, (S, cur, sigma, hemi / np.linalg.norm(hemi), x0p, R), (iters, k))
            statuses.add(st)
    if n >= 3:
        assert any(s & SOLVE_REACQUIRED for s in statuses)
    assert len(statuses) > 1


def test_solve_finish_with_a_distortion_map_and_non_finite_results():
    """The Python LM (a solver whose model carries a distortion map) finished by the compiled
    finish, and a solve from signals so large that its normal equations overflow: the same
    results and status flags as the reference."""
    rng = np.random.default_rng(5)
    ref = PoseSolver(ORTHO, "exact", core=core.PYTHON)
    got = PoseSolver(ORTHO, "exact", core=COMPILED)
    p, R = np.array([0.2, -0.1, 0.15]), Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix()
    cur = np.ones(3)
    S = _signals(ORTHO, p, R, cur, rng, 1e-9)
    sigma = np.full((3, 3), 1e-9)
    _same_solve(ref, got, (S, cur, sigma, None, p + 0.01, R), "plain")
    huge = S * 1e300
    _same_solve(ref, got, (huge, cur, sigma, None, p + 0.01, R), "huge")
    dmap = DistortionMap([[(0.4, 0.1, -0.2)]] * 3, [[(1e-3, -2e-3, 5e-4)]] * 3)
    for sv in (ref, got):
        sv.signal.set_distortion(dmap)
    _same_solve(ref, got, (S, cur, sigma, None, p + 0.01, R), "distortion")
    assert got._lm is got._lm_py


# ------------------------------------------------------------------- quality
def test_quality_from_bit_identical():
    """Random and edge inputs (x below and above 1, zero and huge variances, non-finite and
    negative values, a quality that rounds to 255): the compiled quality_from is the
    reference's."""
    rng = np.random.default_rng(6)
    vals = [0.0, 1e-300, 1e-12, 1e-6, 1.0, 1e6, math.inf, -math.inf, math.nan, -1e-9]
    cases = [(a, b, 0.01, c) for a in vals for b in vals[:7] + [0.5, 2.0, math.nan] for c in vals[:5] + [math.nan]]
    cases += [(10.0 ** rng.uniform(-14, -2), 10.0 ** rng.uniform(-3, 3), 10.0 ** rng.uniform(-4, -1),
               10.0 ** rng.uniform(-14, -2)) for _ in range(2000)]
    for c in cases:
        assert EXT.finish_quality_from(*c) == quality_from(*c), c


CFG = FirmwareConfig()


def _graders(coils, nodes, quiet_sigma=0.0):
    cfg = CFG.with_(quality={"quality_quiet_sigma_t": quiet_sigma})
    chans = [SimpleNamespace(node=nd) for nd in nodes]
    ref = PoseQuality(cfg, len(coils), chans, coils, core.PYTHON)
    got = PoseQuality(cfg, len(coils), chans, coils, COMPILED)
    assert got.grade_burst.__func__ is PoseQuality._grade_burst_compiled
    assert ref.grade_burst.__func__ is PoseQuality.grade_burst
    return ref, got


def _burst_case(rng, n, t_mid):
    """A random burst graded at ``t_mid``: cost, covariance, pose, signals, sigmas, pulses."""
    u = rng.normal(size=3)
    p = u / np.linalg.norm(u) * rng.uniform(0.1, 0.8)
    R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
    S = rng.normal(size=(3, n)) * 10.0 ** rng.uniform(-8, -5)
    sigma = np.abs(rng.normal(size=(3, n))) * 1e-8 + 1e-10
    start = t_mid - 150_000 + np.arange(n, dtype=np.int64) * 100_000
    end = start + 60_000
    return float(rng.chisquare(3 * n)), _cov6(rng, 10.0 ** rng.uniform(-5, -1)), p, R, S, sigma, start, end


@pytest.mark.parametrize("coils", [ORTHO, SKEWED])
def test_grade_burst_bit_identical(coils):
    """A sequence of bursts of three nodes at cycle intervals (the motion term from the previous
    solution), gaps beyond two cycles, a repeated instant, an unknown node, a zero sigma, a
    sensor on a coil's centre, non-finite covariances and an NIS term: the quality, the motion
    term, its residual, the last quality per node and the kept previous solutions the same to
    the bit."""
    rng = np.random.default_rng(7)
    n = len(coils)
    nodes = (16, 17, 18)
    ref, got = _graders(coils, nodes)
    cyc = CFG.timing.cycle_us
    t = 10_000_000
    moved = 0
    for k in range(300):
        node = int(rng.choice(nodes + (99,))) if k % 17 else 99
        t += int(rng.choice([cyc // 3, cyc // 3, 3 * cyc, 0]))
        cost, C, p, R, S, sigma, start, end = _burst_case(rng, n, t)
        if k % 23 == 5:
            sigma[1, 0] = 0.0
        if k % 29 == 3:
            p = np.array(coils[0].center, dtype=float)
        if k % 31 == 7:
            C[0, 1] = C[1, 0] = math.nan
        nis = float(rng.uniform(0, 3)) if k % 2 else 0.0
        q_ref = ref.grade_burst(node, t, cost, C, p, R, S, sigma, start, end, nis)
        q_got = got.grade_burst(node, t, cost, C, p, R, S, sigma, start, end, nis)
        assert q_got == q_ref, k
        assert (got.motion_m2, got.chi2_motion) == (ref.motion_m2, ref.chi2_motion), k
        assert got.last == ref.last, k
        np.testing.assert_array_equal(got._prev_rows, ref._prev_rows, err_msg=str(k))
        moved += ref.motion_m2 > 0.0
    assert moved > 50


def test_grade_burst_motion_against_numpy():
    """Independent reference: ``dp_motion`` and ``chi2_motion`` written with numpy matrices:
    ``xdot`` from the two poses (scipy's rotation vector of ``R_prev^T R``), ``H_j = [R^T J_j,
    [h_j]x]`` with ``J`` the dipole gradient ``3 c / r^4 (m n^T + n m^T + (m.n)(I - 5 n n^T))``
    (``c m`` solved from the field ``B = c (3 (m.n) n - m)``), ``u = D H xdot``,
    ``dx = P H^T W u``: the compiled grader's to 1e-9 relative."""
    rng = np.random.default_rng(8)
    ref, got = _graders(ORTHO, (16,))
    cyc = CFG.timing.cycle_us
    for k in range(40):
        t0 = 20_000_000 + k * 10 * cyc
        _, C0, p0, R0, S0, s0, st0, en0 = _burst_case(rng, 3, t0)
        got.grade_burst(16, t0, 1.0, C0, p0, R0, S0, s0, st0, en0)
        t1 = t0 + cyc
        cost, C, _, _, S, sigma, start, end = _burst_case(rng, 3, t1)
        p = p0 + rng.normal(0.0, 0.01, 3)
        R = R0 @ Rotation.from_rotvec(rng.normal(0.0, 0.1, 3)).as_matrix()
        got.grade_burst(16, t1, cost, C, p, R, S, sigma, start, end)
        dt = cyc * 1e-6
        xd = np.concatenate([(p - p0) / dt, Rotation.from_matrix(R0.T @ R).as_rotvec() / dt])
        H = np.zeros((9, 6))
        for j in range(3):
            B = R @ S[:, j]
            r = p - np.asarray(ORTHO[j].center, float)
            rn = np.linalg.norm(r)
            nv = r / rn
            cm = 1.5 * (B @ nv) * nv - B                  # c m
            cmn = cm @ nv
            J = 3.0 / rn * (np.outer(cm, nv) + np.outer(nv, cm) + cmn * (np.eye(3) - 5.0 * np.outer(nv, nv)))
            h = S[:, j]
            H[3 * j:3 * j + 3, :3] = R.T @ J
            H[3 * j:3 * j + 3, 3:] = np.array([[0, -h[2], h[1]], [h[2], 0, -h[0]], [-h[1], h[0], 0]])
        d = ((start + end) / 2 - t1) * 1e-6
        u = np.repeat(d, 3) * (H @ xd)
        W = np.diag(1.0 / sigma.T.flatten() ** 2)
        dx = C @ H.T @ W @ u
        chi2 = float((u - H @ dx) @ W @ (u - H @ dx))
        assert got.motion_m2 == pytest.approx(float(dx[:3] @ dx[:3]), rel=1e-9), k
        assert got.chi2_motion == pytest.approx(chi2, rel=1e-9, abs=1e-300), k


def test_grade_burst_quiet_term_and_other_arrays_go_to_the_reference():
    """The quiet field's term read from the node's sample ring on both cores, and arrays of
    another kind than the tracker's (a transposed signal matrix, float pulse times, a list
    covariance) graded by the reference inside the compiled grader: the same qualities."""
    from coiltrack.firmware.measure.pulse import SampleRing

    rng = np.random.default_rng(9)
    ring = SampleRing(8)
    ring.push(5, 3e-5, -1e-5, 4e-5, False, 0)
    cfg = CFG.with_(quality={"quality_quiet_sigma_t": 2e-7})
    ch = SimpleNamespace(node=16, ring=ring)
    ref = PoseQuality(cfg, 3, [ch], ORTHO, core.PYTHON)
    got = PoseQuality(cfg, 3, [ch], ORTHO, COMPILED)
    t = 5_000_000
    for k in range(12):
        t += CFG.timing.cycle_us // 3
        cost, C, p, R, S, sigma, start, end = _burst_case(rng, 3, t)
        if k % 3 == 1:
            S = np.asfortranarray(S)
        if k % 3 == 2:
            start, end = start.astype(float), end.astype(float)
        q_ref = ref.grade_burst(16, t, cost, C, p, R, S, sigma, start, end)
        q_got = got.grade_burst(16, t, cost, C, p, R, S, sigma, start, end)
        assert q_got == q_ref and (got.motion_m2, got.chi2_motion) == (ref.motion_m2, ref.chi2_motion), k
        np.testing.assert_array_equal(got._prev_rows, ref._prev_rows, err_msg=str(k))
    assert ref.quiet_term(16) > 0.0


@pytest.mark.skipif(not available(), reason="needs numpy's allocation hooks")
def test_compiled_finish_and_grade_allocate_no_array():
    rng = np.random.default_rng(10)
    s = PoseSolver(ORTHO, "exact", core=COMPILED)
    p, R = np.array([0.25, 0.05, -0.1]), Rotation.from_rotvec([0.1, 0.5, -0.3]).as_matrix()
    cur = np.ones(3)
    S = _signals(ORTHO, p, R, cur, rng, 1e-9)
    sigma = np.full((3, 3), 1e-9)
    hemi = p / np.linalg.norm(p)
    _, got = _graders(ORTHO, (16,))
    cost, C, gp, gR, gS, gs, start, end = _burst_case(rng, 3, 1_000_000)
    x0 = p + 0.005
    s.solve(S, cur, sigma, hemi, x0, R)
    with NumpyAllocationCounter() as c:
        for k in range(5):
            assert s.solve(S, cur, sigma, hemi, x0, R) != SOLVE_RUNNING
            got.grade_burst(16, 1_000_000 + k * 200_000, cost, C, gp, gR, gS, gs, start, end)
    assert c.count == 0


# -------------------------------------------------------------------- report
def test_report_pose_bit_identical():
    """The magnetic tracker's report of its solver's pose: the range check (inside, outside, on
    the boundary, NaN) with its copies, and the POSE's quaternion (every branch of Shepperd's
    method: a positive trace and each largest diagonal element) the same as in_range, np.copyto
    and rotation.quat_tuple; scipy's quaternion as the independent reference (w >= 0)."""
    from coiltrack.firmware.rotation import quat_tuple
    from coiltrack.firmware.track.magnetic import in_range

    rng = np.random.default_rng(11)
    pos, rot, q = np.zeros(3), np.eye(3), np.zeros(4)
    rp = EXT.ReportPose(pos, rot, q)
    angles = [rng.normal(size=3) for _ in range(200)] + [np.array([math.pi, 0, 0]), np.array([0, math.pi, 0]),
                                                        np.array([0, 0, math.pi]), np.zeros(3)]
    for k, rv in enumerate(angles):
        R = Rotation.from_rotvec(rv).as_matrix()
        p = rng.normal(size=3) * 0.5
        if k == 3:
            p[1] = math.nan
        rng_m = float(np.linalg.norm(p)) if k == 4 else 0.6
        pos[:], rot[:] = p, R
        dst_p, dst_R = np.full(3, 7.0), np.full((3, 3), 7.0)
        took = rp.take(dst_p, dst_R, rng_m)
        assert took == in_range(p, rng_m), k
        if took:
            np.testing.assert_array_equal(dst_p, p)
            np.testing.assert_array_equal(dst_R, R)
        else:
            assert np.all(dst_p == 7.0) and np.all(dst_R == 7.0)
        assert rp.quat(R)
        assert tuple(q) == quat_tuple(R), k
        want = Rotation.from_matrix(R).as_quat()[[3, 0, 1, 2]]
        if abs(want[0]) > 1e-9:                     # (w = 0: either sign is the rotation)
            np.testing.assert_allclose(q, want if want[0] > 0 else -want, atol=1e-12, err_msg=str(k))
    assert rp.take(np.zeros(3, np.float32), np.zeros((3, 3)), 1.0) is None
    assert rp.quat(np.eye(3).T) is None


def _svd_projection(m):
    """The independent reference: the orthogonal Procrustes projection U diag(1, 1, det(U V^T)) V^T."""
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def test_nearest_rotation_bit_identical_and_against_the_svd_projection():
    """ct_nearest_rotation against linalg.nearest_rotation to the bit and against the SVD
    projection to 1e-12: an interpolated warm start (two rotations averaged, as the fusion
    history's pose_at gives), noisy and scaled matrices, a reflection (det < 0: the proper
    rotation nearest it), and a rotation to the tolerance already (copied unchanged). A wrong sign
    in one of K's off-diagonal elements or the smallest eigenvector taken would fail both."""
    fin, _ = _finisher()
    rng = np.random.default_rng(30)
    cases = []
    for _ in range(60):
        a, b = Rotation.random(2, random_state=rng).as_matrix()
        cases.append(0.5 * (a + b) if np.linalg.det(a + b) > 0 else a)
        cases.append(a + rng.normal(0.0, 0.05, (3, 3)))
        cases.append(rng.uniform(0.5, 2.0) * b)
    # distinct singular values, so the nearest proper rotation is unique
    cases.append(np.diag([1.0, 1.0, -1.0]) @ Rotation.random(random_state=rng).as_matrix() @ np.diag([1.3, 1.0, 0.7]))
    exact = Rotation.random(random_state=rng).as_matrix()
    cases.append(exact)
    for m in cases:
        m9 = np.ascontiguousarray(m, dtype=float).ravel()
        ref = np.zeros((3, 3))
        nearest_rotation(memoryview(m9), ref, Rot3())
        out = np.full((3, 3), np.nan)
        assert fin.nearest(m9, out) is True
        np.testing.assert_array_equal(out, ref)
        np.testing.assert_allclose(out, _svd_projection(m), rtol=0, atol=1e-12)
    out = np.zeros((3, 3))
    fin.nearest(exact.ravel().copy(), out)
    np.testing.assert_array_equal(out, exact)
    assert fin.nearest(np.zeros(9, dtype=np.float32), out) is None     # another kind: the caller's Python
