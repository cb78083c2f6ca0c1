"""The pose covariance's 6x6 inverse (``pose.covariance.RobustInverse6``), the one inverse of
the information matrix that both runtime solvers (least squares and Raab's tracker) use."""
import numpy as np

from coiltrack.firmware.pose.covariance import EIG_FLOOR, MAX_VARIANCE, RobustInverse6


def _info(rng):
    """An information matrix J^T J of a 3-coil pose fit: position rows 1e3 times the
    orientation rows (metres against radians at 30 cm), so the two blocks are 1e6 apart."""
    J = rng.normal(size=(9, 6)) * np.array([1e3, 1e3, 1e3, 1.0, 1.0, 1.0])
    return J.T @ J


def test_plain_inverse_against_numpy():
    """A well-posed information matrix is inverted exactly: numpy's inverse to 1e-12 of its
    largest element, symmetric. Catches a transposed off-diagonal block or the floor applied
    where nothing needs flooring."""
    rng = np.random.default_rng(28)
    inv = RobustInverse6()
    out = memoryview(np.zeros(36))
    for _ in range(20):
        A = _info(rng)
        inv.into(memoryview(A.ravel().copy()), out)
        ref = np.linalg.inv(A)
        C = np.array(out).reshape(6, 6)
        assert np.abs(C - ref).max() < 1e-12 * np.abs(ref).max()
        assert np.array_equal(C, C.T)


def test_unobservable_direction_is_floored_not_infinite():
    """An information matrix blind to one rotation (its orientation block of rank 2) has no
    inverse; the robust one floors that eigenvalue at EIG_FLOOR of the largest (or
    1/MAX_VARIANCE): the covariance is finite, symmetric, its variance along the blind
    direction 1/floor within 1e-6, and the observable directions keep numpy's pseudo-inverse
    to 1e-7 (the 1e8 variance along the blind direction leaks its rounding, about 1e-8, into
    the projection). Catches a floor relative to the wrong eigenvalue, a dropped eigenvector
    normalisation, or NaN from the failed Cholesky leaking out."""
    rng = np.random.default_rng(5)
    A = _info(rng)
    w, V = np.linalg.eigh(A)
    w[0] = 0.0                                       # one direction carries no information
    A = (V * w) @ V.T
    A = 0.5 * (A + A.T)
    out = memoryview(np.zeros(36))
    RobustInverse6().into(memoryview(A.ravel().copy()), out)
    C = np.array(out).reshape(6, 6)
    assert np.all(np.isfinite(C)) and np.allclose(C, C.T, rtol=0, atol=1e-9 * np.abs(C).max())
    floor = max(EIG_FLOOR * w[-1], 1.0 / MAX_VARIANCE)
    v0 = V[:, 0]
    assert abs(v0 @ C @ v0 * floor - 1.0) < 1e-6
    P = np.eye(6) - np.outer(v0, v0)                 # the observable subspace
    ref = np.linalg.pinv(A, rcond=1e-14)
    assert np.abs(P @ C @ P - P @ ref @ P).max() < 1e-7 * np.abs(ref).max()


def test_non_finite_information_gives_the_unknown_covariance():
    """A NaN in the information (a failed evaluation) gives MAX_VARIANCE on the diagonal and
    zeros elsewhere: the pose is reported unknown, never as NaN."""
    A = np.eye(6)
    A[2, 4] = np.nan
    out = memoryview(np.zeros(36))
    RobustInverse6().into(memoryview(A.ravel().copy()), out)
    assert np.array_equal(np.array(out).reshape(6, 6), MAX_VARIANCE * np.eye(6))
