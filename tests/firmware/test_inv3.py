"""The one symmetric 3x3 inverse (``linalg.inv3_sym``) against numpy, and
its positive-definiteness test (Sylvester), which every caller relies on: the
3-dof Kalman update, the single-coil NIS and the coil-choice posterior."""
import numpy as np
import pytest

from coiltrack.firmware.estimate.ekf import EKF_NOT_PD, EKF_OK, KalmanUpdate
from coiltrack.firmware.linalg import inv3_sym, quad3_sym


def _six(S):
    return tuple(float(S[i, j]) for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))


def test_inverse_and_quadratic_form_match_numpy():
    rng = np.random.default_rng(5)
    for _ in range(200):
        A = rng.normal(size=(3, 3))
        S = A @ A.T + rng.uniform(1e-3, 1.0) * np.eye(3)
        S *= 10.0 ** rng.uniform(-12, 2)
        inv = inv3_sym(*_six(S))
        Si = np.linalg.inv(S)
        np.testing.assert_allclose(inv, _six(Si), rtol=1e-9)
        r = rng.normal(size=3)
        assert quad3_sym(inv, *r) == pytest.approx(r @ Si @ r, rel=1e-9)


@pytest.mark.parametrize("S", [
    np.diag([-1.0, -2.0, 3.0]),                 # det > 0, indefinite
    np.diag([1.0, -1.0, -1.0]),                 # det > 0, first minor > 0, indefinite
    np.diag([1.0, 1.0, 0.0]),                   # singular
    np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, -1.0]]),   # det > 0, indefinite
    np.diag([1.0, np.nan, 1.0]),
    np.diag([1e300, 1e300, 1e300]),             # determinant overflows
])
def test_not_positive_definite_is_refused(S):
    assert inv3_sym(*_six(S)) is None
    u = KalmanUpdate(3, 3, 1.0)
    u.H[:] = np.eye(3)
    u.R[:] = S
    u.y[:] = [0.1, 0.0, 0.0]
    assert u.update(np.zeros((3, 3))) == EKF_NOT_PD


def test_kalman_update_3dof_uses_it():
    u = KalmanUpdate(3, 3, 1.0)
    u.H[:] = np.eye(3)
    S = np.array([[2.0, 0.3, -0.1], [0.3, 1.5, 0.2], [-0.1, 0.2, 1.0]])
    u.R[:] = S
    u.y[:] = [0.1, -0.2, 0.3]
    assert u.update(np.zeros((3, 3))) == EKF_OK
    np.testing.assert_allclose(u.Sinv, np.linalg.inv(S), rtol=1e-12)
    assert u.nis == pytest.approx(u.y @ np.linalg.solve(S, u.y), rel=1e-12)
