"""The compiled Kalman update (firmware_py/core/src/ekf.c: ct_kalman_update, ct_inv3,
ct_spd_inverse) against its reference estimate.ekf.KalmanUpdate.update (numpy/BLAS products,
linalg.inv3_sym, linalg.spd_inverse): the one update shape of every filter (innovation variance,
chi-square gate, gain, Joseph form).

S^-1 is the same code in the same order (bit-identical for the same S); the products go through
BLAS in the reference, so P, dx, K are compared to 1e-12 relative. Seeded; skips where the
extension is not built."""
import math

import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NONFINITE, EKF_NOT_PD, EKF_OK, KalmanUpdate
from coiltrack.firmware.linalg import spd_inverse
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")


def _pair(n, m, monkeypatch, gate_probability=0.999):
    ref = KalmanUpdate(n, m, gate_probability, core.PYTHON)
    got = KalmanUpdate(n, m, gate_probability, core.load("compiled"))
    assert (ref.core, got.core) == ("python", "compiled")
    return ref, got


def _spd(rng, n, cond=1e3):
    Qm, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (Qm * np.geomspace(1.0, 1.0 / cond, n)) @ Qm.T


def _load(pairs, H, R, y):
    for u in pairs:
        u.H[:] = H
        u.R[:] = R
        u.y[:] = y


def _close(a, b):
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * max(np.abs(a).max(), 1e-300))


@pytest.mark.parametrize("n,m", [(9, 3), (21, 6), (24, 9), (15, 3), (12, 3)])
def test_update_matches_the_reference(n, m, monkeypatch):
    """40 updates from random covariances with a sparse H (a skew block and an identity block, as
    the filters write them) and a dense one: P, dx, S, K and the NIS equal to 1e-12 relative, the
    flags equal. A K computed as S^-1 PHt, or the Joseph form's K R K^T dropped, is off by O(1)."""
    rng = np.random.default_rng(100 + n + m)
    ref, got = _pair(n, m, monkeypatch, gate_probability=1.0)
    for trial in range(40):
        H = np.zeros((m, n))
        if trial % 2:
            H[:] = rng.normal(size=(m, n))
        else:
            for r in range(m):
                H[r, rng.integers(0, n, size=3)] = rng.normal(size=3)
        R = _spd(rng, m) * 1e-2
        y = rng.normal(size=m) * 0.1
        _load((ref, got), H, R, y)
        P1 = _spd(rng, n, cond=1e6)
        P2 = P1.copy()
        f1, f2 = ref.update(P1), got.update(P2)
        assert f1 == f2 == EKF_OK
        for a, b in ((P1, P2), (ref.dx, got.dx), (ref.S, got.S), (ref.K, got.K)):
            _close(a, b)
        assert got.nis == pytest.approx(ref.nis, rel=1e-12)
    assert ref.count == got.count == 40


@pytest.mark.parametrize("m", [3, 6])
def test_inverse_of_s_is_bit_identical(m):
    """ct_inv3 / ct_spd_inverse (through an update with H = I, P = 0: S = R exactly) against
    linalg.inv3_sym / spd_inverse(m): the same operations in the same order, so the same bits."""
    rng = np.random.default_rng(7 + m)
    inv = spd_inverse(m)
    for _ in range(30):
        S = _spd(rng, m, cond=1e8)
        u = KalmanUpdate(m, m, 1.0, core.load("compiled"))
        u.H[:] = np.eye(m)
        u.R[:] = S
        u.y[:] = 0.0
        P = np.zeros((m, m))
        assert u.update(P) == EKF_OK
        ref = np.zeros(m * m)
        if m == 3:
            from coiltrack.firmware.estimate.ekf import _inv3

            assert _inv3(S.reshape(-1), ref)
        else:
            assert inv(S.reshape(-1), ref)
        np.testing.assert_array_equal(u.Sinv.reshape(-1), ref)


def test_rejections_match_the_reference(monkeypatch):
    """A gated innovation, a non-positive-definite S (R negative, near singular), a NaN
    innovation: the same flags, dx zeroed, P untouched, the rejection counted, NIS inf when S is
    not positive definite."""
    rng = np.random.default_rng(9)
    n, m = 9, 3
    ref, got = _pair(n, m, monkeypatch)
    H = np.zeros((m, n))
    H[:, :3] = np.eye(3)
    P0 = _spd(rng, n) * 1e-4
    cases = [(np.eye(3) * 1e-6, np.array([1.0, 0.0, 0.0]), EKF_GATED),
             (-np.eye(3), np.array([1e-3, 0.0, 0.0]), EKF_NOT_PD),
             (np.eye(3) * 1e-2, np.array([np.nan, 0.0, 0.0]), EKF_NONFINITE)]
    for R, y, flag in cases:
        _load((ref, got), H, R, y)
        for u in (ref, got):
            u.dx[:] = 1.0
        P1, P2 = P0.copy(), P0.copy()
        assert ref.update(P1) == got.update(P2) == flag
        np.testing.assert_array_equal(P2, P0)
        np.testing.assert_array_equal(got.dx, 0.0)
        assert (math.isnan(got.nis) and math.isnan(ref.nis)) or got.nis == pytest.approx(ref.nis, rel=1e-12)
        if flag == EKF_NOT_PD:
            assert got.nis == math.inf
    assert ref.rejected == got.rejected == 3


@pytest.mark.skipif(not available(), reason="needs numpy's allocation hook")
def test_compiled_update_allocates_no_array(monkeypatch):
    _, got = _pair(24, 9, monkeypatch, 1.0)
    got.H[:, :9] = np.eye(9)
    got.R[:] = np.eye(9) * 1e-2
    P = np.eye(24)
    got.update(P)
    with NumpyAllocationCounter() as c:
        for _ in range(40):
            got.y[0] = 0.01
            got.update(P)
    assert c.count == 0
