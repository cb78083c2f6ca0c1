"""The compiled covariance prediction (firmware_py/core/src/ekf.c) against its reference
estimate.ekf.CovariancePredict.predict (numpy/BLAS products): P <- A P A^T + Q.

The C sums each entry over k in increasing order with A's zero entries skipped; BLAS blocks and
fuses differently on each machine, so the comparison is to 1e-12 relative of the largest entry
(rounding: observed ~1e-15). Seeded; skips where the extension is not built."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.estimate.ekf import SYMMETRIZE_EVERY, CovariancePredict
from coiltrack.firmware.estimate.strapdown import Strapdown, transition_nav, transition_sensor, transition_static
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")


def _pair(n, monkeypatch):
    ref = CovariancePredict(n, core.PYTHON)
    got = CovariancePredict(n, core.load("compiled"))
    assert (ref.core, got.core) == ("python", "compiled")
    return ref, got


def _spd(rng, n, cond=1e3):
    Qm, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (Qm * np.geomspace(1.0, 1.0 / cond, n)) @ Qm.T


def _rotation(rng, angle=None):
    w = rng.normal(size=3)
    w /= np.linalg.norm(w)
    w *= rng.uniform(0, np.pi) if angle is None else angle
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(w).as_matrix()


@pytest.mark.parametrize("n", [9, 12, 21, 24])
def test_dense_random_transition_matches_the_reference(n, monkeypatch):
    """A dense random A (no zero to skip) and a full Q, 40 steps (symmetrised every 16 as the
    reference): equal to 1e-12 relative; a transposed product (A^T P A) or Q added twice is off
    by O(1)."""
    rng = np.random.default_rng(n)
    ref, got = _pair(n, monkeypatch)
    A = np.eye(n) + 0.05 * rng.normal(size=(n, n))
    Q = 1e-4 * _spd(rng, n)
    for pr in (ref, got):
        pr.A[:] = A
        pr.Q[:] = Q
    P1 = _spd(rng, n)
    P2 = P1.copy()
    for _ in range(40):
        ref.predict(P1)
        got.predict(P2)
    np.testing.assert_allclose(P2, P1, rtol=0, atol=1e-12 * np.abs(P1).max())
    assert got.count == ref.count == 40 and 40 // SYMMETRIZE_EVERY == 2


@pytest.mark.parametrize("sensor_frame", [False, True])
def test_inertial_error_transition_matches_the_reference(sensor_frame, monkeypatch):
    """The 24-state error transition of eq 6.17 as the filters write it (estimate.strapdown:
    static blocks, the navigation- or sensor-frame blocks, with an angle near pi and a specific
    force of gravity), its structural zeros skipped by the C: 200 steps equal to 1e-12 relative.
    A skipped non-zero entry (a wrong sparsity test) is off by far more."""
    rng = np.random.default_rng(7)
    n = 24
    ref, got = _pair(n, monkeypatch)
    dt = 1.0 / 120.0
    sd = Strapdown()
    for pr in (ref, got):
        transition_static(pr.A, dt, 0.999, 0.9995)
        R = _rotation(np.random.default_rng(1), angle=np.pi - 1e-9)
        if sensor_frame:
            transition_sensor(pr.A, dt, R, 0.1, -0.2, 9.81, 0.3, -0.1, 0.05, sd)
        else:
            transition_nav(pr.A, dt, R, 0.05, 0.1, 9.81)
        pr.Q[:] = np.diag(rng.uniform(1e-10, 1e-4, n)) if pr is ref else ref.Q
    assert np.count_nonzero(got.A) < n * n // 4
    P1 = _spd(rng, n, cond=1e8)
    P2 = P1.copy()
    for _ in range(200):
        ref.predict(P1)
        got.predict(P2)
    np.testing.assert_allclose(P2, P1, rtol=0, atol=1e-12 * np.abs(P1).max())


def test_near_singular_covariance_and_zero_rows(monkeypatch):
    """A rank-deficient P (a state known exactly) and an A with a zero row (a state reset every
    step): the zero row and column stay exactly Q's, as the reference's."""
    rng = np.random.default_rng(8)
    n = 9
    ref, got = _pair(n, monkeypatch)
    A = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    A[4, :] = 0.0
    Q = np.diag(rng.uniform(1e-6, 1e-3, n))
    for pr in (ref, got):
        pr.A[:] = A
        pr.Q[:] = Q
    v = rng.normal(size=(n, 2))
    P1 = v @ v.T
    P2 = P1.copy()
    ref.predict(P1)
    got.predict(P2)
    np.testing.assert_allclose(P2, P1, rtol=0, atol=1e-12 * np.abs(P1).max())
    assert P2[4, 4] == Q[4, 4] and np.all(P2[4, np.arange(n) != 4] == 0.0)


@pytest.mark.skipif(not available(), reason="needs numpy's allocation hook")
def test_compiled_prediction_allocates_no_array(monkeypatch):
    _, got = _pair(24, monkeypatch)
    P = np.eye(24)
    got.predict(P)
    with NumpyAllocationCounter() as c:
        for _ in range(2 * SYMMETRIZE_EVERY):
            got.predict(P)
    assert c.count == 0


def test_a_non_contiguous_covariance_is_refused(monkeypatch):
    _, got = _pair(6, monkeypatch)
    with pytest.raises(TypeError, match="P"):
        got.predict(np.eye(12)[::2, ::2])
