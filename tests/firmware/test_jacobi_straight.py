"""The straight-line Jacobi eigen-decomposition (``linalg.jacobi_eigh``, used by the nearest
rotation of every pose solve, the pose covariance and Kuipers' closed form) against numpy and,
bit for bit, against the loops it is written from (``linalg.jacobi_eigh_loops``)."""
import math

import numpy as np
import pytest

from coiltrack.firmware.linalg import Rot3, flat, jacobi_eigh, jacobi_eigh_loops, nearest_rotation


def _both(M, sweeps=60):
    n = M.shape[0]
    a1, a2 = M.copy(), M.copy()
    w1, w2 = np.zeros(n), np.zeros(n)
    v1, v2 = np.zeros((n, n)), np.zeros((n, n))
    jacobi_eigh(flat(a1), n, flat(w1), flat(v1), sweeps)
    jacobi_eigh_loops(flat(a2), n, flat(w2), flat(v2), sweeps)
    return (a1, w1, v1), (a2, w2, v2)


@pytest.mark.parametrize("n", range(1, 8))
def test_eigenpairs_match_numpy_and_the_loops_to_the_bit(n):
    """A wrong index in the generated rotation (an element of the other triangle left stale,
    an eigenvector column not rotated, a term's sign) breaks ``M v = w v`` far beyond rounding;
    and the generated code does the loops' operations in their order: the overwritten matrix,
    the eigenvalues and the eigenvectors are the same to the bit."""
    rng = np.random.default_rng(200 + n)
    for k in range(25):
        A = rng.normal(size=(n, n))
        M = (A + A.T) * 10.0 ** rng.uniform(-8, 3)
        if k % 5 == 0:
            M = np.diag(rng.normal(size=n)) + 1e-9 * M       # nearly diagonal: few rotations
        if k % 7 == 0 and n > 1:
            M[0, n - 1] = M[n - 1, 0] = 0.0                  # a zero off-diagonal element: skipped
        (a1, w1, v1), (a2, w2, v2) = _both(M)
        assert np.array_equal(a1, a2) and np.array_equal(w1, w2) and np.array_equal(v1, v2)
        np.testing.assert_allclose(w1, np.linalg.eigvalsh(M), rtol=1e-9, atol=1e-12 * np.abs(M).max())
        np.testing.assert_allclose(M @ v1, v1 * w1, atol=1e-9 * np.abs(M).max())
        assert np.all(np.diff(w1) >= 0.0)


def test_sweep_limit_and_non_finite_input_follow_the_loops():
    """One sweep only (not converged) and a NaN element: still the loops' result, bit for bit
    (NaN where they give NaN)."""
    rng = np.random.default_rng(7)
    A = rng.normal(size=(4, 4))
    for M, sweeps in ((A + A.T, 1), (A + A.T, 2)):
        r1, r2 = _both(M, sweeps)
        for x, y in zip(r1, r2):
            assert np.array_equal(x, y)
    M = A + A.T
    M[1, 2] = M[2, 1] = math.nan
    r1, r2 = _both(M)
    for x, y in zip(r1, r2):
        assert np.array_equal(x, y, equal_nan=True)


def test_nearest_rotation_is_the_polar_factor():
    """Through the straight-line code the nearest rotation is still the SVD's
    ``U diag(1, 1, det(U V^T)) V^T`` (a transposed quaternion eigenvector or the smallest
    eigenvalue's column taken would give another rotation)."""
    rng = np.random.default_rng(11)
    work = Rot3()
    out = np.zeros((3, 3))
    for _ in range(30):
        M = rng.normal(size=(3, 3))
        U, _, Vt = np.linalg.svd(M)
        ref = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        nearest_rotation(memoryview(M.reshape(-1).copy()), out, work)
        np.testing.assert_allclose(out, ref, atol=1e-9)
