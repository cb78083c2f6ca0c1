"""Robust inverse of the 6x6 information matrix, allocation-free.

The pose covariance is ``(H^T W H)^-1`` at the solution (the Cramer-Rao
bound of the Gaussian model). Directions the coils cannot observe make the
information matrix (nearly) singular; their eigenvalues are floored at
``max(1e-15 * max eigenvalue, 1 / MAX_VARIANCE)`` so the variance along them
is large but finite. The plain Cholesky inverse is used whenever it provably
satisfies that floor (``1 / tr(A^-1)`` is below the smallest eigenvalue),
otherwise the Jacobi eigen-decomposition; a non-finite matrix gives
``MAX_VARIANCE * I``. ``pose.reference._robust_inverse`` is the numpy form
the tests compare against.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.linalg import jacobi_eigh, spd_inverse

__all__ = ["MAX_VARIANCE", "RobustInverse6"]

#: largest variance reported for an unobservable direction (m^2 or rad^2)
MAX_VARIANCE = 1e12
# relative eigenvalue floor of the information matrix
EIG_FLOOR = 1e-15


class RobustInverse6:
    """Workspace for :meth:`into`: ``cov = robust (A)^-1`` of a 6x6 ``A``."""

    def __init__(self):
        self._m = memoryview(np.zeros(36))
        self._inv = spd_inverse(6)       # chol_inverse, straight-line (same bits)
        self._w = memoryview(np.zeros(6))
        self._V = memoryview(np.zeros(36))

    def into(self, a, cov) -> None:
        """``a`` (36, row-major, symmetric) -> ``cov`` (36)."""
        for i in range(36):
            if not math.isfinite(a[i]):
                for k in range(36):
                    cov[k] = MAX_VARIANCE if k % 7 == 0 else 0.0
                return
        tr = a[0] + a[7] + a[14] + a[21] + a[28] + a[35]
        floor_hi = max(EIG_FLOOR * max(tr, 0.0), 1.0 / MAX_VARIANCE)
        if self._inv(a, cov):
            tri = cov[0] + cov[7] + cov[14] + cov[21] + cov[28] + cov[35]
            if tri > 0.0 and 1.0 / tri >= floor_hi:
                return
        self._floored(a, cov)

    def _floored(self, a, cov) -> None:
        m, w, V = self._m, self._w, self._V
        for i in range(36):
            m[i] = a[i]
        jacobi_eigh(m, 6, w, V)
        top = w[5] if w[5] > 0.0 else 0.0
        floor = max(EIG_FLOOR * top, 1.0 / MAX_VARIANCE)
        for k in range(6):
            if w[k] < floor:
                w[k] = floor
        for i in range(6):
            for j in range(i, 6):
                acc = 0.0
                for k in range(6):
                    acc += V[i * 6 + k] * V[j * 6 + k] / w[k]
                cov[i * 6 + j] = acc
                cov[j * 6 + i] = acc
