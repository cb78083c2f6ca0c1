"""The covariance of Raab's tracker (``pose.raab``) at each estimate: the
Cramer-Rao bound of the exact model ``(H^T W H)^-1`` (``pose.covariance``;
orientation error ``R_true = R exp([dtheta]x)``, parameter order ``(p,
dtheta)`` as ``PoseSolver``), formed (one 6x6 inversion) at an evaluation of the
signal model and carried to later estimates in closed form by the dipole's
symmetry (Raab et al. 1979, ``seeds/004_86267342cd7488ce.txt`` eqs 3-5:
rotation about the source centre, ``rho^8 / rho^7 / rho^6`` range factors, the
estimate's orientation, the weights' common scale), formed again where that
carry would err by more than ``_COV_TOL``.

Python floats and buffers allocated at construction only (two numpy products
into them per formation). On the compiled core (chosen at construction, with the
tracker's buffers bound: ``inputs``) :meth:`RaabCovariance.rows` and
:meth:`RaabCovariance.publish` are ``ct_raab_cov_rows`` and ``ct_raab_cov_publish``
of ``core/src/raab_cov.c`` (the same operations in the same order but the
information's sum, 1e-12 relative); where the robust inverse needs its
eigenvalue floor the kernel changes nothing and the Python reference publishes.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.linalg import flat
from coiltrack.firmware.pose.covariance import EIG_FLOOR, MAX_VARIANCE, RobustInverse6

__all__ = ["RaabCovariance"]

#: the covariance formed at one evaluation is carried to later estimates while its error, ~15 rel d / rho,
#: stays below this fraction of sqrt(C_ii C_kk) (then formed again at the newest evaluation) ...
_COV_TOL = 0.02
#: ... and at most this x range
_CARRY_MAX = 0.1
#: the cached covariance is scaled, not formed again, while every coil's weight x current stays within
#: this fraction of the common scale (the variances then err by at most twice this)
_Q_TOL = 0.005
#: the weights of a coil's three axes count as equal (isotropic: the orientation cancels) within this
_ISO_TOL = 1e-3


def mul3(a, b):
    """``a b`` of two 3x3 (9, row-major) as a 9-tuple."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = b
    return (a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
            a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
            a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8)


def block(c, r: int, k: int):
    """The 3x3 block at row ``r``, column ``k`` of a 6x6 (36, row-major) as a 9-tuple."""
    o = 6 * r + k
    return (c[o], c[o + 1], c[o + 2], c[o + 6], c[o + 7], c[o + 8], c[o + 12], c[o + 13], c[o + 14])


class RaabCovariance:
    """The covariance of ``n`` coils (centroid ``cbar``) into ``out`` (6, 6),
    the tracker's published result; ``sig_p``, ``sig_o``: the smallest
    position and orientation standard deviations of it (m, rad: the noise
    level of the next solve's stop).

    Owns the rows ``[J_j | [B_j]x]`` per ampere of the last evaluation
    (:meth:`rows`) and the source-frame covariance ``C_s`` formed from them at
    ``p_c``.

    ``inputs``: the tracker's buffers ``(x, Rn, w, cur, pm, Bv, Jv)`` (Raab's
    coordinates (6), the rotation (3, 3), the weights (3 n), the currents (n),
    the last evaluation's point (3), the signal model's fields (3 n) and
    gradients (9 n)), which :meth:`rows` and :meth:`publish` then read: on a
    compiled ``core`` they are bound to the kernels here and the two methods
    replaced on this instance (their arguments must be those buffers)."""

    def __init__(self, n: int, cbar, out, core=_DEFAULT_CORE, inputs=None):
        self.n = n
        self._cbar = cbar
        self._cov = flat(out)
        self._Kn = np.zeros((3 * n, 6))              # [J_j | [B_j]x] per A at the last evaluation (source frame)
        self._Ks = flat(self._Kn)
        self._Hn = np.zeros((3 * n, 6))              # the same in the sensor frame (anisotropic weights)
        self._H = flat(self._Hn)
        self._qn = np.zeros((3 * n, 1))              # weights x currents of the information, a column
        self._qv = flat(self._qn)
        self._qm = memoryview(np.zeros(n))           # per-coil weight x current of the cached covariance
        self._HWn = np.zeros((3 * n, 6))
        self._HWt = self._HWn.T
        self._An = np.zeros((6, 6))
        self._A36 = flat(self._An)
        self._Cs = memoryview(np.zeros(36))          # covariance at p_c, source-frame orientation error
        self._cs_ok = False                          # _Cs formed at _pc (isotropic weights _qm)
        self._pc = memoryview(np.zeros(3))           # where _Cs was formed (an evaluation point)
        self._inv = RobustInverse6()
        self.sig_p = 0.0
        self.sig_o = 0.0
        self.core = "python"
        if core.ext is not None and inputs is not None and 3 <= n <= 64:
            self._bind_compiled(core.ext, inputs)

    def _bind_compiled(self, ext, inputs) -> None:
        """:meth:`rows` and :meth:`publish` on ``ct_raab_cov_rows`` / ``ct_raab_cov_publish``, the buffers
        (these and the tracker's ``inputs``) and the constants bound once."""
        self._par = np.array([_COV_TOL, _CARRY_MAX, _Q_TOL, _ISO_TOL, MAX_VARIANCE, EIG_FLOOR])
        self._cb = np.array(self._cbar, dtype=float)
        self._st = np.zeros(3)                       # C_s formed, sig_p, sig_o (ct_ac.h: CT_RCS_*)
        self._stv = memoryview(self._st)
        self._scratch = np.zeros((3, 36))
        own = (self._par, self._cb, self._cov, self._Ks, self._H, self._qv, self._qm, self._A36, self._Cs, self._pc,
               self._st, self._scratch[0], self._scratch[1], self._scratch[2])
        self._ck = ext.RaabCov(self.n, own + tuple(inputs))
        self.rows = self._rows_compiled
        self.publish = self._publish_compiled
        self.core = "compiled"

    def _rows_compiled(self, Bv, Jv) -> None:
        self._ck.rows()

    def _publish_compiled(self, x, R, w, cur, pm, rel: float, point) -> None:
        st = self._stv
        if not self._ck.publish(rel):
            # the robust inverse takes its eigenvalue floor: the reference, from the same state
            self._cs_ok = st[0] != 0.0
            RaabCovariance.publish(self, x, R, w, cur, pm, rel, point)
            st[0], st[1], st[2] = 1.0 if self._cs_ok else 0.0, self.sig_p, self.sig_o
            return
        self.sig_p, self.sig_o = st[1], st[2]

    def rows(self, Bv, Jv) -> None:
        """The rows ``[J_j | [B_j]x]`` (source frame; orientation error
        ``dtheta_s = R dtheta``) of the exact model's fields ``Bv`` and
        gradients ``Jv`` per ampere at a new evaluation."""
        K = self._Ks
        for j in range(self.n):
            o, g, k = 3 * j, 9 * j, 18 * j
            Bx, By, Bz = Bv[o], Bv[o + 1], Bv[o + 2]
            K[k], K[k + 1], K[k + 2], K[k + 3], K[k + 4], K[k + 5] = Jv[g], Jv[g + 1], Jv[g + 2], 0.0, -Bz, By
            K[k + 6], K[k + 7], K[k + 8], K[k + 9], K[k + 10], K[k + 11] = Jv[g + 3], Jv[g + 4], Jv[g + 5], Bz, 0.0, -Bx
            K[k + 12], K[k + 13], K[k + 14], K[k + 15], K[k + 16], K[k + 17] = (Jv[g + 6], Jv[g + 7], Jv[g + 8],
                                                                                 -By, Bx, 0.0)

    def publish(self, x, R, w, cur, pm, rel: float, point) -> None:
        """The covariance of ``(p, dtheta)`` at the estimate ``x`` (rotation
        ``R``, Raab's coordinates, at ``point`` in the source frame) for the
        weights ``w = 1 / sigma`` and currents ``cur``, the last evaluation at
        ``pm`` (``rel``: its correction's gradient over the dipole's), (6, 6)
        into ``out``, without a 6x6 inversion while it can be carried.

        The information of the exact model at the last evaluation ``p_m``,
        with source-frame orientation errors ``dtheta_s = R dtheta``, is
        ``A_s = sum_j q_j^2 K_j^T K_j``, ``K_j = [J_j | [B_j]x]`` per ampere
        (the Jacobian of ``model.signal`` with ``R`` taken out: ``H_j = R^T
        K_j``), ``q_j = I_j / sigma_j`` when the three axes of coil ``j`` have
        one ``sigma_j``; then ``R`` cancels from ``H_j^T H_j``. Its robust
        inverse ``C_s`` (``pose.covariance``) is formed at an evaluation
        (:meth:`_cov_form`) and carried to each estimate in closed form
        (:meth:`_cov_carry`) while that is accurate (:meth:`_carry_too_far`).
        While the ``q_j`` stay proportional to those of ``C_s`` (within
        ``_Q_TOL``) only the common scale changes:
        ``C = C_s q_m^2 / q^2``. Weights that differ between the axes of a
        coil: the sensor-frame information at the current ``R`` is formed
        and inverted (the evaluation's position)."""
        n, qm = self.n, self._qm
        iso = True
        for j in range(n):
            w0 = w[3 * j]
            if abs(w[3 * j + 1] - w0) > _ISO_TOL * w0 or abs(w[3 * j + 2] - w0) > _ISO_TOL * w0:
                iso = False
                break
        if not iso:
            self._cs_ok = False
            self._cov_form(False, R, w, cur, pm)
            self._published_sigmas()
            return
        scale = 1.0
        if self._cs_ok and self._carry_too_far(pm, rel, point, x[2]):
            self._cs_ok = False
        if self._cs_ok:
            num = den = 0.0
            for j in range(n):
                q = w[3 * j] * cur[j]
                num += q * q
                den += qm[j] * qm[j]
            s2 = num / den                      # common scale of q^2
            for j in range(n):
                q = w[3 * j] * cur[j]
                r = q * q / (qm[j] * qm[j] * s2)
                if not (1.0 - 2.0 * _Q_TOL <= r <= 1.0 + 2.0 * _Q_TOL):
                    self._cs_ok = False
                    break
            scale = 1.0 / s2
        if not self._cs_ok:
            self._cov_form(True, R, w, cur, pm)
            scale = 1.0
        self._cov_carry(scale, x, R)
        self._published_sigmas()

    def _carry_too_far(self, pm, rel: float, point, rho: float) -> bool:
        """The carry from ``p_c`` would err by more than ``_COV_TOL`` (of
        sqrt(C_ii C_kk)) and a newer evaluation exists: its error, measured
        against magpylib's bound, is about ``15 rel d / rho`` for a carry ``d``
        (``rel``: the correction's gradient over the dipole's, 0.3 at 15 cm,
        0.036 at 40 cm, 0.012 at 70 cm), and the dipole carry's own ``1e-3``
        up to ``_CARRY_MAX`` x range."""
        pc = self._pc
        if pc[0] == pm[0] and pc[1] == pm[1] and pc[2] == pm[2]:
            return False
        lim = min(_CARRY_MAX, _COV_TOL / (15.0 * rel)) if rel > 0.0 else _CARRY_MAX
        dx, dy, dz = point[0] - pc[0], point[1] - pc[1], point[2] - pc[2]
        return dx * dx + dy * dy + dz * dz > (lim * rho) ** 2

    def _cov_form(self, iso: bool, R, w, cur, pm) -> None:
        """The information at ``p_m`` and its robust inverse (the one 6x6 work):
        ``iso``: source-frame form into ``_Cs`` with ``q_j = I_j / sigma_j``
        kept in ``_qm``; otherwise the sensor frame of the current ``R`` with a
        weight per element, into ``covariance``. Two numpy products into
        preallocated buffers."""
        n, q = self.n, self._qv
        if iso:
            for j in range(n):
                qj = w[3 * j] * cur[j]
                self._qm[j] = qj
                q[3 * j] = q[3 * j + 1] = q[3 * j + 2] = qj
            np.multiply(self._Kn, self._qn, out=self._HWn)
            np.matmul(self._HWt, self._HWn, out=self._An)
            self._inverse(self._Cs)
            pc = self._pc
            pc[0], pc[1], pc[2] = pm[0], pm[1], pm[2]
            self._cs_ok = True
            return
        K, H = self._Ks, self._H
        for j in range(n):
            for i in range(3):
                q[3 * j + i] = w[3 * j + i] * cur[j]
                r0, r1, r2 = R[0, i], R[1, i], R[2, i]           # row i of R^T
                o = 18 * j + 6 * i
                for c in range(6):
                    H[o + c] = r0 * K[18 * j + c] + r1 * K[18 * j + 6 + c] + r2 * K[18 * j + 12 + c]
        np.multiply(self._Hn, self._qn, out=self._HWn)
        np.matmul(self._HWt, self._HWn, out=self._An)
        self._inverse(self._cov)

    def _inverse(self, out) -> None:
        """``out = A^-1`` of the information ``_An`` (``pose.covariance.RobustInverse6``, the
        runtime solver's inverse)."""
        self._inv.into(self._A36, out)

    def _cov_carry(self, scale: float, x, R) -> None:
        """``C_s`` (at ``p_m``, source-frame orientation) carried to the
        estimate ``p`` with orientation ``R``, times ``scale``, into
        ``covariance``. For co-centred orthogonal dipoles of equal moment the
        information is covariant under a rotation ``Q`` about the source
        centre (``A_s(Q p) = diag(Q, Q) A_s(p) diag(Q, Q)^T``: it sums over an
        orthonormal set of moments) and scales with the range as ``B ~
        rho^-3``, ``J ~ rho^-4`` (Raab eqs 3-5). With ``Q`` the rotation taking
        ``u_m`` to ``u``, ``t = rho / rho_m`` and ``M = Q^T R``:
        ``C_pp = t^8 Q C_pp,s Q^T``, ``C_ptheta = t^7 Q C_ptheta,s M``,
        ``C_thetatheta = t^6 M^T C_thetatheta,s M``. The exact loops and unequal
        currents depart from the symmetry: the carry errs by about ``15 rel
        d / rho`` (:meth:`_carry_too_far`; test against magpylib's bound)."""
        c, pm = self._cbar, self._pc
        mx, my, mz = pm[0] - c[0], pm[1] - c[1], pm[2] - c[2]
        rm = math.sqrt(mx * mx + my * my + mz * mz)
        mx, my, mz = mx / rm, my / rm, mz / rm
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        ux, uy, uz = cb * ca, cb * sa, -sb
        # Q = I + [w]x + [w]x^2 / (1 + u_m.u), w = u_m x u (the shortest rotation from u_m to u)
        wx, wy, wz = my * uz - mz * uy, mz * ux - mx * uz, mx * uy - my * ux
        h = 1.0 / (1.0 + mx * ux + my * uy + mz * uz)
        q00, q11, q22 = 1.0 - h * (wy * wy + wz * wz), 1.0 - h * (wx * wx + wz * wz), 1.0 - h * (wx * wx + wy * wy)
        q01, q10 = h * wx * wy - wz, h * wx * wy + wz
        q02, q20 = h * wx * wz + wy, h * wx * wz - wy
        q12, q21 = h * wy * wz - wx, h * wy * wz + wx
        Q = (q00, q01, q02, q10, q11, q12, q20, q21, q22)
        Qt = (q00, q10, q20, q01, q11, q21, q02, q12, q22)
        # M = Q^T R
        r = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2])
        M = mul3(Qt, r)
        Mt = (M[0], M[3], M[6], M[1], M[4], M[7], M[2], M[5], M[8])
        t = x[2] / rm
        t2 = t * t
        t6 = t2 * t2 * t2 * scale
        Cs, cov = self._Cs, self._cov
        pp = mul3(mul3(Q, block(Cs, 0, 0)), Qt)
        pt = mul3(mul3(Q, block(Cs, 0, 3)), M)
        tt = mul3(mul3(Mt, block(Cs, 3, 3)), M)
        f8, f7 = t6 * t2, t6 * t
        for i in range(3):
            for k in range(3):
                cov[6 * i + k] = f8 * pp[3 * i + k]
                v = f7 * pt[3 * i + k]
                cov[6 * i + 3 + k] = v
                cov[6 * (3 + k) + i] = v
                cov[6 * (3 + i) + 3 + k] = t6 * tt[3 * i + k]

    def _published_sigmas(self) -> None:
        """The smallest position and orientation standard deviations of the
        published covariance (the noise level of the next solve's stop)."""
        cov = self._cov
        vp, vo = min(cov[0], cov[7], cov[14]), min(cov[21], cov[28], cov[35])
        self.sig_p = math.sqrt(vp) if vp > 0.0 and math.isfinite(vp) else 0.0
        self.sig_o = math.sqrt(vo) if vo > 0.0 and math.isfinite(vo) else 0.0
