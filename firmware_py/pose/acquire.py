"""Acquisition: a start for the pose fit from one signal matrix, no prior.

Follows ``pose.reference._initial_pose`` (the numpy reference), staged into
units of at most ``n`` field evaluations (``pose.staged``; the three
closed-form units evaluate no field and are charged ``n`` for their run
time):

1. Kuipers' closed form (thesis ``seeds/002_cd7f1fdb7fc67471.txt``
   App. 5.A, eqs 5.9-5.34) applied to ``S M^+`` (``M`` the coil moments,
   ``M^+ = M^T (M M^T)^-1``): exact for dipoles at a common centre; three
   units (``M^+``, the position, the orientation).
2. Exact model within ``NEAR_FIELD`` coil radii of the source only: the
   position is refined on the rotation invariant ``U = S^T S = B(p)^T B(p)``
   (thesis eq 5.15 without the dipole assumption) by the shared
   Levenberg-Marquardt (``pose.lm``, 3 parameters; one unit = one step =
   ``n`` evaluations).
3. If that does not fit its noise level: a grid of ``GRID_DIRECTIONS``
   directions in the hemisphere, each at the radius matching ``tr U``
   (power law ``tr U ~ r^-6``, two steps) and scored by the misfit of ``U``
   (three units of ``n`` evaluations per direction); the best
   ``GRID_CANDIDATES`` are refined as in 2.
4. The orientation from the position in closed form (orthogonal
   Procrustes, ``R = polar(B(p) S^T)``; ``n`` evaluations).

Signals are in the solver's layout ``S[3 j + i]`` (component ``i`` of coil
``j``, sensor frame, T); the result is ``p`` (3,) and ``R`` (3, 3).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.linalg import JACOBI_SWEEPS, Rot3, atb3, chol_inverse, flat, jacobi_eigh_of, nearest_rotation
from coiltrack.firmware.model.field import MU0
from coiltrack.firmware.pose.lm import LM_RUNNING, LevenbergMarquardt
from coiltrack.firmware.pose.staged import Staged

__all__ = ["Acquisition", "fibonacci_directions", "NEAR_FIELD", "GRID_DIRECTIONS", "GRID_CANDIDATES"]

#: mu0 / 4 pi, T m / A (the compiled acquisition's too)
MU0_4PI = MU0 / (4.0 * math.pi)
#: below this many coil radii (plus the centre spread) the exact model
#: replaces the Kuipers start by the search on the invariants
NEAR_FIELD = 4.0
GRID_DIRECTIONS = 512          # over the sphere, half of them per hemisphere
GRID_CANDIDATES = 3
_INV_ITERS = 15


def fibonacci_directions(n: int) -> np.ndarray:
    """``n`` nearly uniform unit vectors on the sphere, shape (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    rxy = np.sqrt(1.0 - z * z)
    phi = i * (math.pi * (3.0 - math.sqrt(5.0)))
    return np.column_stack([rxy * np.cos(phi), rxy * np.sin(phi), z])


class _Kuipers:
    """Kuipers' closed form on ``S M^+`` into ``p``, ``R``; buffers only."""

    def __init__(self, signal, S, cur, cbar):
        n = signal.n
        self.signal, self.S, self.cur, self.cbar = signal, S, cur, cbar
        self._G = memoryview(np.zeros(9))
        self._W = memoryview(np.zeros(9))
        self._V = memoryview(np.zeros(9))
        self._w = memoryview(np.zeros(3))
        self._L = memoryview(np.zeros(9))
        self._mp = memoryview(np.zeros(3 * n))     # M^+ (n, 3)
        self._S3 = memoryview(np.zeros(9))
        self._rot3 = Rot3()
        self._eigh = jacobi_eigh_of(3)     # jacobi_eigh(., 3, ...), made at start-up
        self._u = (1.0, 0.0, 0.0)
        self._k = 1.0

    def _moment(self, j):
        mx, my, mz = self.signal.moment_per_amp(j)
        c = self.cur[j]
        return mx * c, my * c, mz * c

    def pseudo_inverse(self) -> bool:
        """``M^+`` into ``_mp``; False if the moments do not span 3-D."""
        n = self.signal.n
        G = self._G
        for a in range(9):
            G[a] = 0.0
        for j in range(n):
            m = self._moment(j)
            for a in range(3):
                for b in range(3):
                    G[3 * a + b] += m[a] * m[b]
        W = self._W
        for a in range(9):
            W[a] = G[a]
        self._eigh(W, self._w, self._V, JACOBI_SWEEPS)          # smallest singular value of M
        w = self._w
        if not (w[0] > 0.0 and math.sqrt(w[0]) > 1e-9 * math.sqrt(max(w[2], 0.0))):
            return False
        if not chol_inverse(G, 3, W, self._L):       # W = (M M^T)^-1
            return False
        mp = self._mp
        for j in range(n):
            m0, m1, m2 = self._moment(j)
            for c in range(3):
                mp[3 * j + c] = m0 * W[c] + m1 * W[3 + c] + m2 * W[6 + c]
        return True

    def solve(self, hx, hy, hz, p, R) -> bool:
        """All three parts: False if the moments do not span 3-D."""
        if not self.pseudo_inverse():
            return False
        self.position(hx, hy, hz, p)
        self.rotation(R)
        return True

    def position(self, hx, hy, hz, p) -> None:
        """Position from ``U = (S M^+)^T (S M^+) = k^2 (I + 3 u u^T)``,
        ``k = sqrt(tr U / 6)`` (thesis eqs 5.15-5.17), on the side of
        ``(hx, hy, hz)``; after :meth:`pseudo_inverse`."""
        n = self.signal.n
        S, mp, S3, W = self.S, self._mp, self._S3, self._W
        atb3(S, mp, n, S3)
        atb3(S3, S3, 3, W)
        tr = W[0] + W[4] + W[8]
        k = max(math.sqrt(max(tr / 6.0, 0.0)), 1e-300)
        self._eigh(W, self._w, self._V, JACOBI_SWEEPS)
        v = self._V
        ux, uy, uz = v[2], v[5], v[8]
        if ux * hx + uy * hy + uz * hz < 0.0:
            ux, uy, uz = -ux, -uy, -uz
        r = (MU0_4PI / k) ** (1.0 / 3.0)
        self._u = (ux, uy, uz)
        self._k = k
        cx, cy, cz = self.cbar
        p[0], p[1], p[2] = r * ux + cx, r * uy + cy, r * uz + cz

    def rotation(self, R) -> None:
        """``R = polar(A S3^T / k)``, ``A = 1.5 u u^T - I`` (thesis eqs
        5.30-5.34); after :meth:`position`."""
        u, k, S3, W = self._u, self._k, self._S3, self._W
        for i in range(3):
            for c in range(3):
                acc = 0.0
                for l in range(3):
                    acc += (1.5 * u[i] * u[l] - (1.0 if i == l else 0.0)) * S3[3 * c + l]
                W[3 * i + c] = acc / k
        nearest_rotation(W, R, self._rot3)


class Acquisition(Staged):
    """Staged acquisition of a start pose (module docstring).

    ``begin(hx, hy, hz, sigma_rms)`` then run the units; afterwards ``ok``
    (False: the coil moments do not span 3-D) and the start in ``p`` (3,)
    and ``R`` (3, 3). ``S`` and ``cur`` are the solver's buffers, read at
    every unit.
    """

    def __init__(self, signal, S, cur, cbar, reach):
        n = signal.n
        self.signal, self.S, self.cur = signal, S, cur
        self.cbar, self.reach = cbar, reach
        #: the range within which the start is refined on the invariants: the exact model's near field
        #: (``NEAR_FIELD`` x ``reach``), none for the dipole model (Kuipers' start is exact there)
        self.near = NEAR_FIELD * reach if signal.model == "exact" else 0.0
        self.p = np.zeros(3)
        self.R = np.zeros((3, 3))
        self._pv = memoryview(self.p)
        self._kuipers = _Kuipers(signal, S, cur, cbar)
        self._lm = LevenbergMarquardt(3, 1e-3, 1e8, _INV_ITERS, 0.0)
        self._U = memoryview(np.zeros(n * n))
        self._ip = memoryview(np.zeros(3))        # point being refined
        self._tp = memoryview(np.zeros(3))        # its trial
        self._best = memoryview(np.zeros(3))
        #: the search's directions (:func:`fibonacci_directions`), flat (3 per direction)
        self.grid = flat(fibonacci_directions(GRID_DIRECTIONS))
        self._cand_p = memoryview(np.zeros(3 * GRID_CANDIDATES))
        self._cand_m = memoryview(np.zeros(GRID_CANDIDATES))
        self._M = memoryview(np.zeros(9))
        self._rot3 = Rot3()
        self.ok = False
        self._h = (1.0, 0.0, 0.0)
        self._sigma_rms = 0.0
        self._tr = 1.0
        self._tol = 0.0
        self._best_m = math.inf
        self._k = 0
        self._rad = 0.0
        self._rstep = 0
        self._r0 = 0.0
        self._cand = -1

    def begin(self, hx: float, hy: float, hz: float, sigma_rms: float) -> None:
        self._h = (hx, hy, hz)
        self._sigma_rms = sigma_rms
        self.ok = False
        self._then(self._unit_moments, self.signal.n)

    # ------------------------------------------------------------- units
    def _unit_moments(self) -> None:
        """``M^+`` of the coil moments (closed form, charged ``n``)."""
        if self._kuipers.pseudo_inverse():
            self._then(self._unit_kuipers_position, self.signal.n)
        else:
            self._then(None)

    def _unit_kuipers_position(self) -> None:
        """Kuipers' position from ``S M^+`` (closed form, charged ``n``)."""
        hx, hy, hz = self._h
        self._kuipers.position(hx, hy, hz, self._pv)
        self.ok = True
        self._then(self._unit_kuipers_rotation, self.signal.n)

    def _unit_kuipers_rotation(self) -> None:
        """Kuipers' orientation (closed form, charged ``n``), then the
        near-field refinement or done."""
        self._kuipers.rotation(self.R)
        p = self._pv
        cx, cy, cz = self.cbar
        r0 = math.sqrt((p[0] - cx) ** 2 + (p[1] - cy) ** 2 + (p[2] - cz) ** 2)
        if not r0 < self.near:
            self._then(None)
            return
        self._r0 = r0
        self._invariants()
        ip = self._ip
        ip[0], ip[1], ip[2] = p[0], p[1], p[2]
        self._cand = -1
        self._then(self._unit_refine_start, self.signal.n)

    def _invariants(self) -> None:
        """``U = S^T S``, its trace and the noise level of its misfit."""
        n = self.signal.n
        S, U = self.S, self._U
        tr = 0.0
        for i in range(n):
            for j in range(n):
                U[i * n + j] = (S[3 * i] * S[3 * j] + S[3 * i + 1] * S[3 * j + 1]
                                + S[3 * i + 2] * S[3 * j + 2])
            tr += U[i * n + i]
        self._tr = tr
        self._tol = 20.0 * self._sigma_rms / math.sqrt(max(tr, 1e-300)) + 1e-9

    def _unit_refine_start(self) -> None:
        self._lm.start(self)
        self._then(self._unit_refine_step, self.signal.n)

    def _unit_refine_step(self) -> None:
        if self._lm.iterate() != LM_RUNNING:
            self._refined()

    def _refined(self) -> None:
        """Keep the better fit; next candidate, grid or orientation."""
        m = math.sqrt(self._lm.cost)
        if self._cand < 0 or m < self._best_m:
            self._best_m = m
            b, ip = self._best, self._ip
            b[0], b[1], b[2] = ip[0], ip[1], ip[2]
        if self._cand >= 0:
            self._cand += 1
            self._next_candidate()
        elif m <= self._tol:
            self._then(self._unit_orient, self.signal.n)
        else:
            self._start_grid()

    def _start_grid(self) -> None:
        cm = self._cand_m
        for c in range(GRID_CANDIDATES):
            cm[c] = math.inf
        self._k = 0
        self._seek_direction()

    def _seek_direction(self) -> None:
        """Advance ``_k`` to the next grid direction in the hemisphere."""
        hx, hy, hz = self._h
        use_h = hx != 0.0 or hy != 0.0 or hz != 0.0
        g = self.grid
        k = self._k
        while k < GRID_DIRECTIONS and use_h and g[3 * k] * hx + g[3 * k + 1] * hy + g[3 * k + 2] * hz < 0.0:
            k += 1
        self._k = k
        if k < GRID_DIRECTIONS:
            self._rad = self._r0
            self._rstep = 0
            self._then(self._unit_radius, self.signal.n)
        else:
            self._cand = 0
            self._next_candidate()

    def _unit_radius(self) -> None:
        """One power-law step of the radius of direction ``_k`` (``n`` evaluations)."""
        g, k = self.grid, self._k
        cx, cy, cz = self.cbar
        rad = self._rad
        f = (self._trace_at(cx + g[3 * k] * rad, cy + g[3 * k + 1] * rad, cz + g[3 * k + 2] * rad)
             / self._tr) ** (1.0 / 6.0)
        rad = rad * f if math.isfinite(f) else rad
        self._rad = min(max(rad, 0.25 * self._r0), 4.0 * self._r0) if math.isfinite(rad) else 0.25 * self._r0
        self._rstep += 1
        if self._rstep == 2:
            self._then(self._unit_misfit, self.signal.n)

    def _unit_misfit(self) -> None:
        """Score direction ``_k`` at its radius (``n`` evaluations), go on."""
        g, k = self.grid, self._k
        cx, cy, cz = self.cbar
        rad = self._rad
        px, py, pz = cx + g[3 * k] * rad, cy + g[3 * k + 1] * rad, cz + g[3 * k + 2] * rad
        mis = self._misfit_at(px, py, pz)
        if math.isfinite(mis):
            self._keep_candidate(mis, px, py, pz)
        self._k = k + 1
        self._seek_direction()

    def _trace_at(self, px, py, pz) -> float:
        self.signal.fields(px, py, pz, self.cur, False)
        B = self.signal.Bv
        tr = 0.0
        for q in range(3 * self.signal.n):
            tr += B[q] * B[q]
        return tr if tr > 0.0 else 0.0

    def _misfit_at(self, px, py, pz) -> float:
        """``|U - B(p)^T B(p)|_F / tr U``."""
        n = self.signal.n
        self.signal.fields(px, py, pz, self.cur, False)
        B, U = self.signal.Bv, self._U
        mis = 0.0
        for i in range(n):
            for j in range(n):
                e = (B[3 * i] * B[3 * j] + B[3 * i + 1] * B[3 * j + 1] + B[3 * i + 2] * B[3 * j + 2]
                     - U[i * n + j])
                mis += e * e
        return math.sqrt(mis) / self._tr

    def _keep_candidate(self, mis, px, py, pz) -> None:
        """Insert into the short list of the best grid points (sorted)."""
        cm, cp = self._cand_m, self._cand_p
        c = GRID_CANDIDATES - 1
        if not mis < cm[c]:
            return
        while c > 0 and mis < cm[c - 1]:
            cm[c] = cm[c - 1]
            cp[3 * c], cp[3 * c + 1], cp[3 * c + 2] = cp[3 * c - 3], cp[3 * c - 2], cp[3 * c - 1]
            c -= 1
        cm[c] = mis
        cp[3 * c], cp[3 * c + 1], cp[3 * c + 2] = px, py, pz

    def _next_candidate(self) -> None:
        c = self._cand
        if c < GRID_CANDIDATES and math.isfinite(self._cand_m[c]):
            cp, ip = self._cand_p, self._ip
            ip[0], ip[1], ip[2] = cp[3 * c], cp[3 * c + 1], cp[3 * c + 2]
            self._then(self._unit_refine_start, self.signal.n)
        else:
            self._then(self._unit_orient, self.signal.n)

    def _unit_orient(self) -> None:
        """``p`` = the best point, ``R = polar(B(p) S^T)``."""
        n = self.signal.n
        b, p = self._best, self._pv
        p[0], p[1], p[2] = b[0], b[1], b[2]
        self.signal.fields(b[0], b[1], b[2], self.cur, False)
        atb3(self.signal.Bv, self.S, n, self._M)
        nearest_rotation(self._M, self.R, self._rot3)
        self._then(None)

    # ------------------------------------------ LM problem (3 parameters)
    def evaluate(self, A, g) -> float:
        ip = self._ip
        return self._invariant_residual(ip[0], ip[1], ip[2], A, g)

    def trial(self, d, A, g) -> float:
        ip, tp = self._ip, self._tp
        tp[0], tp[1], tp[2] = ip[0] + d[0], ip[1] + d[1], ip[2] + d[2]
        return self._invariant_residual(tp[0], tp[1], tp[2], A, g)

    def accept(self) -> None:
        ip, tp = self._ip, self._tp
        ip[0], ip[1], ip[2] = tp[0], tp[1], tp[2]

    def small(self, d) -> bool:
        tp = self._tp
        return (math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
                <= 1e-9 * math.sqrt(tp[0] * tp[0] + tp[1] * tp[1] + tp[2] * tp[2]))

    def _invariant_residual(self, px, py, pz, a, g) -> float:
        """Cost of ``(U_ij - B_i . B_j) / tr U`` over ``i <= j`` and its
        normal equations (3x3 ``a``, ``g = -Jr^T r``), with
        ``dU_ij/dp_c = J_i[:, c] . B_j + B_i . J_j[:, c]``."""
        n = self.signal.n
        self.signal.fields(px, py, pz, self.cur, True)
        B, J, U = self.signal.Bv, self.signal.Jv, self._U
        scale = 1.0 / self._tr
        for i in range(9):
            a[i] = 0.0
        g[0] = g[1] = g[2] = 0.0
        cost = 0.0
        for i in range(n):
            bi0, bi1, bi2 = B[3 * i], B[3 * i + 1], B[3 * i + 2]
            oi = 9 * i
            for j in range(i, n):
                bj0, bj1, bj2 = B[3 * j], B[3 * j + 1], B[3 * j + 2]
                r = (U[i * n + j] - (bi0 * bj0 + bi1 * bj1 + bi2 * bj2)) * scale
                cost += r * r
                oj = 9 * j
                d0 = -(J[oi] * bj0 + J[oi + 3] * bj1 + J[oi + 6] * bj2
                       + bi0 * J[oj] + bi1 * J[oj + 3] + bi2 * J[oj + 6]) * scale
                d1 = -(J[oi + 1] * bj0 + J[oi + 4] * bj1 + J[oi + 7] * bj2
                       + bi0 * J[oj + 1] + bi1 * J[oj + 4] + bi2 * J[oj + 7]) * scale
                d2 = -(J[oi + 2] * bj0 + J[oi + 5] * bj1 + J[oi + 8] * bj2
                       + bi0 * J[oj + 2] + bi1 * J[oj + 5] + bi2 * J[oj + 8]) * scale
                a[0] += d0 * d0
                a[1] += d0 * d1
                a[2] += d0 * d2
                a[4] += d1 * d1
                a[5] += d1 * d2
                a[8] += d2 * d2
                g[0] -= d0 * r
                g[1] -= d1 * r
                g[2] -= d2 * r
        a[3], a[6], a[7] = a[1], a[2], a[5]
        return cost
