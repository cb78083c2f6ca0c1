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

:class:`RotationMargin` then adds to the position block what that linear
covariance leaves out at low signal-to-noise ratio: the second-order term of
the orientation error in the position (see the class).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.linalg import JACOBI_SWEEPS, inv3_sym, jacobi_eigh_of, spd_inverse

__all__ = ["MAX_VARIANCE", "MARGIN_MAX_ORI_VAR", "RobustInverse6", "RotationMargin"]

#: largest variance reported for an unobservable direction (m^2 or rad^2)
MAX_VARIANCE = 1e12
# relative eigenvalue floor of the information matrix
EIG_FLOOR = 1e-15
#: orientation variance (rad^2, trace of the orientation block) up to which the margin of
#: :class:`RotationMargin` follows the second-order expansion; beyond it (about 57 deg rss)
#: the expansion says nothing more and the margin stays at its value there
MARGIN_MAX_ORI_VAR = 1.0


class RobustInverse6:
    """Workspace for :meth:`into`: ``cov = robust (A)^-1`` of a 6x6 ``A``."""

    def __init__(self):
        self._m = memoryview(np.zeros(36))
        self._inv = spd_inverse(6)       # chol_inverse, straight-line (same bits)
        self._w = memoryview(np.zeros(6))
        self._V = memoryview(np.zeros(36))
        self._eigh = jacobi_eigh_of(6)     # jacobi_eigh(., 6, ...), made at start-up

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
        self._eigh(m, w, V, JACOBI_SWEEPS)
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


class RotationMargin:
    """The position variance the linearised covariance leaves out at large orientation errors.

    The covariance ``(H^T W H)^-1`` of a pose fit (``p``, ``dtheta``) is the first-order
    (Gauss-Newton) one: an orientation error ``theta`` of the solution comes with the position
    error ``K theta``, ``K = C_pt C_tt^-1``, and what is left, ``C_pp - K C_tp``, is the
    position's own uncertainty. A fusion filter that knows the orientation better than the
    solver leans on exactly that split (it reads the position error off the orientation error).
    The rotation enters the model through ``exp([theta]x) = I + [theta]x + [theta]x^2 / 2 + ...``
    (``R_true = R exp([dtheta]x)``, Schepers & Veltink ``000_e46ec0e8bf7ea271.txt`` eqs 5 and
    11): the second-order term is at most ``|theta| / 2`` of the first, so the position error
    that goes with ``theta`` is ``K theta`` give or take ``|theta| / 2 |K theta|``. Far from
    the source the orientation is known to 10-20 deg and that term is as large as the
    position's own uncertainty: a Monte Carlo of the solver alone (its own field model, the
    noise of roetenberg-fusion at 76 cm, 3000 draws) puts the position's distance from
    ``K theta``, against ``C_pp - K C_tp``, at a mean square of 4.0 (three degrees of
    freedom: 3.0), 6.5 when ``|theta|`` is 30-45 deg and 20 beyond 45 deg, although every
    solution is the cost's global minimum (a fit started at the true pose ends there too).

    Its covariance for a Gaussian ``theta ~ N(0, C_tt)`` (Isserlis:
    ``E[|theta|^2 theta theta^T] = tr(C_tt) C_tt + 2 C_tt^2``) is added to the position block::

        M = 1/4 K (tr(C_tt) C_tt + 2 C_tt^2) K^T = 1/4 (tr(C_tt) C_pt C_tt^-1 C_tp + 2 C_pt C_tp)

    like the linearisation margin a filter puts in its measurement noise
    (``estimate.single_coil_update``). It brings that mean square to 3.2-3.3 at 76 cm; it grows
    the conditional position variance ``C_pp - K C_tp`` by 47 % there, 10-20 % at 58-67 cm and
    under 2 % within 42 cm, where the orientation is known to a few degrees. Beyond
    ``MARGIN_MAX_ORI_VAR`` of orientation variance the expansion is meaningless and ``C_tt`` is
    taken scaled down to it
    (``M`` times ``(MARGIN_MAX_ORI_VAR / tr C_tt)^2``: at most 3/4 of the position variance
    the orientation explains). Allocation-free; ``pose.reference.rotation_margin`` is the
    numpy form."""

    def __init__(self):
        self._d = memoryview(np.zeros(9))

    def into(self, cov) -> None:
        """``cov`` (36, row-major, (p, dtheta)): its position block plus the margin, in place."""
        t00, t01, t02, t11, t12, t22 = cov[21], cov[22], cov[23], cov[28], cov[29], cov[35]
        tr = t00 + t11 + t22
        if not tr > 0.0 or not math.isfinite(tr):
            return
        inv = inv3_sym(t00, t01, t02, t11, t12, t22)
        if inv is None:
            return
        i00, i01, i02, i11, i12, i22 = inv
        s = MARGIN_MAX_ORI_VAR / tr if tr > MARGIN_MAX_ORI_VAR else 1.0
        a = 0.25 * tr * s * s           # of C_pt C_tt^-1 C_tp
        b = 0.5 * s * s                 # of C_pt C_tp
        for i in range(3):
            c0, c1, c2 = cov[6 * i + 3], cov[6 * i + 4], cov[6 * i + 5]        # row i of C_pt
            # row i of C_pt C_tt^-1
            k0 = c0 * i00 + c1 * i01 + c2 * i02
            k1 = c0 * i01 + c1 * i11 + c2 * i12
            k2 = c0 * i02 + c1 * i12 + c2 * i22
            for j in range(i, 3):
                d0, d1, d2 = cov[6 * j + 3], cov[6 * j + 4], cov[6 * j + 5]
                m = a * (k0 * d0 + k1 * d1 + k2 * d2) + b * (c0 * d0 + c1 * d1 + c2 * d2)
                cov[6 * i + j] += m
                if j != i:
                    cov[6 * j + i] += m

    def realized_into(self, C, t2: float, Phi, P, q0: int, scale: float) -> None:
        """The margin for an orientation error known to be ``|theta|^2 = t2`` (rad^2), for a filter
        that knows the orientation far better than the solver (the fusion filter's innovation
        ``log(Psi Theta^T)``, thesis ``002_cd7f1fdb7fc67471.txt`` eq 6.21): :meth:`into` put
        the expected ``|theta|^2 = tr(C_tt)`` in ``C``; where the solution's error is larger, the
        rest ``1/4 (t2 - tr C_tt) (C_pt C_tt^-1 C_tp + 2 C_pt C_tp / tr C_tt)`` (``t2`` at most
        ``MARGIN_MAX_ORI_VAR``), turned by ``Phi`` into the filter's frame and times ``scale``,
        is added to ``P[q0:q0+3, q0:q0+3]``: the margin's formula with the realized ``|theta|^2``
        in place of its expectation. It leaves the white position state less weight along the
        directions the orientation explains exactly when the solution is seen to lie in the tail
        (a 30-45 deg error where 13-21 deg is stated). roetenberg-fusion seed 4, 120 s: the
        fused poses over the 99.9 % bound went from 139 (the expected margin alone; 144 without
        either) to 0, fused RMS 27.7 -> 28.0 mm. (The solver-only Monte Carlo of the class
        docstring does not show that gain: there the conditional error beyond 45 deg lies mostly
        outside those directions, and its mean square stays about 21; why the filter gains this
        much is not established.)
        ``C`` (6, 6) as the solver's; nothing when ``t2`` is
        within the expected or the orientation block is degenerate."""
        tr = C[3, 3] + C[4, 4] + C[5, 5]
        t2 = t2 if t2 < MARGIN_MAX_ORI_VAR else MARGIN_MAX_ORI_VAR
        if not (tr > 0.0 and t2 > tr and math.isfinite(tr)):
            return
        inv = inv3_sym(C[3, 3], C[3, 4], C[3, 5], C[4, 4], C[4, 5], C[5, 5])
        if inv is None:
            return
        i00, i01, i02, i11, i12, i22 = inv
        f = 0.25 * (t2 - tr)
        g = 2.0 / tr
        d = self._d
        for i in range(3):
            c0, c1, c2 = C[i, 3], C[i, 4], C[i, 5]
            k0 = c0 * i00 + c1 * i01 + c2 * i02
            k1 = c0 * i01 + c1 * i11 + c2 * i12
            k2 = c0 * i02 + c1 * i12 + c2 * i22
            for j in range(i, 3):
                e0, e1, e2 = C[j, 3], C[j, 4], C[j, 5]
                v = f * (k0 * e0 + k1 * e1 + k2 * e2 + g * (c0 * e0 + c1 * e1 + c2 * e2))
                d[3 * i + j] = v
                d[3 * j + i] = v
        for i in range(3):
            for j in range(3):
                acc = 0.0
                for a in range(3):
                    for b in range(3):
                        acc += Phi[i, a] * d[3 * a + b] * Phi[j, b]
                P[q0 + i, q0 + j] += acc * scale
