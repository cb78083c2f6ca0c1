"""The exact-loop correction of Raab's tracker (``pose.raab``; Raab et al. 1979,
``seeds/004_86267342cd7488ce.txt``), chosen once at construction:
:class:`LoopCorrection` (``correction=True``) or :class:`NoCorrection`
(Raab's detection on the measured signals).

Raab's model is the point dipole (eqs 3-6); the bench's coils are finite loops.
The measured signals are corrected through the one signal model
(``model.signal``) before the pre-excitation rotation (eq 7):
``S_c[:, j] = S[:, j] - R^T (b_j + G_j (p - p_m)) I_j`` with ``b_j = B_model,j -
B_raab,j`` per ampere, the source-frame difference between the exact loop of
coil ``j`` and Raab's co-centred dipole (``model.field.dipole_polar``, at the
centroid of the coil centres) at the point ``p_m`` of the last evaluation and
``G_j`` its gradient: exact in the orientation, linear in the position (within
``_LIN_MAX`` x range of ``p_m``). The detected errors are solved through ``K = I
+ G D T`` (:meth:`LoopCorrection.precondition`), which restores quadratic
convergence near the source and changes only the rate, not the fixed point.

Python floats and buffers allocated at construction only. On the compiled core
(chosen at construction) :meth:`LoopCorrection.refresh` and
:meth:`LoopCorrection.precondition` are ``ct_raab_refresh`` and
``ct_raab_precondition`` of ``core/src/raab.c`` (the same operations in the
same order); these methods are their reference.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.linalg import lu_factor, lu_solve
from coiltrack.firmware.model.field import MU0_2PI, dipole_polar

__all__ = ["LoopCorrection", "NoCorrection", "K_MIN"]

#: the preconditioner K sets only the rate, not the fixed point: it is reused within this x range (rad)
_K_REUSE = 0.15
#: K is taken as I (not formed) where the correction's gradient is below this fraction of the dipole's
#: (beyond ~55 cm for the thesis source): K - I is of that order, the rate of the updates without it
K_MIN = 0.02
#: the preconditioner is applied to detected steps below this (rad, x range): the linear regime
LIN_STEP = _LIN_STEP = 0.15
#: the correction's linear term is used within this fraction of the range (rad) of its evaluation
LIN_MAX = _LIN_MAX = 0.1


class NoCorrection:
    """Raab's own detection on the measured signals (``correction=False``):
    ``S_c = S``, ``K = I``; a refresh changes nothing. ``rel`` (the
    correction's gradient over the dipole's) is 1: the covariance is formed at
    each evaluation."""

    refreshes = False
    rel = 1.0
    lin = False
    k_id = True

    def correct(self, S, Sc, n: int, point, pm, R, rho: float, cur) -> None:
        """``S_c = S``."""
        for o in range(3 * n):
            Sc[o] = S[o]

    def drop_linear(self) -> None:
        pass

    def resume(self) -> None:
        pass

    def refresh(self, Bv, Jv, x, mpa, w, cur, dd, shift_ok: bool) -> float:
        """Nothing to evaluate; no shift to measure."""
        return math.inf

    def prepare(self, point, x, mp, cur, k: float) -> None:
        pass

    def precondition_step(self, rho: float, d):
        """Raab's detection as it is (``K = I``)."""
        return d

    def kernel_buffers(self):
        """No buffers for the compiled update (``pose.raab_update.Update``): no correction."""
        return None


class LoopCorrection:
    """The exact-loop correction of ``n`` coils and the preconditioner ``K``.

    Owns the correction per ampere ``b`` (``[3 j + i]``) and its gradient ``G``
    (``[9 j + 3 r + c]``, source frame) of the last evaluation, ``rel`` (the
    largest ratio of the correction's gradient to the dipole's there), ``lin``
    (the linear term and ``K`` in use) and ``K``'s LU factors with the point
    ``pk`` where they were formed (``K`` does not depend on the sensor's
    orientation: the rotations of ``D``, ``T`` and ``G`` cancel)."""

    refreshes = True

    def __init__(self, n: int, core=_DEFAULT_CORE):
        self.n = n
        self.rel = 1.0                               # the correction's gradient / the dipole's at the evaluation
        self.lin = False                             # the correction's linear term (and K) in use
        self.k_id = False                            # K taken as I (the correction's gradient below K_MIN)
        self.k_ok = False                            # K factored, at _pk
        self.b = memoryview(np.zeros(3 * n))        # correction B_model - B_raab per A (source frame), [3 j + i]
        self.G = memoryview(np.zeros(9 * n))        # its gradient d/dp per A, [9 j + 3 r + c]
        self._pk = [0.0] * 3
        self._Fk = [0.0] * 54                        # the six detected couplings of K's columns
        self._K = memoryview(np.zeros(36))          # K = I + G D T, LU factors
        self._perm = memoryview(np.zeros(6, dtype=np.int64))
        self._e = [0.0] * 6
        self._y = [0.0] * 6
        self._ro = memoryview(np.zeros(2))          # rel, shift of the compiled refresh
        #: the numeric core, bound once here (``coiltrack.firmware.core``)
        self.core = "python"
        if core.ext is not None and n <= 64:
            self._bind_compiled(core.ext)

    def _bind_compiled(self, ext) -> None:
        """:meth:`refresh` and :meth:`precondition` on ``ct_raab_refresh`` / ``ct_raab_precondition``
        (``core/src/raab.c``), bound once to ``b``, ``G``, ``K`` and its permutation; the methods
        are replaced on this instance."""
        self._ck = ext.RaabCorr(self.n, MU0_2PI, self.b, self.G, self._K, self._perm)
        self.refresh = self._refresh_compiled
        self.precondition = self._precondition_compiled
        self.core = "compiled"

    def _refresh_compiled(self, Bv, Jv, x, mpa, w, cur, dd, shift_ok: bool) -> float:
        ro = self._ro
        self._ck.refresh(x, Bv, Jv, mpa, w, cur, dd[0], dd[1], dd[2], shift_ok, ro)
        self.rel = ro[0]
        return ro[1]

    def _precondition_compiled(self, x, mp, cur, k: float) -> None:
        self.k_ok = self._ck.precondition(x, mp, cur, k)

    def correct(self, S, Sc, n: int, point, pm, R, rho: float, cur) -> None:
        """``S_c[:, j] = S[:, j] - R^T (b_j + G_j (p - p_m)) I_j`` at the
        estimate ``point`` (range ``rho``) with rotation ``R``; the linear term
        only within ``_LIN_MAX`` x range of ``p_m`` (during acquisition the pose
        may be far from it: then ``lin`` drops)."""
        px, py, pz = point
        dx, dy, dz = px - pm[0], py - pm[1], pz - pm[2]
        if dx * dx + dy * dy + dz * dz > (_LIN_MAX * rho) ** 2:
            dx = dy = dz = 0.0
            self.lin = False
        b, G = self.b, self.G
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2],
                                                       R[2, 0], R[2, 1], R[2, 2])
        for j in range(n):
            o, g, c = 3 * j, 9 * j, cur[j]
            vx = (b[o] + G[g] * dx + G[g + 1] * dy + G[g + 2] * dz) * c
            vy = (b[o + 1] + G[g + 3] * dx + G[g + 4] * dy + G[g + 5] * dz) * c
            vz = (b[o + 2] + G[g + 6] * dx + G[g + 7] * dy + G[g + 8] * dz) * c
            Sc[o] = S[o] - (r00 * vx + r10 * vy + r20 * vz)
            Sc[o + 1] = S[o + 1] - (r01 * vx + r11 * vy + r21 * vz)
            Sc[o + 2] = S[o + 2] - (r02 * vx + r12 * vy + r22 * vz)

    def kernel_buffers(self):
        """``(b, G, K, perm)`` for the compiled update (``pose.raab_update.Update``), bound once."""
        return self.b, self.G, self._K, self._perm

    def drop_linear(self) -> None:
        """A new evaluation (or the estimate beyond the linear term's range): the linear term is
        not in use until :meth:`prepare`."""
        self.lin = False

    def resume(self) -> None:
        """A warm start within the cached evaluation: its linear term and ``K`` apply."""
        self.lin = self.k_ok

    def refresh(self, Bv, Jv, x, mpa, w, cur, dd, shift_ok: bool) -> float:
        """The correction again from the exact model's fields ``Bv`` and
        gradients ``Jv`` per ampere at the estimate ``x`` (``model.signal``)
        and Raab's dipole there (``dipole_polar`` of the moments per ampere
        ``mpa``: no field evaluation); ``rel`` updated. Returns the shift: the
        new correction against the last one's linear term (moved by ``dd``) in
        the noise of the signals (weights ``w``, currents ``cur``), squared and
        summed, when ``shift_ok`` (else 0)."""
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        ux, uy, uz = cb * ca, cb * sa, -sb
        ddx, ddy, ddz = dd
        b, G = self.b, self.G
        rel = shift = 0.0
        for j in range(self.n):
            o, g = 3 * j, 9 * j
            bx, by, bz, gxx, gyy, gzz, gxy, gxz, gyz = dipole_polar(ux, uy, uz, x[2], mpa[o], mpa[o + 1],
                                                                    mpa[o + 2], True)
            nx, ny, nz = Bv[o] - bx, Bv[o + 1] - by, Bv[o + 2] - bz
            if shift_ok:
                # the new correction against the last one's linear term here, in the noise of coil j's signals
                ex = nx - (b[o] + G[g] * ddx + G[g + 1] * ddy + G[g + 2] * ddz)
                ey = ny - (b[o + 1] + G[g + 3] * ddx + G[g + 4] * ddy + G[g + 5] * ddz)
                ez = nz - (b[o + 2] + G[g + 6] * ddx + G[g + 7] * ddy + G[g + 8] * ddz)
                wm = max(w[o], w[o + 1], w[o + 2]) * cur[j]
                shift += (ex * ex + ey * ey + ez * ez) * wm * wm
            b[o], b[o + 1], b[o + 2] = nx, ny, nz
            G[g], G[g + 1], G[g + 2] = Jv[g] - gxx, Jv[g + 1] - gxy, Jv[g + 2] - gxz
            G[g + 3], G[g + 4], G[g + 5] = Jv[g + 3] - gxy, Jv[g + 4] - gyy, Jv[g + 5] - gyz
            G[g + 6], G[g + 7], G[g + 8] = Jv[g + 6] - gxz, Jv[g + 7] - gyz, Jv[g + 8] - gzz
            gg = 0.0
            for q in range(g, g + 9):
                gg += G[q] * G[q]
            jj = gxx * gxx + gyy * gyy + gzz * gzz + 2.0 * (gxy * gxy + gxz * gxz + gyz * gyz)
            if gg > rel * rel * jj:
                rel = math.sqrt(gg / jj)
        self.rel = rel
        return shift

    def prepare(self, point, x, mp, cur, k: float) -> None:
        """``K`` for the fresh correction at ``point`` (the estimate ``x``,
        ``M^+`` ``mp``, ``k = C / rho^3`` of the corrected coupling): ``I``
        where ``rel < K_MIN``, else formed again unless one formed within
        ``_K_REUSE`` x range holds; then the linear term is in use."""
        if self.rel < K_MIN:
            self.k_id = True                        # K = I + O(rel): Raab's own detection (no LU)
            self.k_ok = True
        else:
            pk = self._pk
            dx, dy, dz = point[0] - pk[0], point[1] - pk[1], point[2] - pk[2]
            if self.k_id or not self.k_ok or dx * dx + dy * dy + dz * dz > (_K_REUSE * x[2]) ** 2:
                self.k_id = False
                self.precondition(x, mp, cur, k)
                pk[0], pk[1], pk[2] = point
        self.lin = self.k_ok

    def precondition(self, x, mp, cur, k: float) -> None:
        """``K = I + G D T`` at the evaluation point and its LU factors:
        ``T`` maps Raab's tracking-frame steps ``(d_alpha0, d_beta0, d_rho,
        d_psi0, d_theta0, d_phi0)`` to ``(dp, dtheta)`` (``dp = rho P^T (0,
        d_alpha0, -d_beta0) + d_rho u``, ``dtheta = R^T P^T (d_phi0,
        d_theta0, d_psi0)``), ``D`` is the correction's Jacobian and ``G``
        the detection (eqs 7, 11, 21-26) of a signal change. With ``S_c = S
        - d - D dx`` the detected errors are ``e = K d`` to first order, so
        solving for ``d`` gives the exact model's step (Raab's own detection is
        ``K = I``, exact for the dipole) and the iteration converges
        quadratically instead of by the ratio of loop to dipole near the source.
        ``x`` the estimate, ``mp`` ``M^+``, ``cur`` the currents, ``k = C /
        rho^3`` of the corrected coupling."""
        n, b, G = self.n, self.b, self.G
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        p00, p01, p02 = cb * ca, cb * sa, -sb
        p10, p11 = -sa, ca
        p20, p21, p22 = sb * ca, sb * sa, cb
        rho = x[2]
        # The detected coupling of column c is F7_c = P R (D T_c) M^+ P^T = sum_j y_jc (P m^+_j)^T with, in
        # the tracking frame (Gt_j = P G_j P^T, bt_j = P b_j; R cancels: R [R^T b]x R^T = [b]x):
        # d_alpha0: rho Gt_j e_y, d_beta0: -rho Gt_j e_z, d_rho: Gt_j e_x, d_psi0: bt_j x e_z,
        # d_theta0: bt_j x e_y, d_phi0: bt_j x e_x (each times the current I_j).
        Fk = self._Fk
        for i in range(54):
            Fk[i] = 0.0
        for j in range(n):
            cj, o, g = cur[j], 3 * j, 9 * j
            m0, m1, m2 = mp[o], mp[o + 1], mp[o + 2]
            q0 = p00 * m0 + p01 * m1 + p02 * m2
            q1 = p10 * m0 + p11 * m1
            q2 = p20 * m0 + p21 * m1 + p22 * m2
            bx, by, bz = b[o] * cj, b[o + 1] * cj, b[o + 2] * cj
            t0 = p00 * bx + p01 * by + p02 * bz
            t1 = p10 * bx + p11 * by
            t2 = p20 * bx + p21 * by + p22 * bz
            # G_j P^T e_k = G_j (row k of P), k = x, y, z
            cols = []
            for (e0, e1, e2) in ((p00, p01, p02), (p10, p11, 0.0), (p20, p21, p22)):
                w0 = (G[g] * e0 + G[g + 1] * e1 + G[g + 2] * e2) * cj
                w1 = (G[g + 3] * e0 + G[g + 4] * e1 + G[g + 5] * e2) * cj
                w2 = (G[g + 6] * e0 + G[g + 7] * e1 + G[g + 8] * e2) * cj
                cols.append((p00 * w0 + p01 * w1 + p02 * w2, p10 * w0 + p11 * w1, p20 * w0 + p21 * w1 + p22 * w2))
            gx, gy, gz = cols
            ys = ((rho * gy[0], rho * gy[1], rho * gy[2]), (-rho * gz[0], -rho * gz[1], -rho * gz[2]), gx,
                  (t1, -t0, 0.0), (-t2, 0.0, t0), (0.0, t2, -t1))
            for c in range(6):
                y0, y1, y2 = ys[c]
                f = 9 * c
                Fk[f] += y0 * q0
                Fk[f + 1] += y0 * q1
                Fk[f + 2] += y0 * q2
                Fk[f + 3] += y1 * q0
                Fk[f + 4] += y1 * q1
                Fk[f + 5] += y1 * q2
                Fk[f + 6] += y2 * q0
                Fk[f + 7] += y2 * q1
                Fk[f + 8] += y2 * q2
        K, inv = self._K, 1.0 / k
        for c in range(6):
            f = 9 * c
            fxy, fyx, fxz, fzx, fyz, fzy = (Fk[f + 1] * inv, Fk[f + 3] * inv, Fk[f + 2] * inv, Fk[f + 6] * inv,
                                            Fk[f + 5] * inv, Fk[f + 7] * inv)
            col = ((2.0 / 3.0) * (2.0 * fxy - fyx), (2.0 / 3.0) * (fzx - 2.0 * fxz),
                   -(rho / 9.0) * (2.0 * Fk[f] - Fk[f + 4] - Fk[f + 8]) * inv,
                   2.0 * (fxy - fyx), 2.0 * (fzx - fxz), fzy - fyz)           # eqs 21-26, as error_angles
            for r in range(6):
                K[6 * r + c] = col[r] + (1.0 if r == c else 0.0)
        self.k_ok = lu_factor(self._K, 6, self._perm)

    def precondition_step(self, rho: float, d):
        """The detected errors ``d = (d_alpha0, d_beta0, d_rho, d_psi0,
        d_theta0, d_phi0)`` at range ``rho`` solved through ``K d' = d`` while
        the linear term is in use, ``K`` is not ``I`` and the steps are in the
        linear regime (below ``_LIN_STEP``); else ``d`` as it is."""
        da0, db0, drho, dpsi0, dth0, dphi0 = d
        if self.lin and not self.k_id \
                and max(abs(da0), abs(db0), abs(drho) / rho, abs(dpsi0), abs(dth0), abs(dphi0)) < _LIN_STEP:
            # the exact model's sensitivities: solve K d = e (K = I + G D T of the last evaluation)
            e = self._e
            e[0], e[1], e[2], e[3], e[4], e[5] = da0, db0, drho, dpsi0, dth0, dphi0
            lu_solve(self._K, 6, self._perm, e, self._y)
            return e[0], e[1], e[2], e[3], e[4], e[5]
        return d

