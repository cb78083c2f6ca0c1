"""The one shape of every estimator update, and the covariance prediction.

Every measurement update in the firmware goes through
:meth:`KalmanUpdate.update`, in this order (thesis ``002_cd7f1fdb7fc67471.txt``
eqs 2.16-2.18 and Fig. 4.3; Joseph form after Bucy & Joseph):

1. innovation ``y = z - H dx-`` (``dx- = 0`` in a complementary filter with
   feedback, so the caller passes ``y = z``);
2. innovation variance ``S = H P H^T + R``;
3. chi-square gate: the normalised innovation squared ``NIS = y^T S^-1 y``
   is compared with the ``gate_probability`` quantile of a chi-square with
   ``m`` degrees of freedom (table below, no scipy on a board); a rejected
   measurement leaves ``P`` untouched;
4. gain ``K = P H^T S^-1`` (eq 2.17);
5. correction ``dx = K y`` (eq 2.16);
6. Joseph-form covariance ``P = (I - K H) P (I - K H)^T + K R K^T``; it
   stays positive semi-definite whatever the rounding (re-symmetrised every
   ``SYMMETRIZE_EVERY`` updates against the drift of rounding). ``I - K H``
   is applied as two rank-``m`` corrections, ``T = P - K (H P)`` and
   ``T - (T H^T) K^T`` (``H P = (P H^T)^T`` of step 2): the same factors, with
   products of inner size ``m`` instead of ``n``. (Multiplying the Joseph form
   out to ``P - K H P - P H^T K^T + K S K^T`` is the same algebra but not the
   same arithmetic: it cancels the measured states' prior to rounding and
   loses a precise measurement's posterior, ``tests/firmware/test_references.py``);
7. health flags are returned, never raised.

``predict_covariance`` is ``P = A P A^T + Q`` (eq 2.18, 6.5).

All buffers are allocated by the constructors; the calls allocate no numpy
array (no Python scalars in ufuncs, no overlapping ``out=``).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.linalg import flat, inv3_sym, spd_inverse

#: rounding makes P drift from symmetry; it is re-symmetrised every this many calls
SYMMETRIZE_EVERY = 16

# health flags (bit field)
EKF_OK = 0
EKF_GATED = 1          # NIS beyond the gate: measurement rejected
EKF_NOT_PD = 2         # innovation covariance not positive definite: rejected
EKF_NONFINITE = 4      # non-finite innovation or correction: rejected

#: chi-square quantiles, degrees of freedom 1..12 (scipy.stats.chi2.ppf)
CHI2_QUANTILES = {
    0.99: (6.6349, 9.2103, 11.3449, 13.2767, 15.0863, 16.8119, 18.4753, 20.0902, 21.666,
           23.2093, 24.725, 26.217),
    0.999: (10.8276, 13.8155, 16.2662, 18.4668, 20.515, 22.4577, 24.3219, 26.1245, 27.8772,
            29.5883, 31.2641, 32.9095),
    0.9999: (15.1367, 18.4207, 21.1075, 23.5127, 25.7448, 27.8563, 29.8775, 31.8276, 33.7199,
             35.564, 37.367, 39.1344),
}


def chi2_gate(dof: int, probability: float) -> float:
    """Gate threshold on the NIS; ``probability`` 1.0 (or above) disables the gate."""
    if probability >= 1.0:
        return math.inf
    try:
        return CHI2_QUANTILES[probability][dof - 1]
    except (KeyError, IndexError):
        raise ValueError(f"no chi-square quantile for p={probability}, dof={dof}; "
                         f"choose one of {sorted(CHI2_QUANTILES)}") from None


class KalmanUpdate:
    """Workspace of an ``m``-dimensional update of an ``n``-state filter.

    ``H`` (m, n), ``R`` (m, m) and ``y`` (m,) are public buffers the caller
    fills; :meth:`update` then corrects ``P`` (n, n) in place and writes the
    error-state correction into ``dx`` (n,). After a call, ``nis``, ``S``
    and ``K`` describe the update.
    """

    def __init__(self, n: int, m: int, gate_probability: float = 0.999, core=_DEFAULT_CORE):
        self.n = n
        self.m = m
        self.gate = chi2_gate(m, gate_probability)
        self.H = np.zeros((m, n))
        self.R = np.zeros((m, m))
        self.y = np.zeros(m)
        self.dx = np.zeros(n)
        self.S = np.zeros((m, m))
        self.Sinv = np.zeros((m, m))
        self.K = np.zeros((n, m))
        self._PHt = np.zeros((n, m))
        self._T = np.zeros((n, n))       # (I - K H) P
        self._TH = np.zeros((n, m))      # T H^T
        self._X = np.zeros((n, n))
        self._KR = np.zeros((n, m))
        self._w = np.zeros(m)            # S^-1 y
        self._half = np.full((), 0.5)
        self._Ht = self.H.T
        self._HP = self._PHt.T           # H P (P symmetric)
        self._Kt = self.K.T
        self._Tt = self._T.T
        self._s = flat(self.S)
        self._si = flat(self.Sinv)
        self._inv = spd_inverse(m)       # straight-line inverse for this m (linalg)
        self._yv = memoryview(self.y)
        self._wv = memoryview(self._w)
        self._dxv = memoryview(self.dx)
        # the update's count and rejections (int64: count, rejected) and its NIS, in arrays a compiled
        # kernel bound once updates in place (core/src/fusimu.c's one-call IMU sample); read and
        # written through the properties below as the attributes they stand for
        self.kst = np.zeros(2, dtype=np.int64)
        self._kstv = memoryview(self.kst)
        self._nis = np.zeros(1)
        self._nisv = memoryview(self._nis)
        #: the numeric core of :meth:`update`, bound once here (``coiltrack.firmware.core``)
        self.core = "python"
        ext = core.ext
        if ext is not None:
            # core/src/ekf.c ct_kalman_update: the same steps with H's structural zeros skipped
            # (equal to the BLAS products below to rounding; S's inverse is the same code)
            self._L = np.zeros((m, m))
            self._M = np.zeros((m, m))
            self._ck = ext.KUpdate(n, m, *self.buffers())
            self._sym = ext.symmetrize           # symmetrize's (core/src/sc_close.c): the same bits
            self.update = self._update_compiled
            self.core = "compiled"

    def _set_nis(self, v: float) -> None:
        self._nisv[0] = v

    def _set_count(self, v: int) -> None:
        self._kstv[0] = v

    def _set_rejected(self, v: int) -> None:
        self._kstv[1] = v

    nis = property(lambda self: self._nisv[0], _set_nis)                 # the last update's NIS
    count = property(lambda self: self._kstv[0], _set_count)             # updates applied
    rejected = property(lambda self: self._kstv[1], _set_rejected)       # updates rejected

    def buffers(self) -> tuple:
        """The compiled update's buffers in ``ext.KUpdate``'s order (``H``, ``R``, ``y``, ``dx``, ``S``,
        ``Sinv``, ``K``, then its scratch and the NIS), for a kernel that runs this update inside a
        larger call (``magnetic_inertial.FusionFilter``, ``ext.FusionUpdate``)."""
        return (self.H, self.R, self.y, self.dx, self.S, self.Sinv, self.K, self._PHt, self._T, self._TH, self._X,
                self._KR, self._w, self._L, self._M, self._nis)

    def _update_compiled(self, P: np.ndarray, gate: float | None = None) -> int:
        flags = self._ck.update(P, self.gate if gate is None else gate)
        if flags != EKF_OK:
            self.rejected += 1
            return flags
        self.count += 1
        if self.count % SYMMETRIZE_EVERY == 0 and not self._sym(P, self._T):
            symmetrize(P, self._T, self._Tt, self._half)
        return EKF_OK

    def counted(self, flags: int) -> int:
        """The bookkeeping of an update a compiled kernel ran with its symmetrisation (the count or the
        rejection, the NIS it wrote); returns ``flags``."""
        if flags != EKF_OK:
            self.rejected += 1
        else:
            self.count += 1
        return flags

    def add_counts(self, applied: int, rejected: int, nis: float) -> None:
        """The bookkeeping of updates a compiled kernel ran in one call (``applied`` applied,
        ``rejected`` rejected, the last one's NIS ``nis``)."""
        self.count += applied
        self.rejected += rejected
        self.nis = nis

    def update(self, P: np.ndarray, gate: float | None = None) -> int:
        """One update of ``P`` with the current ``H``, ``R``, ``y``; returns the
        health flags (``EKF_OK`` when applied). ``dx`` is zeroed when rejected.
        ``gate``: this update's NIS gate instead of ``self.gate`` (``math.inf``: ungated)."""
        m = self.m
        np.matmul(P, self._Ht, out=self._PHt)
        np.matmul(self.H, self._PHt, out=self.S)
        np.add(self.S, self.R, out=self.S)
        s = self._s
        # (the factorisation reads the lower triangle only)
        if not (_inv3(s, self._si) if m == 3 else self._inv(s, self._si)):
            self.dx.fill(0.0)
            self.rejected += 1
            self.nis = math.inf
            return EKF_NOT_PD
        np.matmul(self.Sinv, self.y, out=self._w)
        yv = self._yv
        wv = self._wv
        nis = 0.0
        for i in range(m):
            nis += yv[i] * wv[i]
        self.nis = nis
        if not math.isfinite(nis):
            self.dx.fill(0.0)
            self.rejected += 1
            return EKF_NONFINITE
        if nis > (self.gate if gate is None else gate):
            self.dx.fill(0.0)
            self.rejected += 1
            return EKF_GATED
        np.matmul(self._PHt, self.Sinv, out=self.K)
        np.matmul(self.K, self.y, out=self.dx)
        # Joseph form: P = (I - K H) P (I - K H)^T + K R K^T
        T, X = self._T, self._X
        np.matmul(self.K, self._HP, out=T)
        np.subtract(P, T, out=T)                 # T = (I - K H) P
        np.matmul(T, self._Ht, out=self._TH)
        np.matmul(self._TH, self._Kt, out=X)
        np.subtract(T, X, out=P)                 # P = T (I - K H)^T
        np.matmul(self.K, self.R, out=self._KR)
        np.matmul(self._KR, self._Kt, out=X)
        np.add(P, X, out=P)
        self.count += 1
        if self.count % SYMMETRIZE_EVERY == 0:
            symmetrize(P, self._T, self._Tt, self._half)
        return EKF_OK


def _inv3(s, out) -> bool:
    """``linalg.inv3_sym`` of the lower triangle of the flat 3x3 ``s`` into the
    flat ``out``; False when it is not positive definite."""
    inv = inv3_sym(s[0], s[3], s[6], s[4], s[7], s[8])
    if inv is None:
        return False
    out[0], out[1], out[2], out[4], out[5], out[8] = inv
    out[3], out[6], out[7] = inv[1], inv[2], inv[4]
    return True


def symmetrize(P: np.ndarray, tmp: np.ndarray, tmp_t: np.ndarray, half: np.ndarray) -> None:
    """``P = (P + P^T) / 2`` through ``tmp`` (``tmp_t`` is ``tmp.T``, made once)."""
    np.copyto(tmp, P)
    np.add(tmp, tmp_t, out=P)
    np.multiply(P, half, out=P)


class CovariancePredict:
    """Workspace for ``P = A P A^T + Q`` with ``A`` (n, n) and a diagonal or
    full ``Q`` (thesis eq 2.18 / 6.5, Fig. 4.3)."""

    def __init__(self, n: int, core=_DEFAULT_CORE):
        self.n = n
        self.A = np.eye(n)
        self.Q = np.zeros((n, n))
        self._At = self.A.T
        self._T = np.zeros((n, n))
        self._T2 = np.zeros((n, n))
        self._T2t = self._T2.T
        self._half = np.full((), 0.5)

        self.cst = np.zeros(1, dtype=np.int64)     # the count (int64, in place for a compiled kernel)
        self._cstv = memoryview(self.cst)
        #: the numeric core of :meth:`predict`, bound once here (``coiltrack.firmware.core``)
        self.core = "python"
        ext = core.ext
        if ext is not None:
            # core/src/ekf.c: the same product with A's structural zeros skipped (equal to the
            # BLAS products below to rounding); A, Q and the scratch are bound once
            self._ck = ext.CovPredict(n, self.A, self.Q, self._T)
            self.predict = self._predict_compiled
            self.core = "compiled"

    def _set_count(self, v: int) -> None:
        self._cstv[0] = v

    count = property(lambda self: self._cstv[0], _set_count)             # predictions run

    def _predict_compiled(self, P: np.ndarray) -> None:
        self._ck.predict(P)
        self.after_predict(P)

    def set_count(self, count: int) -> None:
        """The count after predictions a compiled kernel ran with their periodic symmetrisation
        (``core/src/fusion.c`` ``ct_fusion_replay``, as :meth:`after_predict` does it)."""
        self.count = count

    def after_predict(self, P: np.ndarray) -> None:
        """The bookkeeping after a compiled prediction of ``P`` (its count, and the periodic
        symmetrisation as :meth:`predict` does it)."""
        self.count += 1
        if self.count % SYMMETRIZE_EVERY == 0:
            symmetrize(P, self._T2, self._T2t, self._half)

    def predict(self, P: np.ndarray) -> None:
        np.matmul(self.A, P, out=self._T)
        np.matmul(self._T, self._At, out=P)
        np.add(P, self.Q, out=P)
        self.count += 1
        if self.count % SYMMETRIZE_EVERY == 0:
            symmetrize(P, self._T2, self._T2t, self._half)
