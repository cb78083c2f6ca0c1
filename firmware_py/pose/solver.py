"""Allocation-free pose solver: the firmware's counterpart of ``solve.solve_pose``.

:class:`PoseSolver` is built once from the source coils and then solves one
signal matrix per call without creating any numpy array: it follows
``coiltrack.firmware.pose.reference.solve_pose`` step for step (that functional API stays the
reference this class is tested against, ``tests/firmware/test_solver.py``):

1. start (``solve._initial_pose``): Kuipers' closed form (thesis
   ``002_cd7f1fdb7fc67471.txt`` App. 5.A, eqs 5.9-5.34) applied to
   ``S M^+`` (``M`` the coil moments, ``M^+ = M^T (M M^T)^-1``); with the exact
   model within four coil radii of the source, the position is refined on the
   rotation invariant ``S^T S`` (thesis eq 5.15 without the dipole assumption)
   and, if that does not fit its noise level, searched on a grid of
   directions; the orientation then follows from the polar factor of
   ``B(p) S^T``;
2. Levenberg-Marquardt on ``sum ((S - h(p, R)) / sigma)^2`` with the exact
   loop model (Schepers & Veltink ``000_e46ec0e8bf7ea271.txt`` eqs 5-7,
   Jacobian eqs 9-11) or the dipole (eq 8), multiplicative orientation step
   ``R = R exp([d]x)``;
3. covariance ``(H^T W H)^-1`` at the solution, robust to unobservable
   directions exactly as ``solve._robust_inverse`` (eigenvalue floor, only
   taken when the plain Cholesky inverse would not already satisfy it).

Fields come from ``field.loop_point`` / ``field.dipole_point`` on Python
floats; the small systems use ``coiltrack.firmware.linalg``. Conventions are those of
``coiltrack.firmware.pose.reference``: ``S[:, j] = R^T B_j(p)`` in the sensor frame,
``R_true = R exp([dtheta]x)``, parameter order ``(p, dtheta)``.

Bad input never raises: :meth:`PoseSolver.solve` returns status flags.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.model.field import MU0, dipole_point, loop_point
from coiltrack.firmware.linalg import Rot3, chol_inverse, chol_solve, cholesky, flat, jacobi_eigh, nearest_rotation
from coiltrack.firmware.pose.reference import MAX_VARIANCE, _fibonacci_directions, so3_exp

# status flags (bit field)
SOLVE_OK = 0
SOLVE_BAD_INPUT = 1        # non-finite S, bad sigma or currents: nothing solved
SOLVE_NO_START = 2         # coil moments do not span 3-D and no x0: nothing solved
SOLVE_NOT_CONVERGED = 4    # LM stopped on its iteration or damping limit (result still written)
SOLVE_NONFINITE = 8        # the result is not finite

_MU0_4PI = MU0 / (4.0 * math.pi)
_EIG_FLOOR = 1e-15
_STEP_TOL = 1e-9
_COST_TOL = 1e-12
_NEAR_FIELD = 4.0
_GRID_DIRECTIONS = 512
_GRID_CANDIDATES = 3
_INV_ITERS = 15


def _damped(a, m, n: int, lam: float) -> None:
    """``m = a + lam * diag(a)`` for an n x n row-major ``a`` (Marquardt's
    scaling; a non-positive diagonal element is damped by ``lam``)."""
    for i in range(n * n):
        m[i] = a[i]
    for i in range(0, n * n, n + 1):
        da = a[i]
        if da <= 0.0:
            da = 1.0
        m[i] += lam * da


class PoseSolver:
    """Preallocated Kuipers + Levenberg-Marquardt pose solver.

    Parameters
    ----------
    coils : sequence of ``field.Coil``, length n
    model : {"exact", "dipole"}
    iters : int
        LM iteration limit (as ``solve_pose``).

    After :meth:`solve`: ``position`` (3,), ``rotation`` (3, 3),
    ``covariance`` (6, 6), ``iterations``, ``cost``, ``converged``.
    """

    def __init__(self, coils, model: str = "exact", iters: int = 20):
        if model not in ("exact", "dipole"):
            raise ValueError(f"unknown field model {model!r}")
        self.model = model
        self.exact = model == "exact"
        self.iters = int(iters)
        n = len(coils)
        if n < 1:
            raise ValueError("need at least one coil")
        self.n = n
        # coil geometry as Python floats (read in the inner loops)
        self._c = [tuple(float(v) for v in c.center) for c in coils]
        self._rot = [tuple(float(v) for v in c.rotation.reshape(9)) for c in coils]
        self._ax = [tuple(float(v) for v in c.axis) for c in coils]
        self._rad = [float(c.radius) for c in coils]
        self._spa = [MU0 * c.turns / (2.0 * math.pi * c.radius) for c in coils]   # field scale per A
        self._mpa = [c.turns * math.pi * c.radius * c.radius for c in coils]      # moment per A
        centers = np.array([c.center for c in coils], dtype=float)
        cbar = centers.mean(axis=0)
        self._cbar = tuple(float(v) for v in cbar)
        self._reach = float(max(c.radius for c in coils)) + float(np.linalg.norm(centers - cbar, axis=1).max())
        # results
        self.position = np.zeros(3)
        self.rotation = np.eye(3)
        self.covariance = np.zeros((6, 6))
        self.iterations = 0
        self.cost = 0.0
        self.converged = False
        self.status = SOLVE_OK
        self._pv = memoryview(self.position)
        self._Rv = memoryview(self.rotation)
        self._cov = flat(self.covariance)
        # per-solve inputs, copied in
        self._S = np.zeros((3, n))
        self._w = np.zeros((3, n))
        self._cur = np.zeros(n)
        self._Sv = flat(self._S)
        self._wv = flat(self._w)
        self._curv = memoryview(self._cur)
        # model buffers: h (3, n) and H (3n, 6), current and trial
        self._h = [np.zeros(3 * n), np.zeros(3 * n)]
        self._H = [np.zeros(3 * n * 6), np.zeros(3 * n * 6)]
        self._hv = [memoryview(a) for a in self._h]
        self._Hv = [memoryview(a) for a in self._H]
        self._B = np.zeros(3 * n)                 # source-frame fields of the coils
        self._J = np.zeros(9 * n)                 # source-frame gradients (3x3 per coil)
        self._Bv = memoryview(self._B)
        self._Jv = memoryview(self._J)
        # state of the LM
        self._p = np.zeros(3)
        self._p_t = np.zeros(3)
        self._R = np.zeros((3, 3))
        self._R_t = np.zeros((3, 3))
        self._dR = np.zeros((3, 3))
        self._R_tmp = np.zeros((3, 3))
        self._A6 = np.zeros(36)
        self._M6 = np.zeros(36)
        self._L6 = np.zeros(36)
        self._g6 = np.zeros(6)
        self._d6 = np.zeros(6)
        self._e6 = np.zeros(6)
        self._V6 = np.zeros(36)
        self._a6 = memoryview(self._A6)
        self._m6 = memoryview(self._M6)
        self._l6 = memoryview(self._L6)
        self._g6v = memoryview(self._g6)
        self._d6v = memoryview(self._d6)
        self._e6v = memoryview(self._e6)
        self._v6 = memoryview(self._V6)
        # Kuipers and invariant buffers
        self._k3 = np.zeros(9)
        self._kv3 = np.zeros(9)
        self._kw3 = np.zeros(3)
        self._k3v = memoryview(self._k3)
        self._kv3v = memoryview(self._kv3)
        self._kw3v = memoryview(self._kw3)
        self._m9 = np.zeros(9)
        self._m9v = memoryview(self._m9)
        self._mpinv = np.zeros(3 * n)             # M^+ (n, 3), row-major
        self._mpv = memoryview(self._mpinv)
        self._S3 = np.zeros(9)
        self._S3v = memoryview(self._S3)
        self._Um = np.zeros(n * n)
        self._Umv = memoryview(self._Um)
        self._rot3 = Rot3()
        self._dR_buf = self._dR
        self._grid = _fibonacci_directions(_GRID_DIRECTIONS)
        self._gridv = flat(self._grid)
        self._cand_p = np.zeros(3 * _GRID_CANDIDATES)
        self._cand_m = np.zeros(_GRID_CANDIDATES)
        self._cpv = memoryview(self._cand_p)
        self._cmv = memoryview(self._cand_m)
        self._ip = np.zeros(3)
        self._ipv = memoryview(self._ip)
        self._inv_scale = 1.0
        # element access goes through memoryviews (Python floats, no numpy scalars)
        self._pm = memoryview(self._p)
        self._ptm = memoryview(self._p_t)
        self._Rm = memoryview(self._R)
        self._Rtm = memoryview(self._R_t)

    # ------------------------------------------------------------ fields
    def _fields(self, px, py, pz, jac):
        """Source-frame field (and gradient) of every coil at (px, py, pz)
        into ``_B`` / ``_J``, using the current ``_cur``."""
        Bv = self._Bv
        Jv = self._Jv
        cur = self._curv
        exact = self.exact
        for j in range(self.n):
            cx, cy, cz = self._c[j]
            dx = px - cx
            dy = py - cy
            dz = pz - cz
            I = cur[j]
            if exact:
                r00, r01, r02, r10, r11, r12, r20, r21, r22 = self._rot[j]
                # coil-frame point: R_j^T d
                x = r00 * dx + r10 * dy + r20 * dz
                y = r01 * dx + r11 * dy + r21 * dz
                z = r02 * dx + r12 * dy + r22 * dz
                t = loop_point(x, y, z, self._rad[j], self._spa[j] * I, jac)
                bx, by, bz = t[0], t[1], t[2]
                Bv[3 * j] = r00 * bx + r01 * by + r02 * bz
                Bv[3 * j + 1] = r10 * bx + r11 * by + r12 * bz
                Bv[3 * j + 2] = r20 * bx + r21 * by + r22 * bz
                if jac:
                    jxx, jyy, jzz, jxy, jxz, jyz = t[3], t[4], t[5], t[6], t[7], t[8]
                    # R_j Jc R_j^T: first T = R_j Jc
                    t00 = r00 * jxx + r01 * jxy + r02 * jxz
                    t01 = r00 * jxy + r01 * jyy + r02 * jyz
                    t02 = r00 * jxz + r01 * jyz + r02 * jzz
                    t10 = r10 * jxx + r11 * jxy + r12 * jxz
                    t11 = r10 * jxy + r11 * jyy + r12 * jyz
                    t12 = r10 * jxz + r11 * jyz + r12 * jzz
                    t20 = r20 * jxx + r21 * jxy + r22 * jxz
                    t21 = r20 * jxy + r21 * jyy + r22 * jyz
                    t22 = r20 * jxz + r21 * jyz + r22 * jzz
                    o = 9 * j
                    Jv[o] = t00 * r00 + t01 * r01 + t02 * r02
                    Jv[o + 1] = t00 * r10 + t01 * r11 + t02 * r12
                    Jv[o + 2] = t00 * r20 + t01 * r21 + t02 * r22
                    Jv[o + 3] = t10 * r00 + t11 * r01 + t12 * r02
                    Jv[o + 4] = t10 * r10 + t11 * r11 + t12 * r12
                    Jv[o + 5] = t10 * r20 + t11 * r21 + t12 * r22
                    Jv[o + 6] = t20 * r00 + t21 * r01 + t22 * r02
                    Jv[o + 7] = t20 * r10 + t21 * r11 + t22 * r12
                    Jv[o + 8] = t20 * r20 + t21 * r21 + t22 * r22
            else:
                ax, ay, az = self._ax[j]
                m = self._mpa[j] * I
                t = dipole_point(dx, dy, dz, ax * m, ay * m, az * m, jac)
                Bv[3 * j] = t[0]
                Bv[3 * j + 1] = t[1]
                Bv[3 * j + 2] = t[2]
                if jac:
                    o = 9 * j
                    Jv[o] = t[3]
                    Jv[o + 4] = t[4]
                    Jv[o + 8] = t[5]
                    Jv[o + 1] = Jv[o + 3] = t[6]
                    Jv[o + 2] = Jv[o + 6] = t[7]
                    Jv[o + 5] = Jv[o + 7] = t[8]

    def _evaluate(self, p, R, k):
        """Model ``h`` and Jacobian ``H`` at pose (p, R) into buffer set ``k``;
        returns the weighted cost. ``h[i * n + j]``; ``H`` row ``i * n + j``."""
        n = self.n
        self._fields(p[0], p[1], p[2], True)
        Bv = self._Bv
        Jv = self._Jv
        hv = self._hv[k]
        Hv = self._Hv[k]
        Sv = self._Sv
        wv = self._wv
        r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
        r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
        r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
        cost = 0.0
        for j in range(n):
            bx, by, bz = Bv[3 * j], Bv[3 * j + 1], Bv[3 * j + 2]
            # h_j = R^T B_j
            hx = r00 * bx + r10 * by + r20 * bz
            hy = r01 * bx + r11 * by + r21 * bz
            hz = r02 * bx + r12 * by + r22 * bz
            hv[j] = hx
            hv[n + j] = hy
            hv[2 * n + j] = hz
            o = 9 * j
            j00, j01, j02 = Jv[o], Jv[o + 1], Jv[o + 2]
            j10, j11, j12 = Jv[o + 3], Jv[o + 4], Jv[o + 5]
            j20, j21, j22 = Jv[o + 6], Jv[o + 7], Jv[o + 8]
            # rows i of R^T J_j, then [h_j]x
            for i in range(3):
                ri0 = R[0, i]
                ri1 = R[1, i]
                ri2 = R[2, i]
                row = 6 * (i * n + j)
                Hv[row] = ri0 * j00 + ri1 * j10 + ri2 * j20
                Hv[row + 1] = ri0 * j01 + ri1 * j11 + ri2 * j21
                Hv[row + 2] = ri0 * j02 + ri1 * j12 + ri2 * j22
            row = 6 * j
            Hv[row + 3] = 0.0
            Hv[row + 4] = -hz
            Hv[row + 5] = hy
            row = 6 * (n + j)
            Hv[row + 3] = hz
            Hv[row + 4] = 0.0
            Hv[row + 5] = -hx
            row = 6 * (2 * n + j)
            Hv[row + 3] = -hy
            Hv[row + 4] = hx
            Hv[row + 5] = 0.0
        for q in range(3 * n):
            rr = (Sv[q] - hv[q]) * wv[q]
            cost += rr * rr
        return cost

    def _normal_equations(self, k):
        """``A = Jw^T Jw`` into ``_A6`` and ``g = Jw^T rw`` into ``_g6``."""
        a = self._a6
        g = self._g6v
        for i in range(36):
            a[i] = 0.0
        for i in range(6):
            g[i] = 0.0
        hv = self._hv[k]
        Hv = self._Hv[k]
        Sv = self._Sv
        wv = self._wv
        for q in range(3 * self.n):
            w = wv[q]
            w2 = w * w
            rr = (Sv[q] - hv[q]) * w2
            o = 6 * q
            h0, h1, h2, h3, h4, h5 = Hv[o], Hv[o + 1], Hv[o + 2], Hv[o + 3], Hv[o + 4], Hv[o + 5]
            g[0] += h0 * rr
            g[1] += h1 * rr
            g[2] += h2 * rr
            g[3] += h3 * rr
            g[4] += h4 * rr
            g[5] += h5 * rr
            a0 = h0 * w2
            a1 = h1 * w2
            a2 = h2 * w2
            a3 = h3 * w2
            a4 = h4 * w2
            a[0] += a0 * h0
            a[1] += a0 * h1
            a[2] += a0 * h2
            a[3] += a0 * h3
            a[4] += a0 * h4
            a[5] += a0 * h5
            a[7] += a1 * h1
            a[8] += a1 * h2
            a[9] += a1 * h3
            a[10] += a1 * h4
            a[11] += a1 * h5
            a[14] += a2 * h2
            a[15] += a2 * h3
            a[16] += a2 * h4
            a[17] += a2 * h5
            a[21] += a3 * h3
            a[22] += a3 * h4
            a[23] += a3 * h5
            a[28] += a4 * h4
            a[29] += a4 * h5
            a[35] += h5 * h5 * w2
        for i in range(6):
            for j in range(i):
                a[i * 6 + j] = a[j * 6 + i]

    # ------------------------------------------------------------- start
    def _kuipers_start(self, hx, hy, hz) -> bool:
        """Kuipers closed form on ``S M^+`` into ``_p``, ``_R`` (solve._initial_guess
        and solve.kuipers with unit moments). False if the moments do not span 3-D."""
        n = self.n
        cur = self._curv
        mp = self._mpv
        mm = self._m9v
        # M (3, n): column j = axis_j * m_j * I_j; G = M M^T
        for a in range(9):
            mm[a] = 0.0
        for j in range(n):
            ax, ay, az = self._ax[j]
            s = self._mpa[j] * cur[j]
            m0, m1, m2 = ax * s, ay * s, az * s
            mm[0] += m0 * m0
            mm[1] += m0 * m1
            mm[2] += m0 * m2
            mm[4] += m1 * m1
            mm[5] += m1 * m2
            mm[8] += m2 * m2
        mm[3] = mm[1]
        mm[6] = mm[2]
        mm[7] = mm[5]
        # rank test as solve._initial_guess: smallest singular value of M
        k3 = self._k3v
        for a in range(9):
            k3[a] = mm[a]
        jacobi_eigh(k3, 3, self._kw3v, self._kv3v)
        w = self._kw3v
        if not (w[0] > 0.0 and math.sqrt(w[0]) > 1e-9 * math.sqrt(max(w[2], 0.0))):
            return False
        # G^-1 into k3 (3x3 inverse through Cholesky)
        if not chol_inverse(mm, 3, k3, self._l6):
            return False
        # M^+ = M^T G^-1 (n, 3)
        for j in range(n):
            ax, ay, az = self._ax[j]
            s = self._mpa[j] * cur[j]
            m0, m1, m2 = ax * s, ay * s, az * s
            for c in range(3):
                mp[3 * j + c] = m0 * k3[c] + m1 * k3[3 + c] + m2 * k3[6 + c]
        # S3 = S M^+ (3, 3)
        Sv = self._Sv
        S3 = self._S3v
        for i in range(3):
            for c in range(3):
                acc = 0.0
                for j in range(n):
                    acc += Sv[i * n + j] * mp[3 * j + c]
                S3[3 * i + c] = acc
        # U = S3^T S3, k = sqrt(tr U / 6)
        tr = 0.0
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for i in range(3):
                    acc += S3[3 * i + a] * S3[3 * i + b]
                k3[3 * a + b] = acc
            tr += k3[4 * a]
        k = math.sqrt(max(tr / 6.0, 0.0))
        k = max(k, 1e-300)
        jacobi_eigh(k3, 3, self._kw3v, self._kv3v)
        v = self._kv3v
        ux, uy, uz = v[2], v[5], v[8]
        if ux * hx + uy * hy + uz * hz < 0.0:
            ux, uy, uz = -ux, -uy, -uz
        r = (_MU0_4PI / k) ** (1.0 / 3.0)
        # A = 1.5 u u^T - I; R = polar(A S3^T / k)
        u = (ux, uy, uz)
        for i in range(3):
            for c in range(3):
                acc = 0.0
                for l in range(3):
                    a_il = 1.5 * u[i] * u[l] - (1.0 if i == l else 0.0)
                    acc += a_il * S3[3 * c + l]
                mm[3 * i + c] = acc / k
        nearest_rotation(mm, self._R, self._rot3)
        cx, cy, cz = self._cbar
        p = self._pm
        p[0] = r * ux + cx
        p[1] = r * uy + cy
        p[2] = r * uz + cz
        return True

    def _invariant_residual(self, px, py, pz, k):
        """Residual of ``U = S^T S`` against ``B(p)^T B(p)`` (upper triangle,
        scaled by 1/tr U) and its Jacobian's normal equations into ``_A6[:9]``
        (3x3) and ``_g6[:3]``, for solve._refine_position_invariants. Returns
        the cost; ``k`` selects whether normal equations are formed."""
        n = self.n
        self._fields(px, py, pz, k)
        Bv = self._Bv
        Jv = self._Jv
        Um = self._Umv
        scale = self._inv_scale
        a = self._a6
        g = self._g6v
        if k:
            for i in range(9):
                a[i] = 0.0
            g[0] = g[1] = g[2] = 0.0
        cost = 0.0
        for i in range(n):
            bi0, bi1, bi2 = Bv[3 * i], Bv[3 * i + 1], Bv[3 * i + 2]
            for j in range(i, n):
                bj0, bj1, bj2 = Bv[3 * j], Bv[3 * j + 1], Bv[3 * j + 2]
                r = (Um[i * n + j] - (bi0 * bj0 + bi1 * bj1 + bi2 * bj2)) * scale
                cost += r * r
                if k:
                    oi = 9 * i
                    oj = 9 * j
                    # dU_ij/dp_c = J_i[:, c] . B_j + B_i . J_j[:, c]; Jr = -dU * scale
                    d0 = -(Jv[oi] * bj0 + Jv[oi + 3] * bj1 + Jv[oi + 6] * bj2
                           + bi0 * Jv[oj] + bi1 * Jv[oj + 3] + bi2 * Jv[oj + 6]) * scale
                    d1 = -(Jv[oi + 1] * bj0 + Jv[oi + 4] * bj1 + Jv[oi + 7] * bj2
                           + bi0 * Jv[oj + 1] + bi1 * Jv[oj + 4] + bi2 * Jv[oj + 7]) * scale
                    d2 = -(Jv[oi + 2] * bj0 + Jv[oi + 5] * bj1 + Jv[oi + 8] * bj2
                           + bi0 * Jv[oj + 2] + bi1 * Jv[oj + 5] + bi2 * Jv[oj + 8]) * scale
                    a[0] += d0 * d0
                    a[1] += d0 * d1
                    a[2] += d0 * d2
                    a[4] += d1 * d1
                    a[5] += d1 * d2
                    a[8] += d2 * d2
                    # normal equations right side: -Jr^T r
                    g[0] -= d0 * r
                    g[1] -= d1 * r
                    g[2] -= d2 * r
        if k:
            a[3] = a[1]
            a[6] = a[2]
            a[7] = a[5]
        return cost

    def _refine_invariants(self, ip):
        """solve._refine_position_invariants on ``ip`` (3 floats, in place);
        returns sqrt(cost)."""
        px, py, pz = ip[0], ip[1], ip[2]
        cost = self._invariant_residual(px, py, pz, True)
        lam = 1e-3
        a = self._a6
        m = self._m6
        L = self._l6
        g = self._g6v
        d = self._d6v
        for _ in range(_INV_ITERS):
            _damped(a, m, 3, lam)
            if not cholesky(m, 3, L):
                break
            d[0], d[1], d[2] = g[0], g[1], g[2]
            chol_solve(L, 3, d, d)
            d0, d1, d2 = d[0], d[1], d[2]
            if not (math.isfinite(d0) and math.isfinite(d1) and math.isfinite(d2)):
                break
            # keep the accepted normal equations: the trial evaluation overwrites them
            for i in range(9):
                m[i] = a[i]
            g0, g1, g2 = g[0], g[1], g[2]
            ct = self._invariant_residual(px + d0, py + d1, pz + d2, True)
            if math.isfinite(ct) and ct < cost:
                px += d0
                py += d1
                pz += d2
                cost = ct
                lam = max(lam * 0.1, 1e-12)
                if math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) <= 1e-9 * math.sqrt(px * px + py * py + pz * pz):
                    break
            else:
                for i in range(9):
                    a[i] = m[i]
                g[0], g[1], g[2] = g0, g1, g2
                lam *= 10.0
                if lam > 1e8:
                    break
        ip[0], ip[1], ip[2] = px, py, pz
        return math.sqrt(cost)

    def _orientation_from_position(self, px, py, pz):
        """``R = polar(B(p) S^T)`` (as ``_nearest_rotation(B.T @ S.T)``) into ``_R``."""
        n = self.n
        self._fields(px, py, pz, False)
        Bv = self._Bv
        Sv = self._Sv
        mm = self._m9v
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for j in range(n):
                    acc += Bv[3 * j + a] * Sv[b * n + j]
                mm[3 * a + b] = acc
        nearest_rotation(mm, self._R, self._rot3)

    def _initial_pose(self, hx, hy, hz, sigma_rms) -> bool:
        """solve._initial_pose: Kuipers, then (exact model, near field) the
        invariant refinement and the grid search."""
        if not self._kuipers_start(hx, hy, hz):
            return False
        if not self.exact:
            return True
        p = self._pm
        cx, cy, cz = self._cbar
        dx, dy, dz = p[0] - cx, p[1] - cy, p[2] - cz
        r0 = math.sqrt(dx * dx + dy * dy + dz * dz)
        if r0 >= _NEAR_FIELD * self._reach or not (math.isfinite(r0)):
            return True
        n = self.n
        Sv = self._Sv
        Um = self._Umv
        tr_m = 0.0
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for a in range(3):
                    acc += Sv[a * n + i] * Sv[a * n + j]
                Um[i * n + j] = acc
            tr_m += Um[i * n + i]
        self._inv_scale = 1.0 / tr_m
        ip = self._ipv
        ip[0], ip[1], ip[2] = p[0], p[1], p[2]
        best_m = self._refine_invariants(ip)
        bx, by, bz = ip[0], ip[1], ip[2]
        tol = 20.0 * sigma_rms / math.sqrt(max(tr_m, 1e-300)) + 1e-9
        if best_m <= tol:
            p[0], p[1], p[2] = bx, by, bz
            self._orientation_from_position(bx, by, bz)
            return True
        # grid search in the hemisphere, radius from the trace (power law tr U ~ r^-6)
        gv = self._gridv
        cm = self._cmv
        cp = self._cpv
        for c in range(_GRID_CANDIDATES):
            cm[c] = math.inf
        use_h = hx != 0.0 or hy != 0.0 or hz != 0.0
        Bv = self._Bv
        lo, hi = 0.25 * r0, 4.0 * r0
        for k in range(_GRID_DIRECTIONS):
            ux, uy, uz = gv[3 * k], gv[3 * k + 1], gv[3 * k + 2]
            if use_h and ux * hx + uy * hy + uz * hz < 0.0:
                continue
            rad = r0
            for _ in range(2):
                self._fields(cx + ux * rad, cy + uy * rad, cz + uz * rad, False)
                tr = 0.0
                for q in range(3 * n):
                    tr += Bv[q] * Bv[q]
                f = (tr / tr_m) ** (1.0 / 6.0) if tr > 0.0 else 0.0
                rad = rad * f if math.isfinite(f) else rad
                rad = min(max(rad, lo), hi) if math.isfinite(rad) else lo
            px, py, pz = cx + ux * rad, cy + uy * rad, cz + uz * rad
            self._fields(px, py, pz, False)
            mis = 0.0
            for i in range(n):
                for j in range(n):
                    u_ij = Bv[3 * i] * Bv[3 * j] + Bv[3 * i + 1] * Bv[3 * j + 1] + Bv[3 * i + 2] * Bv[3 * j + 2]
                    e = u_ij - Um[i * n + j]
                    mis += e * e
            mis = math.sqrt(mis) / tr_m
            if not math.isfinite(mis):
                continue
            # keep the best few (insertion into a sorted short list)
            if mis < cm[_GRID_CANDIDATES - 1]:
                c = _GRID_CANDIDATES - 1
                while c > 0 and mis < cm[c - 1]:
                    cm[c] = cm[c - 1]
                    cp[3 * c], cp[3 * c + 1], cp[3 * c + 2] = cp[3 * c - 3], cp[3 * c - 2], cp[3 * c - 1]
                    c -= 1
                cm[c] = mis
                cp[3 * c], cp[3 * c + 1], cp[3 * c + 2] = px, py, pz
        for c in range(_GRID_CANDIDATES):
            if not math.isfinite(cm[c]):
                break
            ip[0], ip[1], ip[2] = cp[3 * c], cp[3 * c + 1], cp[3 * c + 2]
            mc = self._refine_invariants(ip)
            if mc < best_m:
                best_m = mc
                bx, by, bz = ip[0], ip[1], ip[2]
        p[0], p[1], p[2] = bx, by, bz
        self._orientation_from_position(bx, by, bz)
        return True

    # ------------------------------------------------------------- solve
    def solve(self, S, currents, sigma, hemisphere=None, x0_position=None, x0_rotation=None) -> int:
        """Solve one signal matrix; returns status flags (``SOLVE_OK`` = 0).

        Parameters
        ----------
        S : ndarray (3, n)
            Signal matrix, T, sensor frame.
        currents : ndarray (n,)
            A.
        sigma : ndarray (3, n)
            Standard deviation of each element of ``S``, T (> 0).
        hemisphere : ndarray (3,), optional
            Kuipers mirror selection (default +x).
        x0_position, x0_rotation : ndarray (3,), (3, 3), optional
            Start instead of Kuipers (both or neither).
        """
        n = self.n
        Sv = self._Sv
        wv = self._wv
        cur = self._curv
        ssum = 0.0
        for i in range(3):
            for j in range(n):
                s = S[i, j]
                sg = sigma[i, j]
                if not (math.isfinite(s) and math.isfinite(sg) and sg > 0.0):
                    self.status = SOLVE_BAD_INPUT
                    return SOLVE_BAD_INPUT
                Sv[i * n + j] = s
                wv[i * n + j] = 1.0 / sg
                ssum += sg * sg
        for j in range(n):
            c = currents[j]
            if not math.isfinite(c):
                self.status = SOLVE_BAD_INPUT
                return SOLVE_BAD_INPUT
            cur[j] = c
        p = self._pm
        R = self._R
        if x0_position is None:
            if hemisphere is None:
                hx, hy, hz = 1.0, 0.0, 0.0
            else:
                hx, hy, hz = hemisphere[0], hemisphere[1], hemisphere[2]
            if not self._initial_pose(hx, hy, hz, math.sqrt(ssum / (3 * n))):
                self.status = SOLVE_NO_START
                return SOLVE_NO_START
        else:
            for i in range(3):
                p[i] = x0_position[i]
            m9 = self._m9v
            for i in range(3):
                for j in range(3):
                    m9[3 * i + j] = x0_rotation[i, j]
            nearest_rotation(m9, R, self._rot3)
        status = self._lm()
        self.status = status
        return status

    def _lm(self) -> int:
        p = self._pm
        p_t = self._ptm
        cur_k = 0
        cost = self._evaluate(p, self._Rm, cur_k)
        lam = 1e-6
        converged = False
        a = self._a6
        m = self._m6
        L = self._l6
        d = self._d6v
        it = 0
        for it in range(1, self.iters + 1):
            self._normal_equations(cur_k)
            _damped(a, m, 6, lam)
            if not cholesky(m, 6, L):
                lam *= 10.0
                if lam > 1e12:
                    break
                continue
            chol_solve(L, 6, self._g6v, d)
            d0, d1, d2, d3, d4, d5 = d[0], d[1], d[2], d[3], d[4], d[5]
            if not (math.isfinite(d0) and math.isfinite(d1) and math.isfinite(d2)
                    and math.isfinite(d3) and math.isfinite(d4) and math.isfinite(d5)):
                break
            p_t[0] = p[0] + d0
            p_t[1] = p[1] + d1
            p_t[2] = p[2] + d2
            so3_exp(self._e6v_rot(d3, d4, d5), out=self._dR)
            np.matmul(self._R, self._dR, out=self._R_t)
            cost_t = self._evaluate(p_t, self._Rtm, 1 - cur_k)
            pn = math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
            small = (math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) <= _STEP_TOL * max(pn, 1e-3)
                     and math.sqrt(d3 * d3 + d4 * d4 + d5 * d5) <= _STEP_TOL)
            if math.isfinite(cost_t) and cost_t <= cost:
                np.copyto(self._p, self._p_t)
                np.copyto(self._R, self._R_t)
                cur_k = 1 - cur_k
                rel = (cost - cost_t) / max(cost, 1e-300)
                cost = cost_t
                lam = max(lam * 0.1, 1e-12)
                if small or rel < _COST_TOL:
                    converged = True
                    break
            else:
                if small:
                    converged = True
                    break
                lam *= 10.0
                if lam > 1e12:
                    break
        # re-orthonormalise once, as solve_pose
        m9 = self._m9v
        R = self._Rm
        for i in range(3):
            for j in range(3):
                m9[3 * i + j] = R[i, j]
        nearest_rotation(m9, self.rotation, self._rot3)
        np.copyto(self.position, self._p)
        self._normal_equations(cur_k)
        self._robust_inverse()
        self.iterations = it
        self.cost = cost
        self.converged = converged
        status = SOLVE_OK if converged else SOLVE_NOT_CONVERGED
        pv = self._pv
        if not (math.isfinite(pv[0]) and math.isfinite(pv[1]) and math.isfinite(pv[2])
                and math.isfinite(self._cov[0])):
            status |= SOLVE_NONFINITE
        return status

    def _e6v_rot(self, d3, d4, d5):
        e = self._e6v
        e[0], e[1], e[2] = d3, d4, d5
        return e

    def _robust_inverse(self) -> None:
        """solve._robust_inverse of ``_A6`` into ``covariance``: the plain
        inverse when every eigenvalue is provably above the floor
        ``max(1e-15 max eig, 1 / MAX_VARIANCE)``, else the eigen-floored one."""
        a = self._a6
        cov = self._cov
        for i in range(36):
            if not math.isfinite(a[i]):
                for k in range(36):
                    cov[k] = MAX_VARIANCE if k % 7 == 0 else 0.0
                return
        tr = a[0] + a[7] + a[14] + a[21] + a[28] + a[35]
        floor_hi = max(_EIG_FLOOR * max(tr, 0.0), 1.0 / MAX_VARIANCE)
        if chol_inverse(a, 6, cov, self._l6):
            tri = cov[0] + cov[7] + cov[14] + cov[21] + cov[28] + cov[35]
            if tri > 0.0 and 1.0 / tri >= floor_hi:
                return
        m = self._m6
        for i in range(36):
            m[i] = a[i]
        w = self._e6v
        V = self._v6
        jacobi_eigh(m, 6, w, V)
        top = w[5] if w[5] > 0.0 else 0.0
        floor = max(_EIG_FLOOR * top, 1.0 / MAX_VARIANCE)
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

    # ------------------------------------------------------------ model
    def predict_signals(self, p, R, currents, out) -> None:
        """Model signal matrix ``out[:, j] = R^T B_j(p)`` (3, n) for the given
        currents (used to bring pulses to a common instant, ``fusion``)."""
        n = self.n
        cur = self._curv
        for j in range(n):
            cur[j] = currents[j]
        self._fields(p[0], p[1], p[2], False)
        Bv = self._Bv
        for j in range(n):
            bx, by, bz = Bv[3 * j], Bv[3 * j + 1], Bv[3 * j + 2]
            for i in range(3):
                out[i, j] = R[0, i] * bx + R[1, i] * by + R[2, i] * bz
