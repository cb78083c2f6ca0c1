"""The straight-line symmetric positive definite inverse (``linalg.spd_inverse``)
that the Kalman updates of more than three dimensions use, against numpy and
against the loops it unrolls (``linalg.chol_inverse``)."""
import numpy as np
import pytest

from coiltrack.firmware.estimate.ekf import EKF_NOT_PD, EKF_OK, KalmanUpdate
from coiltrack.firmware.linalg import chol_inverse, flat, spd_inverse


@pytest.mark.parametrize("n", range(1, 13))
def test_inverse_matches_numpy_and_the_loops_to_the_bit(n):
    """A wrong index in the generated code (an upper-triangle element read, a
    term of a sum dropped, an element written to its transpose only) makes the
    product with ``S`` differ from the identity by far more than rounding.
    Reference: ``numpy.linalg.inv``, relative 1e-9 on condition numbers up to
    about 1e4; and ``chol_inverse``, bit for bit (the same operations in the
    same order, so swapping one for the other changes no figure)."""
    rng = np.random.default_rng(100 + n)
    inv = spd_inverse(n)
    for _ in range(20):
        A = rng.normal(size=(n, n))
        S = (A @ A.T + rng.uniform(1e-2, 1.0) * np.eye(n)) * 10.0 ** rng.uniform(-10, 2)
        U = S.copy()
        U[np.triu_indices(n, 1)] = rng.normal(size=n * (n - 1) // 2)   # only the lower triangle is read
        out = np.zeros((n, n))
        assert inv(flat(U), flat(out))
        np.testing.assert_allclose(out, np.linalg.inv(S), rtol=1e-9, atol=0)
        ref, L = np.zeros((n, n)), np.zeros((n, n))
        assert chol_inverse(flat(U), n, flat(ref), flat(L))
        assert np.array_equal(out, ref)


@pytest.mark.parametrize("S", [
    np.diag([1.0, 2.0, 3.0, -1.0, 5.0, 6.0]),                    # one negative pivot, last ones positive
    np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 0.0]),                     # singular
    np.diag([1.0, 1.0, np.nan, 1.0, 1.0, 1.0]),
    np.diag([1.0, 1.0, 1.0, np.inf, 1.0, 1.0]),
    np.array([[1.0, 2.0], [2.0, 1.0]]),                          # indefinite, positive diagonal
])
def test_not_positive_definite_is_refused(S):
    """A dropped pivot check would return a NaN or a wrong inverse of an
    indefinite ``S``; the 6-dof Kalman update must refuse it (``EKF_NOT_PD``)."""
    n = S.shape[0]
    assert not spd_inverse(n)(flat(S.copy()), flat(np.zeros((n, n))))
    u = KalmanUpdate(n, n, 1.0)
    u.H[:] = np.eye(n)
    u.R[:] = S
    u.y[:] = 0.1
    assert u.update(np.zeros((n, n))) == EKF_NOT_PD


def test_kalman_update_6dof_uses_it():
    """The 6-dof update's ``S^-1`` and NIS against numpy (relative 1e-12)."""
    rng = np.random.default_rng(7)
    A = rng.normal(size=(6, 6))
    S = A @ A.T + np.eye(6)
    u = KalmanUpdate(6, 6, 1.0)
    u.H[:] = np.eye(6)
    u.R[:] = S
    u.y[:] = rng.normal(size=6)
    assert u.update(np.zeros((6, 6))) == EKF_OK
    np.testing.assert_allclose(u.Sinv, np.linalg.inv(S), rtol=1e-12)
    assert u.nis == pytest.approx(u.y @ np.linalg.solve(S, u.y), rel=1e-12)


@pytest.mark.parametrize("n", [3, 6])
def test_damped_solve_matches_the_loops_to_the_bit(n):
    """The Levenberg-Marquardt system ``(A + lam diag A) d = g`` solved by the
    straight-line ``damped_spd_solve`` against ``pose.lm.damped``,
    ``cholesky`` and ``chol_solve`` (bit for bit: a solve that differed would
    move every pose figure), and against ``numpy.linalg.solve`` (relative
    1e-9). A non-positive diagonal element is damped by ``lam`` alone (a
    dropped branch would divide by a zero pivot)."""
    from coiltrack.firmware.linalg import chol_solve, cholesky, damped_spd_solve
    from coiltrack.firmware.pose.lm import damped

    rng = np.random.default_rng(40 + n)
    solve = damped_spd_solve(n)
    for trial in range(30):
        J = rng.normal(size=(n + 3, n))
        A = J.T @ J
        if trial % 5 == 0:
            A[n - 1, :] = A[:, n - 1] = 0.0        # a parameter the data do not see
        lam = 10.0 ** rng.uniform(-8, 2)
        b = rng.normal(size=n)
        x = np.zeros(n)
        assert solve(flat(A), memoryview(b), memoryview(x), lam)
        m, L, ref = np.zeros(n * n), np.zeros(n * n), np.zeros(n)
        damped(flat(A), memoryview(m), n, lam)
        assert cholesky(memoryview(m), n, memoryview(L))
        chol_solve(memoryview(L), n, memoryview(b), memoryview(ref))
        assert np.array_equal(x, ref)
        np.testing.assert_allclose(x, np.linalg.solve(m.reshape(n, n), b), rtol=1e-9)
    A = -np.eye(n)
    A[0, 0] = 1.0
    A[1, 1] = np.nan
    x = np.full(n, 7.0)
    assert not solve(flat(A), memoryview(np.ones(n)), memoryview(x), 0.5)
    assert np.all(x == 7.0)
