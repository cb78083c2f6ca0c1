"""Raab's iterative update (Raab et al. 1979, ``seeds/004_86267342cd7488ce.txt``,
eqs 7-31): the arithmetic of one update, without state. The tracker that runs it
(:class:`coiltrack.firmware.pose.raab.RaabTracker`) keeps the pose, the cached
correction and the covariance.

Raab's six coordinates (Fig. 2): position azimuth ``alpha``, elevation
``beta`` and range ``rho`` about the source centre, orientation azimuth
``psi``, elevation ``theta`` and roll ``phi``; with the rotations of
Table II,

    ``P = T_beta T_alpha`` (source -> position/tracking frame, eq 4),
    ``A = T_phi T_theta T_psi`` (source -> sensor frame, eqs 6, 29), ``R = A^T``,

so the unit vector to the sensor is ``u = P^T e_x = (cb ca, cb sa, -sb)``.
The source is Raab's dipole coupling (eqs 3-6): ``F = (C / rho^3) A Q``,
``Q = P^T S P``, ``S = diag(1, -1/2, -1/2)``, ``C = mu0 / 2 pi`` per unit
moment (``model.field.MU0_2PI``; the field itself ``model.field.dipole_polar``).

* :func:`moment_pseudo_inverse`, :func:`coupling`: ``F = S_c M^+`` and the
  range invariant ``|F|_F = sqrt(3/2) C / rho^3`` (eq 21).
* :func:`post_sense`: the pre-excitation and post-sensing rotations (eqs 7,
  11), ``F_7 = P R F P^T``.
* :func:`error_angles`, :func:`detect`: the error angles (eqs 22-26) and the
  range (eq 21).
* :func:`position_update`, :func:`orientation_update`: the frame conversion
  (eqs 27-31) and the update by addition, with the modified conversion near
  the poles.
* :func:`angles_from_pose`, :func:`dcm`, :func:`euler`: the coordinates of a
  pose and back.
* :func:`residual_cost`: the residual against Raab's dipole (the gate).
* :class:`Update`: one whole update on a tracker's buffers (the correction,
  :func:`coupling`, :func:`detect`, the preconditioner, the clip, the
  conversion, :func:`sync_rotation`), the Python reference or the compiled
  kernel ``core/src/raab.c`` (``ct_raab_update``), chosen at construction.

Python floats only: nothing is allocated after construction.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.linalg import inv3_sym, nearest_rotation
from coiltrack.firmware.model.field import MU0_2PI, dipole_polar
from coiltrack.firmware.pose import raab_correction as rc

__all__ = ["C_RAAB", "POLE_COS", "MAX_STEP", "wrap", "clip", "error_angles", "position_update", "dcm", "euler",
           "orientation_update", "angles_from_pose", "is_rotation", "load_rotation", "moment_pseudo_inverse",
           "coupling", "post_sense", "detect", "residual_cost", "point", "sync_rotation", "Update"]

#: C of eq 3 per unit moment (T m^3 / A m^2): F = (C / rho^3) A Q
C_RAAB = MU0_2PI
_SQRT15 = math.sqrt(1.5)
#: below this |cos beta| (|cos theta|) the modified conversion (composition) replaces eq 27 (eq 31)
POLE_COS = 0.2
#: largest angle step of one update (rad): the signs of large errors are right, not their sizes (Fig. 8)
MAX_STEP = 0.5
#: a warm start's rotation closer than this to orthonormal (each element of R^T R - I) is used as it is
_ORTHO_TOL = 1e-9
_TWO_PI = 2.0 * math.pi


def wrap(a: float) -> float:
    """Angle into (-pi, pi]."""
    a = math.fmod(a, _TWO_PI)
    if a > math.pi:
        a -= _TWO_PI
    elif a <= -math.pi:
        a += _TWO_PI
    return a


def clip(x: float, m: float) -> float:
    """``x`` clipped to ``[-m, m]``."""
    return m if x > m else (-m if x < -m else x)


def error_angles(F7, k: float):
    """Eqs 22-26: tracking-frame error angles from the post-sensed coupling
    ``F7`` (9, row-major; ``F7[3 i + c]`` = component ``i`` of excitation
    state ``c``) normalised by ``k = C / rho^3``; returns ``(d_alpha0,
    d_beta0, d_psi0, d_theta0, d_phi0)`` in rad."""
    inv = 1.0 / k
    fxy, fyx = F7[1] * inv, F7[3] * inv
    fxz, fzx = F7[2] * inv, F7[6] * inv
    fyz, fzy = F7[5] * inv, F7[7] * inv
    return ((2.0 / 3.0) * (2.0 * fxy - fyx), (2.0 / 3.0) * (fzx - 2.0 * fxz),
            2.0 * (fxy - fyx), 2.0 * (fzx - fxz), fzy - fyz)


def position_update(alpha: float, beta: float, da0: float, db0: float):
    """Eqs 27-28 and the update by addition: the new ``(alpha, beta)`` from
    the tracking-frame errors ``(d_alpha0, d_beta0)``. Near the pole
    (``|cos beta| < POLE_COS``) the modified conversion: the direction
    ``P^T (1, d_alpha0, -d_beta0)`` normalised, its angles read back."""
    cb = math.cos(beta)
    if abs(cb) >= POLE_COS:
        a, b = alpha + da0 / cb, beta + db0                     # eqs 27, 28
        if b > 0.5 * math.pi:                                   # over the pole: the same point
            b, a = math.pi - b, a + math.pi
        elif b < -0.5 * math.pi:
            b, a = -math.pi - b, a + math.pi
        return wrap(a), b
    ca, sa, sb = math.cos(alpha), math.sin(alpha), math.sin(beta)
    # u = P^T v, v = (1, da0, -db0); P rows: (cb ca, cb sa, -sb), (-sa, ca, 0), (sb ca, sb sa, cb)
    v0, v1, v2 = 1.0, da0, -db0
    ux = cb * ca * v0 - sa * v1 + sb * ca * v2
    uy = cb * sa * v0 + ca * v1 + sb * sa * v2
    uz = -sb * v0 + cb * v2
    nrm = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / nrm, uy / nrm, uz / nrm
    rxy = math.hypot(ux, uy)
    a = math.atan2(uy, ux) if rxy > 1e-12 else alpha
    return a, math.atan2(-uz, rxy)


def dcm(psi: float, theta: float, phi: float):
    """``A = T_phi T_theta T_psi`` (Table II), row-major 9-tuple."""
    cs, ss = math.cos(psi), math.sin(psi)
    ct, st = math.cos(theta), math.sin(theta)
    cf, sf = math.cos(phi), math.sin(phi)
    return (ct * cs, ct * ss, -st,
            sf * st * cs - cf * ss, sf * st * ss + cf * cs, sf * ct,
            cf * st * cs + sf * ss, cf * st * ss - sf * cs, cf * ct)


def euler(a):
    """``(psi, theta, phi)`` of ``A = T_phi T_theta T_psi`` (9, row-major)."""
    s = -a[2]
    s = 1.0 if s > 1.0 else (-1.0 if s < -1.0 else s)
    return math.atan2(a[1], a[0]), math.asin(s), math.atan2(a[5], a[8])


def orientation_update(alpha, beta, psi, theta, phi, dphi0, dtheta0, dpsi0):
    """Eqs 29-31 and the update by addition: the new ``(psi, theta, phi)``
    from the tracking-frame errors. ``v = T_psi P^T d_0`` (eq 31's
    ``T_{psi-alpha} T_{-beta}``), then ``d_theta1 = v_y``,
    ``d_phi1 = v_x / cos theta``, ``d_psi1 = v_z + d_phi1 sin theta``. Near
    ``theta = +-90 deg`` (``|cos theta| < POLE_COS``) the orientation is
    composed instead, ``A <- A (I - [w]x)`` exactly as ``A exp(-[w]x)`` with
    ``w = P^T d_0``, and its angles read back."""
    ca, sa, cb, sb = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
    d0, d1, d2 = dphi0, dtheta0, dpsi0
    # w = P^T d (source frame)
    wx = cb * ca * d0 - sa * d1 + sb * ca * d2
    wy = cb * sa * d0 + ca * d1 + sb * sa * d2
    wz = -sb * d0 + cb * d2
    ct = math.cos(theta)
    if abs(ct) >= POLE_COS:
        cs, ss = math.cos(psi), math.sin(psi)
        vx = cs * wx + ss * wy                                   # T_psi w
        vy = -ss * wx + cs * wy
        vz = wz
        dphi1 = vx / ct
        return wrap(psi + vz + dphi1 * math.sin(theta)), theta + vy, wrap(phi + dphi1)
    A = dcm(psi, theta, phi)
    # A exp(-[w]x) = A E^T with E = exp([w]x) (Rodrigues)
    t2 = wx * wx + wy * wy + wz * wz
    if t2 < 1e-12:
        f, g = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = math.sqrt(t2)
        f, g = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    e00, e11, e22 = 1.0 - g * (wy * wy + wz * wz), 1.0 - g * (wx * wx + wz * wz), 1.0 - g * (wx * wx + wy * wy)
    e01, e10 = g * wx * wy - f * wz, g * wx * wy + f * wz
    e02, e20 = g * wx * wz + f * wy, g * wx * wz - f * wy
    e12, e21 = g * wy * wz - f * wx, g * wy * wz + f * wx
    n = [0.0] * 9
    for i in range(3):
        a0, a1, a2 = A[3 * i], A[3 * i + 1], A[3 * i + 2]
        n[3 * i] = a0 * e00 + a1 * e01 + a2 * e02
        n[3 * i + 1] = a0 * e10 + a1 * e11 + a2 * e12
        n[3 * i + 2] = a0 * e20 + a1 * e21 + a2 * e22
    return euler(n)


def angles_from_pose(px: float, py: float, pz: float, R):
    """Raab's ``(alpha, beta, rho, psi, theta, phi)`` of a sensor at ``p`` (m,
    from the source centre) with orientation ``R`` (sensor -> source, (3, 3)
    indexable ``R[i, j]``)."""
    rho = math.sqrt(px * px + py * py + pz * pz)
    rxy = math.hypot(px, py)
    alpha = math.atan2(py, px) if rxy > 0.0 else 0.0
    beta = math.atan2(-pz, rxy)
    # A = R^T: A[i][j] = R[j, i]
    a = (R[0, 0], R[1, 0], R[2, 0], R[0, 1], R[1, 1], R[2, 1], R[0, 2], R[1, 2], R[2, 2])
    psi, theta, phi = euler(a)
    return alpha, beta, rho, psi, theta, phi


def is_rotation(m) -> bool:
    """``m`` (9, row-major) is orthonormal with determinant +1 to ``_ORTHO_TOL``
    (then it is its own nearest rotation)."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8]
    t = _ORTHO_TOL
    if not (abs(a0 * a0 + a1 * a1 + a2 * a2 - 1.0) < t and abs(a3 * a3 + a4 * a4 + a5 * a5 - 1.0) < t
            and abs(a6 * a6 + a7 * a7 + a8 * a8 - 1.0) < t and abs(a0 * a3 + a1 * a4 + a2 * a5) < t
            and abs(a0 * a6 + a1 * a7 + a2 * a8) < t and abs(a3 * a6 + a4 * a7 + a5 * a8) < t):
        return False
    return a0 * (a4 * a8 - a5 * a7) - a1 * (a3 * a8 - a5 * a6) + a2 * (a3 * a7 - a4 * a6) > 0.0


def load_rotation(m9, R, Rn, work) -> None:
    """The start's rotation ``m9`` (9, row-major) into ``R`` (``R[i, j]``, a view
    of the array ``Rn``): as it is when it is a rotation already to
    ``_ORTHO_TOL`` (the tracked pose is its own nearest rotation), else its
    nearest rotation (``linalg.nearest_rotation`` with the scratch ``work``)."""
    if is_rotation(m9):
        R[0, 0], R[0, 1], R[0, 2] = m9[0], m9[1], m9[2]
        R[1, 0], R[1, 1], R[1, 2] = m9[3], m9[4], m9[5]
        R[2, 0], R[2, 1], R[2, 2] = m9[6], m9[7], m9[8]
    else:
        nearest_rotation(m9, Rn, work)


def moment_pseudo_inverse(n: int, mpa, cur, mom, mp) -> bool:
    """The coil moments at the currents ``M`` (3, n) into ``mom`` (``[3 j +
    a]``, from the moments per ampere ``mpa``) and ``M^+ = M^T (M M^T)^-1``
    into ``mp`` (``[3 j + c]``): the fixed source-frame pattern of Raab's
    *Variations* (sec. V) applied in computation, ``F = S M^+``; False if
    the moments do not span 3-D."""
    g00 = g01 = g02 = g11 = g12 = g22 = 0.0
    for j in range(n):
        c = cur[j]
        mx, my, mz = mpa[3 * j] * c, mpa[3 * j + 1] * c, mpa[3 * j + 2] * c
        mom[3 * j], mom[3 * j + 1], mom[3 * j + 2] = mx, my, mz
        g00 += mx * mx
        g01 += mx * my
        g02 += mx * mz
        g11 += my * my
        g12 += my * mz
        g22 += mz * mz
    scale = g00 + g11 + g22
    if not scale > 0.0:
        return False
    a00, a01, a02, a11, a12, a22 = g00 / scale, g01 / scale, g02 / scale, g11 / scale, g12 / scale, g22 / scale
    det = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
    inv = inv3_sym(a00, a01, a02, a11, a12, a22) if det > 1e-12 else None
    if inv is None:
        return False
    i00, i01, i02, i11, i12, i22 = inv[0] / scale, inv[1] / scale, inv[2] / scale, inv[3] / scale, \
        inv[4] / scale, inv[5] / scale
    for j in range(n):
        mx, my, mz = mom[3 * j], mom[3 * j + 1], mom[3 * j + 2]
        mp[3 * j] = mx * i00 + my * i01 + mz * i02
        mp[3 * j + 1] = mx * i01 + my * i11 + mz * i12
        mp[3 * j + 2] = mx * i02 + my * i12 + mz * i22
    return True


def coupling(n: int, Sc, mp, F) -> float:
    """``F = S_c M^+ = sum_j s_j (M^+_j)^T`` (3 x 3, row-major) into ``F``
    for the signals ``Sc`` (``[3 j + i]``) and ``M^+`` (``mp``); returns
    ``k = |F|_F / sqrt(3/2)``, which is ``C / rho^3`` (the rotation invariant
    of eq 21)."""
    f0 = f1 = f2 = f3 = f4 = f5 = f6 = f7 = f8 = 0.0
    for j in range(n):
        o = 3 * j
        s0, s1, s2 = Sc[o], Sc[o + 1], Sc[o + 2]
        m0, m1, m2 = mp[o], mp[o + 1], mp[o + 2]
        f0 += s0 * m0
        f1 += s0 * m1
        f2 += s0 * m2
        f3 += s1 * m0
        f4 += s1 * m1
        f5 += s1 * m2
        f6 += s2 * m0
        f7 += s2 * m1
        f8 += s2 * m2
    F[0], F[1], F[2], F[3], F[4], F[5], F[6], F[7], F[8] = f0, f1, f2, f3, f4, f5, f6, f7, f8
    return math.sqrt(f0 * f0 + f1 * f1 + f2 * f2 + f3 * f3 + f4 * f4 + f5 * f5 + f6 * f6 + f7 * f7
                     + f8 * f8) / _SQRT15


def post_sense(x, R, F):
    """Eqs 7 and 11 in closed form: the six off-diagonal elements ``(xy, yx,
    xz, zx, yz, zy)`` of ``F_7 = P R F P^T`` (all that eqs 22-26 read; the
    range comes from the invariant) for the coupling ``F`` (9, row-major)
    at the estimate ``x = (alpha, beta, rho, psi, theta, phi)`` with rotation
    ``R`` (sensor -> source, ``R[i, j]``), as ``(P R) (F P^T)``: 45 products."""
    ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
    # P = T_beta T_alpha (eq 4), rows
    p00, p01, p02 = cb * ca, cb * sa, -sb
    p10, p11 = -sa, ca
    p20, p21, p22 = sb * ca, sb * sa, cb
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2],
                                                   R[2, 0], R[2, 1], R[2, 2])
    # A = P R, rows
    a00, a01, a02 = p00 * r00 + p01 * r10 + p02 * r20, p00 * r01 + p01 * r11 + p02 * r21, \
        p00 * r02 + p01 * r12 + p02 * r22
    a10, a11, a12 = p10 * r00 + p11 * r10, p10 * r01 + p11 * r11, p10 * r02 + p11 * r12
    a20, a21, a22 = p20 * r00 + p21 * r10 + p22 * r20, p20 * r01 + p21 * r11 + p22 * r21, \
        p20 * r02 + p21 * r12 + p22 * r22
    f0, f1, f2, f3, f4, f5, f6, f7, f8 = F[0], F[1], F[2], F[3], F[4], F[5], F[6], F[7], F[8]
    # H = F P^T, column b = F (row b of P)
    h0x, h1x, h2x = f0 * p00 + f1 * p01 + f2 * p02, f3 * p00 + f4 * p01 + f5 * p02, f6 * p00 + f7 * p01 + f8 * p02
    h0y, h1y, h2y = f0 * p10 + f1 * p11, f3 * p10 + f4 * p11, f6 * p10 + f7 * p11
    h0z, h1z, h2z = f0 * p20 + f1 * p21 + f2 * p22, f3 * p20 + f4 * p21 + f5 * p22, f6 * p20 + f7 * p21 + f8 * p22
    return (a00 * h0y + a01 * h1y + a02 * h2y, a10 * h0x + a11 * h1x + a12 * h2x,
            a00 * h0z + a01 * h1z + a02 * h2z, a20 * h0x + a21 * h1x + a22 * h2x,
            a10 * h0z + a11 * h1z + a12 * h2z, a20 * h0y + a21 * h1y + a22 * h2y)


def detect(x, R, F, k: float):
    """Raab's detection of the errors of the estimate ``x`` (rotation ``R``)
    from the coupling ``F`` with ``k = C / rho^3``: eqs 7 and 11
    (:func:`post_sense`), the error angles of eqs 22-26 (as
    :func:`error_angles`) and the range of eq 21; returns ``(d_alpha0,
    d_beta0, d_rho, d_psi0, d_theta0, d_phi0)`` (rad, m) in the tracking
    frame."""
    fxy, fyx, fxz, fzx, fyz, fzy = post_sense(x, R, F)
    inv = 1.0 / k                                           # eqs 22-26 (as error_angles)
    fxy, fyx, fxz, fzx, fyz, fzy = fxy * inv, fyx * inv, fxz * inv, fzx * inv, fyz * inv, fzy * inv
    da0, db0 = (2.0 / 3.0) * (2.0 * fxy - fyx), (2.0 / 3.0) * (fzx - 2.0 * fxz)
    dpsi0, dth0, dphi0 = 2.0 * (fxy - fyx), 2.0 * (fzx - fxz), fzy - fyz
    rho = (C_RAAB / k) ** (1.0 / 3.0)                       # eq 21
    return da0, db0, rho - x[2], dpsi0, dth0, dphi0


def residual_cost(n: int, x, R, Sc, w, mom) -> float:
    """``sum ((S_c - h_raab(x)) / sigma)^2``: the residual of the corrected
    signals ``Sc`` (``[3 j + i]``; ``S_c = S - d - D dx``, the residual
    against the exact model) with weights ``w = 1 / sigma`` at the estimate
    ``x`` (rotation ``R``), ``h_raab`` Raab's dipole (eq 5,
    ``model.field.dipole_polar``) of the moments at the currents ``mom``."""
    ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
    ux, uy, uz = cb * ca, cb * sa, -sb
    cost = 0.0
    for j in range(n):
        o = 3 * j
        bx, by, bz = dipole_polar(ux, uy, uz, x[2], mom[o], mom[o + 1], mom[o + 2], False)
        for i in range(3):
            e = (Sc[o + i] - (R[0, i] * bx + R[1, i] * by + R[2, i] * bz)) * w[o + i]
            cost += e * e
    return cost


def point(x, c):
    """The source-frame point of Raab's coordinates ``x`` about the centre ``c``."""
    ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
    r = x[2]
    return c[0] + r * cb * ca, c[1] + r * cb * sa, c[2] - r * sb


def sync_rotation(x, R) -> None:
    """``R = A^T`` (``R[i, j]``) of the angles ``x[3:6]`` (:func:`dcm`)."""
    a = dcm(x[3], x[4], x[5])
    R[0, 0], R[0, 1], R[0, 2] = a[0], a[3], a[6]
    R[1, 0], R[1, 1], R[1, 2] = a[1], a[4], a[7]
    R[2, 0], R[2, 1], R[2, 2] = a[2], a[5], a[8]


# Update.out: the clipped steps, k and the acquisition test (core/include/ct_ac.h: CT_RO_*)
DA0, DB0, DRHO, DPSI0, DTH0, DPHI0, K_OUT, ACQUIRED = range(8)


class Update:
    """One update of eqs 7-31 on a tracker's buffers (``pose.raab.RaabTracker``): the signals
    corrected at the estimate by ``corrector`` (``pose.raab_correction``) into ``Sc``, ``F =
    S_c M^+`` and ``k = C / rho^3`` (eq 21), the detection (eqs 7, 11, 22-26) solved through the
    corrector's ``K``, each step clipped to ``max_step`` (Fig. 8), converted and added (eqs
    27-31) to ``x`` (alpha, beta, rho, psi, theta, phi), and ``R = A^T`` again. :meth:`run`
    returns False (nothing updated) when ``k`` is not positive and finite; ``out``: the clipped
    steps, ``k`` and whether the unclipped angle steps were all below ``acquired_step``.

    ``x`` (6), ``Rn`` (3, 3), ``S``, ``Sc``, ``mp`` (3 n), ``F`` (9), ``pm`` (3), ``cur`` (n):
    float64 buffers the tracker owns; ``cbar`` the source centre. On a compiled ``core`` the
    kernel ``ct_raab_update`` (``core/src/raab.c``: the same operations in the same order) is
    bound here to them and :meth:`run`, :meth:`couple` and :meth:`pseudo_inverse` replaced on this
    instance."""

    def __init__(self, n: int, x, Rn, S, Sc, mp, F, pm, cbar, cur, corrector, max_step: float,
                 acquired_step: float, core=_DEFAULT_CORE):
        self.n = n
        self.x, self.Rn, self.R, self.S, self.Sc, self.mp, self.F = x, Rn, memoryview(Rn), S, Sc, mp, F
        self.pm, self.cbar, self.cur = pm, tuple(cbar), cur
        self.corrector = corrector
        self.max_step = float(max_step)
        self.acquired_step = float(acquired_step)
        self.out = np.zeros(8)
        self._o = memoryview(self.out)
        self.core = "python"
        if core.ext is not None and n <= 64:
            self._bind_compiled(core.ext)

    def _bind_compiled(self, ext) -> None:
        """``run`` on ``ct_raab_update``, its buffers and constants bound once."""
        bufs = self.corrector.kernel_buffers()
        zero = np.zeros(max(9 * self.n, 36))
        b, G, K, perm = bufs if bufs is not None else (zero, zero, zero, np.zeros(6, dtype=np.int64))
        self._par = np.array([C_RAAB, POLE_COS, self.max_step, rc.LIN_MAX, rc.LIN_STEP, self.acquired_step])
        self._cb = np.array(self.cbar)
        self._ck = ext.Raab(self.n, bufs is not None, self._par, self._cb, self.S, self.mp, self.cur, self.Sc, self.F,
                            self.x, self.Rn, self.pm, b, G, K, perm, self.out)
        self._zero = zero
        self.run = self._run_compiled
        self.couple = self._couple_compiled
        self.pseudo_inverse = self._pseudo_inverse_compiled
        self.core = "compiled"

    def pseudo_inverse(self, mpa, mom) -> bool:
        """:func:`moment_pseudo_inverse` of the moments per ampere ``mpa`` at the currents ``cur``:
        the moments into ``mom`` and ``M^+`` into ``mp`` (the tracker's ``begin``)."""
        return moment_pseudo_inverse(self.n, mpa, self.cur, mom, self.mp)

    def _pseudo_inverse_compiled(self, mpa, mom) -> bool:
        return self._ck.pseudo_inverse(mpa, mom)

    def couple(self) -> float:
        """The signals corrected at the estimate into ``Sc``, ``F = S_c M^+`` and ``k = C /
        rho^3`` (eq 21; also into ``out``), returned: the first part of :meth:`run`
        (``pose.raab.RaabTracker._coupling``)."""
        x = self.x
        self.corrector.correct(self.S, self.Sc, self.n, point(x, self.cbar), self.pm, self.R, x[2], self.cur)
        k = self._o[K_OUT] = coupling(self.n, self.Sc, self.mp, self.F)
        return k

    def _couple_compiled(self) -> float:
        if self._ck.couple() & 2:                   # the estimate left the linear term's range (correct)
            self.corrector.drop_linear()
        return self._o[K_OUT]

    def run(self) -> bool:
        x, R, corr, o = self.x, self.R, self.corrector, self._o
        corr.correct(self.S, self.Sc, self.n, point(x, self.cbar), self.pm, R, x[2], self.cur)
        k = o[K_OUT] = coupling(self.n, self.Sc, self.mp, self.F)
        if not (k > 0.0 and math.isfinite(k)):
            return False
        da0, db0, drho, dpsi0, dth0, dphi0 = corr.precondition_step(x[2], detect(x, R, self.F, k))
        o[ACQUIRED] = 1.0 if max(abs(da0), abs(db0), abs(dpsi0), abs(dth0), abs(dphi0)) < self.acquired_step else 0.0
        m = self.max_step
        da0, db0, dpsi0, dth0, dphi0 = clip(da0, m), clip(db0, m), clip(dpsi0, m), clip(dth0, m), clip(dphi0, m)
        drho = clip(drho, m * x[2])
        rho = x[2] + drho
        psi, theta, phi = orientation_update(x[0], x[1], x[3], x[4], x[5], dphi0, dth0, dpsi0)
        x[0], x[1] = position_update(x[0], x[1], da0, db0)
        x[2], x[3], x[4], x[5] = rho, psi, theta, phi
        sync_rotation(x, R)
        o[DA0], o[DB0], o[DRHO], o[DPSI0], o[DTH0], o[DPHI0] = da0, db0, drho, dpsi0, dth0, dphi0
        return True

    def _run_compiled(self) -> bool:
        corr = self.corrector
        r = self._ck.update(corr.lin, corr.k_id)
        if r & 2:                                   # the estimate left the linear term's range (correct)
            corr.drop_linear()
        return r & 1 == 1
