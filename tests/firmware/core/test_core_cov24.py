"""The 24-state covariance prediction at its fixed size (firmware_py/core/src/cov24.c,
``ct_covariance_predict_24``, run by ekf.c ``ct_covariance_predict`` for n = 24) against the
generic kernel's operations written out in Python floats (ekf.c ``ct_congruence_sparse``, then
``P += Q``): the same sums in the same order, so the same bits; and against numpy's products."""
from __future__ import annotations

import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.estimate.ekf import CovariancePredict
from coiltrack.firmware.estimate.strapdown import Strapdown, transition_nav, transition_sensor, transition_static

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")


def _sparse_order(A, P, Q):
    """ekf.c ct_congruence_sparse then P += Q, operation by operation (IEEE doubles, no fused
    multiply-add): T = A P over A's non-zero entries, P = T A^T column by column, then Q."""
    n = A.shape[0]
    a, p, q = A.tolist(), P.tolist(), Q.tolist()
    T = [[0.0] * n for _ in range(n)]
    for i in range(n):
        Ti = T[i]
        for k in range(n):
            x = a[i][k]
            if x == 0.0:
                continue
            Pk = p[k]
            for j in range(n):
                Ti[j] += x * Pk[j]
    out = [[0.0] * n for _ in range(n)]
    for j in range(n):
        for k in range(n):
            x = a[j][k]
            if x == 0.0:
                continue
            for i in range(n):
                out[i][j] += T[i][k] * x
    return np.array([[out[i][j] + q[i][j] for j in range(n)] for i in range(n)])


def _spd(rng, n, cond=1e6):
    Qm, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (Qm * np.geomspace(1.0, 1.0 / cond, n)) @ Qm.T


def _compiled(n, A, Q):
    pr = CovariancePredict(n, core.load("compiled"))
    assert pr.core == "compiled"
    pr.A[:] = A
    pr.Q[:] = Q
    return pr


@pytest.mark.parametrize("sensor_frame", [False, True])
def test_fusion_transition_bit_for_bit(sensor_frame):
    """The ch. 6 error transition (eq 6.17, estimate.strapdown's blocks; an angle near pi) on an
    ill-conditioned P with a full Q: the fixed-size kernel gives the generic kernel's bits, step
    after step (a product summed in another order, a dropped structural entry or Q added twice
    differs in the last bits at least)."""
    rng = np.random.default_rng(24)
    n = 24
    A = np.zeros((n, n))
    transition_static(A, 1e-3, 0.999, 0.9995)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    if sensor_frame:
        transition_sensor(A, 1e-3, R, 0.1, -0.2, 9.81, 0.3, -0.1, 0.05, Strapdown())
    else:
        transition_nav(A, 1e-3, R, 0.05, 0.1, 9.81)
    Q = 1e-8 * _spd(rng, n, 1e3)
    pr = _compiled(n, A, Q)
    P = _spd(rng, n)
    want = P.copy()
    for _ in range(5):
        pr._ck.predict(P)
        want = _sparse_order(A, want, Q)
        assert P.tobytes() == want.tobytes()
    np.testing.assert_allclose(P, want, rtol=0, atol=0)


def test_dense_and_signed_zero_entries_bit_for_bit():
    """A dense random A with some entries exactly +0.0 and -0.0 (both skipped, as the generic
    kernel's ``a == 0.0``) and a zero row: the same bits as the generic order; numpy's
    ``A P A^T + Q`` within 1e-12."""
    rng = np.random.default_rng(5)
    n = 24
    A = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    A[rng.random((n, n)) < 0.3] = 0.0
    A[rng.random((n, n)) < 0.1] = -0.0
    A[7, :] = 0.0
    Q = np.diag(rng.uniform(1e-6, 1e-3, n))
    P0 = _spd(rng, n)
    P = P0.copy()
    _compiled(n, A, Q)._ck.predict(P)
    assert P.tobytes() == _sparse_order(A, P0, Q).tobytes()
    np.testing.assert_allclose(P, A @ P0 @ A.T + Q, rtol=0, atol=1e-12 * np.abs(P).max())
    assert P[7, 7] == Q[7, 7] and np.all(P[7, np.arange(n) != 7] == 0.0)


def test_other_sizes_keep_the_generic_kernel():
    """n = 23 and 25 run ekf.c's generic loops: the same bits as the order written out."""
    rng = np.random.default_rng(3)
    for n in (23, 25):
        A = np.eye(n) + 0.05 * rng.normal(size=(n, n)) * (rng.random((n, n)) < 0.2)
        Q = 1e-6 * _spd(rng, n, 1e2)
        P0 = _spd(rng, n)
        P = P0.copy()
        _compiled(n, A, Q)._ck.predict(P)
        assert P.tobytes() == _sparse_order(A, P0, Q).tobytes()


@pytest.mark.parametrize("nr, nc", [(15, 15), (16, 16), (16, 17), (17, 16), (24, 24), (10, 20), (1, 1), (24, 3)])
def test_trailing_zero_rows_and_columns_bit_for_bit(nr, nc):
    """A whose non-zero entries lie in rows < nr and columns < nc (the fusion transition: 15 and 15,
    the white states last), trimmed by the kernel: the same bits as the full generic order,
    including P's signed zeros, over P with negative, NaN and infinite entries in the rows and
    columns the trim skips; A with an infinite or NaN entry keeps the dense loops (0 * inf is
    NaN, not the trim's 0): again the generic order's bits (NaN where it has NaN)."""
    rng = np.random.default_rng(nr * 100 + nc)
    n = 24
    A = np.zeros((n, n))
    A[:nr, :nc] = rng.normal(size=(nr, nc)) * (rng.random((nr, nc)) < 0.4)
    A[nr - 1, nc - 1] = -1.5                    # (the corner non-zero: nr, nc exactly)
    Q = np.diag(rng.uniform(1e-6, 1e-3, n))
    Q[3, 5] = Q[5, 3] = -0.0
    P0 = _spd(rng, n)
    P0[n - 1, :] = -P0[n - 1, :]
    for bad in (0.0, np.nan, np.inf):
        Pb = P0.copy()
        if bad:
            Pb[n - 1, n - 2] = bad               # in a row and column the trim never reads when nc < 24
        P = Pb.copy()
        _compiled(n, A, Q)._ck.predict(P)
        ref = _sparse_order(A, Pb, Q)
        assert P.tobytes() == ref.tobytes(), bad
    for bad in (np.inf, np.nan):
        A2 = A.copy()
        A2[0, 0] = bad
        P = P0.copy()
        _compiled(n, A2, Q)._ck.predict(P)
        ref = _sparse_order(A2, P0, Q)
        assert P.tobytes() == ref.tobytes(), bad
