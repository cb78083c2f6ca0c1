"""Magnetic field models of the source coils (numpy only).

Everything is in SI units: positions in m, currents in A, moments in A m^2,
flux density in T, field gradients in T/m.  ``MU0 = 4e-7 * pi`` exactly.

Coil frame
    A circular loop of radius ``a`` lies in the xy-plane, centred at the
    origin; a positive current circulates counter-clockwise seen from +z, so
    the field on the axis points along +z.  ``rho = sqrt(x^2 + y^2)``.

Models
    exact
        Field of a thin circular loop, Schepers & Veltink 2010
        (``000_e46ec0e8bf7ea271.txt``) eqs 6-7 (Smythe form), multiplied by
        the number of turns.  The elliptic integrals are evaluated with the
        arithmetic-geometric mean (AGM) in a form that stays accurate on and
        near the axis, near the wire and far away (see ``_loop_core``).
    dipole
        Point dipole of moment ``m = N I pi a^2`` along the coil axis,
        Schepers & Veltink eq 8.

Jacobians ``dB_i/dp_j`` are analytic (no finite differences).  For the
dipole this is the general form of Schepers & Veltink eq 10; for the exact
loop it is the direct differentiation of eqs 6-7, propagated through the AGM
iteration, and assembled using div B = 0 and curl B = 0, so the returned
matrices are exactly symmetric and traceless.

Functions accept ``out=`` buffers of the documented shape so a caller with
fixed-size state can avoid allocating the results.  For up to eight points
the loop kernel runs on Python floats (the shape a C port takes, and ~5x
faster than numpy on tiny arrays); above that it is vectorised.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = [
    "MU0",
    "agm_ellipke",
    "loop_field",
    "loop_jacobian",
    "dipole_field",
    "dipole_jacobian",
    "dipole_point",
    "dipole_polar",
    "loop_point",
    "Coil",
    "CoilSet",
    "orthogonal_source",
]

#: vacuum permeability, T m / A (pre-2019 SI definition, used throughout)
MU0 = 4e-7 * math.pi
#: ``mu0 / 2 pi`` (T m / A): Raab's ``C`` of eq 3 per unit moment (``seeds/004_86267342cd7488ce.txt``),
#: the dipole's axial field ``C m / rho^3`` (:func:`dipole_polar`)
MU0_2PI = MU0 / (2.0 * math.pi)

_HALF_PI = 0.5 * math.pi
# AGM iteration caps.  From k_c >= 1e-8 (any m < 1 representable in double)
# the AGM converges to machine precision in 8 steps; the loop kernel may
# start much closer to the wire singularity, where the iteration needs a few
# more steps (ratio 1e-150 -> 12 steps).
_AGM_MAX_ITER = 12
_LOOP_MAX_ITER = 20
_AGM_TOL = 1e-15
# up to this many points the loop kernel runs on Python floats
_SCALAR_MAX = 8
# smallest value used for alpha^2 beta^2 (exactly on the wire)
_TINY = 1e-300


# ---------------------------------------------------------------------------
# complete elliptic integrals
# ---------------------------------------------------------------------------
def agm_ellipke(m, out_k=None, out_e=None):
    """Complete elliptic integrals of the first and second kind by the AGM.

    ``K(m) = int_0^{pi/2} (1 - m sin^2 t)^{-1/2} dt`` and
    ``E(m) = int_0^{pi/2} (1 - m sin^2 t)^{1/2} dt`` with the *parameter*
    ``m = k^2`` (the convention of ``scipy.special.ellipk``), as in the
    integrals below Schepers & Veltink eq 7 (there written with the modulus k).

    Gauss' AGM: ``a0 = 1``, ``b0 = sqrt(1 - m)``, ``c0^2 = m``;
    ``a_{n+1} = (a_n + b_n)/2``, ``b_{n+1} = sqrt(a_n b_n)``,
    ``c_{n+1} = c_n^2 / (4 a_{n+1})`` (the subtraction-free form of
    ``(a_n - b_n)/2``).  Then ``K = pi / (2 a_inf)`` and
    ``E = K (1 - sum_n 2^(n-1) c_n^2)``.  The iteration stops when
    ``max |a - b| <= 1e-15 a`` (at most 12 steps).

    Parameters
    ----------
    m : float or array_like, any shape
        Parameter, ``m <= 1`` (negative values allowed).  ``m = 1`` gives
        ``K = inf, E = 1``; ``m > 1`` or NaN gives NaN.
    out_k, out_e : ndarray, optional
        Float64 buffers of the shape of ``m`` for the results.

    Returns
    -------
    K, E : ndarray (shape of ``m``) or float (scalar ``m``)
    """
    m_arr = np.asarray(m, dtype=float)
    scalar = m_arr.ndim == 0
    m1 = np.atleast_1d(m_arr)
    k_out = np.empty(m1.shape) if (out_k is None or scalar) else out_k
    e_out = np.empty(m1.shape) if (out_e is None or scalar) else out_e
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.ones(m1.shape)
        b = np.sqrt(1.0 - m1)
        c = np.empty(m1.shape)
        # sum_n 2^(n-1) c_n^2, term n = 0 is m / 2
        ssum = 0.5 * m1
        # c_1 = c_0^2 / (4 a_1) with a_1 = (1 + b0) / 2
        np.add(a, b, out=c)
        c *= 0.5  # a_1
        np.multiply(a, b, out=b)
        np.sqrt(b, out=b)  # b_1
        a, c = c, np.divide(m1, 4.0 * c)  # a_1, c_1
        w = 1.0
        tmp = np.empty(m1.shape)
        for _ in range(_AGM_MAX_ITER):
            np.multiply(c, c, out=tmp)
            tmp *= w
            ssum += tmp
            np.subtract(a, b, out=tmp)
            np.abs(tmp, out=tmp)
            if not np.any(tmp > _AGM_TOL * a):
                break
            # next step: a' = (a+b)/2, b' = sqrt(ab), c' = c^2 / (4 a')
            np.multiply(a, b, out=tmp)
            a += b
            a *= 0.5
            np.sqrt(tmp, out=b)
            c *= c
            c /= a
            c *= 0.25
            w *= 2.0
        np.divide(_HALF_PI, a, out=k_out)
        np.subtract(1.0, ssum, out=e_out)
        e_out *= k_out
        one = m1 == 1.0
        if np.any(one):
            k_out[one] = np.inf
            e_out[one] = 1.0
    if scalar:
        return float(k_out[0]), float(e_out[0])
    return k_out, e_out


# ---------------------------------------------------------------------------
# circular loop, exact
# ---------------------------------------------------------------------------
def _unconverged_array(a, b):
    return bool(np.any(np.abs(a - b) > _AGM_TOL * a))


def _unconverged_scalar(a, b):
    return abs(a - b) > _AGM_TOL * a


def _loop_core(u, z, jac, sqrt=np.sqrt, maximum=np.maximum, unconverged=_unconverged_array):
    """Dimensionless loop field functions in the coil frame.

    Coordinates are normalised by the loop radius ``a``: ``u = (rho/a)^2``,
    ``z = z/a``.  With ``C0 = mu0 N I / (2 pi a)`` the field is::

        B = C0 * (x/a * F, y/a * F, G)

    and, if ``jac``, ``Fz = dF/dz`` and ``H = 2 dF/du`` (i.e. ``(dF/drho)/rho``)
    are returned as well.  Three steps: the start of the AGM from
    ``(beta, alpha)`` (here), the AGM with its series ``S`` (:func:`_agm_series`,
    or :func:`_agm_series_jac` with the derivatives carried forward), and the
    field functions (:func:`_loop_fg`, :func:`_loop_fg_jac`); the derivation of
    Schepers & Veltink eqs 6-7 in this form is in :func:`_agm_series`.

    The same code runs on numpy arrays and, with ``sqrt=math.sqrt``,
    ``maximum=max`` and ``unconverged=_unconverged_scalar``, on Python floats
    (faster for the few points a pose solve needs, and the form a C port
    takes: ``core/src/field.c ct_loop_core``).  It uses no ``**`` and no
    division that can hit zero, so the float path cannot raise either.

    Parameters
    ----------
    u, z : ndarray, shape (n,), or float
    jac : bool

    Returns
    -------
    F, G : ndarray, shape (n,), or float
    Fz, H : ndarray, shape (n,), or float   (only if ``jac``)
    """
    rho = sqrt(u)
    z2 = z * z
    s = 1.0 + u + z2
    omr = 1.0 - rho
    opr = 1.0 + rho
    one_m_u = omr * opr  # 1 - u, accurate near the wire
    P = maximum((omr * omr + z2) * (opr * opr + z2), _TINY)
    q = sqrt(P)  # alpha * beta
    a = sqrt(0.5 * (s + q))  # a_1 = (alpha + beta) / 2
    b = sqrt(q)  # b_1 = sqrt(alpha beta)
    d = 1.0 / (a * a)  # d_1
    if not jac:
        M, S = _agm_series(u, a, b, d, sqrt, unconverged)
        return _loop_fg(u, z, z2, s, one_m_u, P, M, S)
    M, S, dM, dS, P_u, P_z = _agm_series_jac(u, z, z2, s, one_m_u, P, q, a, b, d, sqrt, unconverged)
    return _loop_fg_jac(u, z, z2, s, one_m_u, P, M, S, dM, dS, P_u, P_z)


def _agm_series(u, a, b, d, sqrt, unconverged):
    """The AGM from ``(a_1, b_1)`` and the series ``S``; returns ``(M, S)``.

    Derivation (Schepers & Veltink eqs 6-7, radius normalised to 1).  With
    ``alpha^2 = (1-rho)^2 + z^2``, ``beta^2 = (1+rho)^2 + z^2``,
    ``s = 1 + rho^2 + z^2``, ``m = 1 - alpha^2/beta^2`` (eq 7, ``m = k^2``),
    run the AGM from ``(beta, alpha)``, which is the AGM of eq ``agm_ellipke``
    scaled by beta.  Its limit ``M = AGM(beta, alpha)`` and the terms
    ``c_n`` (n >= 1) are even functions of rho (``a_1 = (alpha+beta)/2``,
    ``b_1 = sqrt(alpha beta)`` are symmetric in alpha, beta), and::

        K = pi beta / (2 M)
        E = K (1 - (2 rho + rho^2 S) / beta^2),  S = sum_{n>=1} 2^(n-1) (c_n/rho)^2

    ``d_n = (c_n/rho)^2`` obeys ``d_1 = 1/a_1^2``,
    ``d_{n+1} = u d_n^2 / (16 a_{n+1}^2)``: no subtraction and no division by
    rho.  Substituting into eq 6 gives, with ``P = alpha^2 beta^2``::

        B_rho / rho = C0 * pi z (4 - s S) / (2 M P)                       = C0 F
        B_z         = C0 * pi (2 (1 - u + z^2) - (2 - s) u S) / (2 M P)  = C0 G

    Both are smooth in ``u = rho^2``; the cancellations of the textbook form
    near the axis (``(a^2+r^2) E - alpha^2 K = O(rho^2)``) and far away are
    gone.  ``P`` is clamped to 1e-300 exactly on the wire.
    """
    S = 1.0 * d  # a new array (or float), updated in place below
    w = 1.0
    for _ in range(_LOOP_MAX_ITER):
        if not unconverged(a, b):
            break
        an = 0.5 * (a + b)
        bn = sqrt(a * b)
        r16 = 1.0 / (16.0 * an * an)
        dn = u * d * d * r16
        a, b, d = an, bn, dn
        w *= 2.0
        S += w * d
    return 0.5 * (a + b), S


def _agm_series_jac(u, z, z2, s, one_m_u, P, q, a, b, d, sqrt, unconverged):
    """:func:`_agm_series` with the first derivatives with respect to ``u``
    (suffix ``_u``) and ``z`` (suffix ``_z``) propagated alongside the AGM
    (forward mode); returns ``(M, S, (M_u, M_z), (S_u, S_z), P_u, P_z)``."""
    P_u = 2.0 * (z2 - one_m_u)
    P_z = 4.0 * z * s
    q_u = P_u / (2.0 * q)
    q_z = P_z / (2.0 * q)
    a_u = (1.0 + q_u) / (4.0 * a)
    a_z = (2.0 * z + q_z) / (4.0 * a)
    b_u = q_u / (2.0 * b)
    b_z = q_z / (2.0 * b)
    d_u = -2.0 * d * a_u / a
    d_z = -2.0 * d * a_z / a
    S = 1.0 * d  # a new array (or float), updated in place below
    S_u = 1.0 * d_u
    S_z = 1.0 * d_z
    w = 1.0
    for _ in range(_LOOP_MAX_ITER):
        if not unconverged(a, b):
            break
        an = 0.5 * (a + b)
        bn = sqrt(a * b)
        r16 = 1.0 / (16.0 * an * an)
        dn = u * d * d * r16
        an_u = 0.5 * (a_u + b_u)
        an_z = 0.5 * (a_z + b_z)
        bn_u = (a_u * b + a * b_u) / (2.0 * bn)
        bn_z = (a_z * b + a * b_z) / (2.0 * bn)
        dn_u = (d * d + 2.0 * u * d * d_u) * r16 - 2.0 * dn * an_u / an
        dn_z = (2.0 * u * d * d_z) * r16 - 2.0 * dn * an_z / an
        a_u, a_z, b_u, b_z, d_u, d_z = an_u, an_z, bn_u, bn_z, dn_u, dn_z
        a, b, d = an, bn, dn
        w *= 2.0
        S += w * d
        S_u += w * d_u
        S_z += w * d_z
    return 0.5 * (a + b), S, (0.5 * (a_u + b_u), 0.5 * (a_z + b_z)), (S_u, S_z), P_u, P_z


def _loop_fg(u, z, z2, s, one_m_u, P, M, S):
    """``F`` and ``G`` of :func:`_loop_core` from the AGM's ``M`` and ``S``
    (the formulas of :func:`_agm_series`)."""
    inv = _HALF_PI / (M * P)
    Nf = 4.0 - s * S
    F = z * Nf * inv
    G = (2.0 * (one_m_u + z2) - (one_m_u - z2) * u * S) * inv
    return F, G


def _loop_fg_jac(u, z, z2, s, one_m_u, P, M, S, dM, dS, P_u, P_z):
    """``F``, ``G``, ``Fz = dF/dz`` and ``H = 2 dF/du`` of :func:`_loop_core`
    from the AGM's ``M``, ``S`` and their derivatives."""
    inv = _HALF_PI / (M * P)
    Nf = 4.0 - s * S
    F = z * Nf * inv
    G = (2.0 * (one_m_u + z2) - (one_m_u - z2) * u * S) * inv
    M_u, M_z = dM
    S_u, S_z = dS
    Nf_u = -(S + s * S_u)
    Nf_z = -(2.0 * z * S + s * S_z)
    lu = M_u / M + P_u / P
    lz = M_z / M + P_z / P
    H = 2.0 * z * (Nf_u - Nf * lu) * inv
    Fz = (Nf + z * (Nf_z - Nf * lz)) * inv
    return F, G, Fz, H


def _as_points(points):
    p = np.asarray(points, dtype=float)
    if p.ndim == 1:
        if p.shape != (3,):
            raise ValueError("points must have shape (3,) or (n, 3)")
        return p.reshape(1, 3), True
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError("points must have shape (3,) or (n, 3)")
    return p, False


def _loop_eval(p, radius, scale, out_b, out_j):
    """Loop field and/or Jacobian at coil-frame points ``p`` (n, 3).

    ``radius`` and ``scale = mu0 N I / (2 pi a)`` are scalars or arrays (n,)
    (one loop per point).  Writes ``out_b`` (n, 3) and ``out_j`` (n, 3, 3)
    when given.
    """
    n = p.shape[0]
    if n <= _SCALAR_MAX:
        _loop_eval_scalar(p, radius, scale, out_b, out_j)
        return
    inv_a = 1.0 / radius
    xn = p[:, 0] * inv_a
    yn = p[:, 1] * inv_a
    zn = p[:, 2] * inv_a
    u = xn * xn + yn * yn
    jac = out_j is not None
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        if jac:
            F, G, Fz, H = _loop_core(u, zn, True)
        else:
            F, G = _loop_core(u, zn, False)
        if out_b is not None:
            np.multiply(xn, F, out=out_b[:, 0])
            np.multiply(yn, F, out=out_b[:, 1])
            out_b[:, 2] = G
            out_b *= np.reshape(scale, (-1, 1))
        if jac:
            g = scale * inv_a
            F *= g
            H *= g
            Fz *= g
            out_j[:, 0, 0] = F + xn * xn * H
            out_j[:, 1, 1] = F + yn * yn * H
            out_j[:, 2, 2] = -2.0 * F - u * H
            np.multiply(xn * yn, H, out=out_j[:, 0, 1])
            out_j[:, 1, 0] = out_j[:, 0, 1]
            np.multiply(xn, Fz, out=out_j[:, 0, 2])
            out_j[:, 2, 0] = out_j[:, 0, 2]
            np.multiply(yn, Fz, out=out_j[:, 1, 2])
            out_j[:, 2, 1] = out_j[:, 1, 2]


def _loop_eval_scalar(p, radius, scale, out_b, out_j):
    """``_loop_eval`` one point at a time with Python floats."""
    n = p.shape[0]
    rad = np.broadcast_to(radius, (n,))
    sca = np.broadcast_to(scale, (n,))
    sqrt = math.sqrt
    for i in range(n):
        inv_a = 1.0 / float(rad[i])
        xn = float(p[i, 0]) * inv_a
        yn = float(p[i, 1]) * inv_a
        zn = float(p[i, 2]) * inv_a
        u = xn * xn + yn * yn
        c = float(sca[i])
        if out_j is None:
            F, G = _loop_core(u, zn, False, sqrt, max, _unconverged_scalar)
        else:
            F, G, Fz, H = _loop_core(u, zn, True, sqrt, max, _unconverged_scalar)
            g = c * inv_a
            F2, H2, Fz2 = F * g, H * g, Fz * g
            J = out_j[i]
            J[0, 0] = F2 + xn * xn * H2
            J[1, 1] = F2 + yn * yn * H2
            J[2, 2] = -2.0 * F2 - u * H2
            J[0, 1] = J[1, 0] = xn * yn * H2
            J[0, 2] = J[2, 0] = xn * Fz2
            J[1, 2] = J[2, 1] = yn * Fz2
        if out_b is not None:
            Fc = c * F
            out_b[i, 0] = xn * Fc
            out_b[i, 1] = yn * Fc
            out_b[i, 2] = c * G


def _out_buffer(out, shape):
    if out is None:
        return np.empty(shape)
    if out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float64 array of shape {shape}")
    return out


def loop_field(points, radius, turns, current, out=None):
    """Exact flux density of a circular loop (coil frame).

    Schepers & Veltink 2010 (``000_e46ec0e8bf7ea271.txt``) eqs 6-7, evaluated
    in the cancellation-free AGM form of ``_loop_core``.  Relative error
    about 1e-15 (at most 5e-15 against a 60-digit reference) on the axis
    (``rho = 0`` exactly gives ``B_x = B_y = 0``), near it, near the wire
    and far away (tested to ``|p| = 1e4 a``).  Within a distance ``d`` of the
    wire the rounding of the input position alone limits the result to about
    ``1e-16 a / d``.  Points exactly on the wire return 0 and never raise.

    Parameters
    ----------
    points : array_like, shape (n, 3) or (3,)
        Observer positions in the coil frame, m.
    radius : float
        Loop radius ``a``, m (> 0).
    turns : int or float
        Number of turns ``N`` (all at the same radius).
    current : float
        Current ``I``, A.
    out : ndarray, shape (n, 3) or (3,), optional
        Buffer for the result.

    Returns
    -------
    B : ndarray, shape (n, 3) or (3,)
        Flux density in the coil frame, T.
    """
    p, single = _as_points(points)
    n = p.shape[0]
    res = _out_buffer(out, (3,) if single else (n, 3))
    scale = MU0 * turns * current / (2.0 * math.pi * radius)
    _loop_eval(p, radius, scale, res.reshape(n, 3), None)
    return res


def loop_jacobian(points, radius, turns, current, out=None):
    """Spatial Jacobian ``J[i, j] = dB_i / dp_j`` of the exact loop field.

    Direct differentiation of Schepers & Veltink eqs 6-7 (their eq 9 uses
    this block for the position part of the measurement Jacobian), computed
    alongside the AGM.  Valid on the axis.  ``J`` is symmetric and traceless
    (curl B = 0, div B = 0).

    Parameters
    ----------
    points : array_like, shape (n, 3) or (3,)
        Observer positions in the coil frame, m.
    radius : float
        Loop radius, m.
    turns : int or float
        Number of turns.
    current : float
        Current, A.
    out : ndarray, shape (n, 3, 3) or (3, 3), optional

    Returns
    -------
    J : ndarray, shape (n, 3, 3) or (3, 3)
        Field gradient in the coil frame, T/m.
    """
    p, single = _as_points(points)
    n = p.shape[0]
    res = _out_buffer(out, (3, 3) if single else (n, 3, 3))
    scale = MU0 * turns * current / (2.0 * math.pi * radius)
    _loop_eval(p, radius, scale, None, res.reshape(n, 3, 3))
    return res


# ---------------------------------------------------------------------------
# dipole
# ---------------------------------------------------------------------------
_MU0_4PI = 1e-7  # MU0 / (4 pi)


def _dipole_eval(p, mom, out_b, out_j):
    """Dipole field/Jacobian at points ``p`` (n, 3) for moments ``mom``
    (3,) or (n, 3)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        r2 = np.einsum("ij,ij->i", p, p)
        mp = (p @ mom) if mom.ndim == 1 else np.einsum("ij,ij->i", p, mom)
        inv_r2 = 1.0 / r2
        c = _MU0_4PI * inv_r2 / np.sqrt(r2)  # mu0/(4 pi r^3)
        if out_b is not None:
            # B = mu0/(4 pi r^3) (3 (m.r) r / r^2 - m)     (Schepers eq 8)
            np.multiply(p, (3.0 * mp * inv_r2)[:, None], out=out_b)
            out_b -= mom
            out_b *= c[:, None]
        if out_j is not None:
            # dB_i/dp_j = 3 mu0/(4 pi r^5) (m_i p_j + m_j p_i + (m.p) d_ij
            #                                - 5 (m.p) p_i p_j / r^2)
            # (general form of Schepers eq 10)
            c5 = 3.0 * c * inv_r2
            mb = np.broadcast_to(mom, p.shape)
            np.multiply(mb[:, :, None], p[:, None, :], out=out_j)
            out_j += np.swapaxes(out_j, 1, 2).copy()
            out_j -= (5.0 * mp * inv_r2)[:, None, None] * p[:, :, None] * p[:, None, :]
            for i in range(3):
                out_j[:, i, i] += mp
            out_j *= c5[:, None, None]


def dipole_field(points, moment, out=None):
    """Flux density of a point dipole at the origin.

    Schepers & Veltink (``000_e46ec0e8bf7ea271.txt``) eq 8, written for an
    arbitrary moment direction:
    ``B = mu0 / (4 pi r^3) (3 (m . r_hat) r_hat - m)``.

    Parameters
    ----------
    points : array_like, shape (n, 3) or (3,)
        Observer positions relative to the dipole, m.
    moment : array_like, shape (3,)
        Dipole moment, A m^2.
    out : ndarray, shape (n, 3) or (3,), optional

    Returns
    -------
    B : ndarray, shape (n, 3) or (3,)
        Flux density, T.  Non-finite at the origin.
    """
    p, single = _as_points(points)
    n = p.shape[0]
    res = _out_buffer(out, (3,) if single else (n, 3))
    _dipole_eval(p, np.asarray(moment, dtype=float), res.reshape(n, 3), None)
    return res


def dipole_jacobian(points, moment, out=None):
    """Spatial Jacobian ``J[i, j] = dB_i / dp_j`` of a point dipole.

    ``3 mu0 / (4 pi r^5) (m_i p_j + m_j p_i + (m.p) delta_ij
    - 5 (m.p) p_i p_j / r^2)``; for ``m`` along z and ``j = x`` this is
    Schepers & Veltink eq 10 (whose printed denominator exponent 5/2 must
    read 7/2, as differentiating eq 8 and the units T/m show).  Symmetric and
    traceless.

    Parameters
    ----------
    points : array_like, shape (n, 3) or (3,)
        Observer positions relative to the dipole, m.
    moment : array_like, shape (3,)
        Dipole moment, A m^2.
    out : ndarray, shape (n, 3, 3) or (3, 3), optional

    Returns
    -------
    J : ndarray, shape (n, 3, 3) or (3, 3)
        T/m.
    """
    p, single = _as_points(points)
    n = p.shape[0]
    res = _out_buffer(out, (3, 3) if single else (n, 3, 3))
    _dipole_eval(p, np.asarray(moment, dtype=float), None, res.reshape(n, 3, 3))
    return res


# ---------------------------------------------------------------------------
# coils in the source frame
# ---------------------------------------------------------------------------
def _complete_basis(axis):
    """Rotation matrix whose third column is the unit vector ``axis``."""
    n = axis / np.linalg.norm(axis)
    # helper: the coordinate axis least aligned with n
    k = int(np.argmin(np.abs(n)))
    h = np.zeros(3)
    h[k] = 1.0
    e1 = np.cross(h, n)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    R = np.empty((3, 3))
    R[:, 0] = e1
    R[:, 1] = e2
    R[:, 2] = n
    return R


class Coil:
    """A circular source coil: a pose plus radius and turns.

    Parameters
    ----------
    center : array_like, shape (3,)
        Loop centre in the source frame, m.
    axis : array_like, shape (3,)
        Loop axis in the source frame (normalised internally).  A positive
        current gives a moment along ``+axis``.
    radius : float
        Loop radius, m.
    turns : int
        Number of turns.
    gain : float, optional
        Calibrated moment relative to the nominal ``N pi a^2`` (default 1;
        Raab's source imperfection matrix, ``004`` sec. "Source and Sensor
        Imperfections", row by row: see ``coiltrack.firmware.calibration``).
        It scales the field, the gradient and the moment.

    Attributes
    ----------
    center : ndarray (3,)
    axis : ndarray (3,)      unit vector
    rotation : ndarray (3, 3)
        Maps coil-frame vectors to the source frame; its columns are an
        orthonormal completion ``(e1, e2, axis)`` of the axis.
    radius : float
    turns : int
    gain : float

    Orthogonal, tilted and offset sources all use the same code: a field is
    computed in the coil frame and rotated, ``B_src = R B_coil(R^T (p - c))``,
    ``J_src = R J_coil R^T``.
    """

    __slots__ = ("center", "axis", "rotation", "radius", "turns", "gain", "_area")

    def __init__(self, center, axis, radius, turns, gain=1.0):
        self.center = np.array(center, dtype=float).reshape(3)
        ax = np.array(axis, dtype=float).reshape(3)
        nrm = float(np.linalg.norm(ax))
        if not nrm > 0.0:
            raise ValueError("coil axis must be a non-zero vector")
        if not radius > 0.0:
            raise ValueError("coil radius must be positive")
        self.axis = ax / nrm
        self.rotation = _complete_basis(self.axis)
        self.radius = float(radius)
        self.turns = int(turns)
        if not (math.isfinite(gain) and gain > 0.0):
            raise ValueError("coil gain must be a positive number")
        self.gain = float(gain)
        self._area = math.pi * self.radius * self.radius * self.gain    # effective area (gain included)

    def __repr__(self):
        g = "" if self.gain == 1.0 else f", gain={self.gain}"
        return (f"Coil(center={self.center.tolist()}, axis={self.axis.tolist()}, "
                f"radius={self.radius}, turns={self.turns}{g})")

    def moment_magnitude(self, current):
        """``gain N I pi a^2`` in A m^2 (signed with the current)."""
        return self.turns * current * self._area

    def moment(self, current, out=None):
        """Dipole moment vector ``gain N I pi a^2 axis``, shape (3,), A m^2."""
        res = _out_buffer(out, (3,))
        np.multiply(self.axis, self.turns * current * self._area, out=res)
        return res

    def field(self, points, current, model="exact", out=None):
        """Flux density in the source frame.

        Parameters
        ----------
        points : array_like, shape (n, 3) or (3,)
            Observer positions in the source frame, m.
        current : float
            Coil current, A.
        model : {"exact", "dipole"}
        out : ndarray, shape (n, 3) or (3,), optional

        Returns
        -------
        B : ndarray, shape (n, 3) or (3,)
            T, source frame.
        """
        p, single = _as_points(points)
        n = p.shape[0]
        res = _out_buffer(out, (3,) if single else (n, 3))
        r2 = res.reshape(n, 3)
        d = p - self.center
        if model == "exact":
            pc = d @ self.rotation  # rows: R^T (p - c)
            scale = MU0 * self.turns * self.gain * current / (2.0 * math.pi * self.radius)
            _loop_eval(pc, self.radius, scale, r2, None)
            r2[...] = r2 @ self.rotation.T
        elif model == "dipole":
            _dipole_eval(d, self.moment(current), r2, None)
        else:
            raise ValueError(f"unknown field model {model!r}")
        return res

    def jacobian(self, points, current, model="exact", out=None):
        """Field gradient ``dB_i/dp_j`` in the source frame.

        Parameters
        ----------
        points : array_like, shape (n, 3) or (3,)
            Observer positions in the source frame, m.
        current : float
            Coil current, A.
        model : {"exact", "dipole"}
        out : ndarray, shape (n, 3, 3) or (3, 3), optional

        Returns
        -------
        J : ndarray, shape (n, 3, 3) or (3, 3)
            T/m, source frame.
        """
        p, single = _as_points(points)
        n = p.shape[0]
        res = _out_buffer(out, (3, 3) if single else (n, 3, 3))
        r3 = res.reshape(n, 3, 3)
        d = p - self.center
        if model == "exact":
            pc = d @ self.rotation
            scale = MU0 * self.turns * self.gain * current / (2.0 * math.pi * self.radius)
            _loop_eval(pc, self.radius, scale, None, r3)
            R = self.rotation
            r3[...] = R @ r3 @ R.T
        elif model == "dipole":
            _dipole_eval(d, self.moment(current), None, r3)
        else:
            raise ValueError(f"unknown field model {model!r}")
        return res


class CoilSet:
    """A fixed set of coils packed for batched evaluation at one point.

    The solvers evaluate every coil of a source at the same sensor position;
    packing the coil geometry into arrays lets one vectorised AGM pass serve
    all coils.  Scratch buffers are allocated once here.

    Parameters
    ----------
    coils : sequence of Coil, length n

    Attributes
    ----------
    coils : tuple of Coil
    n : int
    centers : ndarray (n, 3), m
    axes : ndarray (n, 3), unit vectors
    rotations : ndarray (n, 3, 3), coil frame -> source frame
    radii : ndarray (n,), m
    turns : ndarray (n,)
    """

    def __init__(self, coils):
        self.coils = tuple(coils)
        n = len(self.coils)
        if n == 0:
            raise ValueError("a CoilSet needs at least one coil")
        self.n = n
        self.centers = np.array([c.center for c in self.coils])
        self.axes = np.array([c.axis for c in self.coils])
        self.rotations = np.array([c.rotation for c in self.coils])
        self.radii = np.array([c.radius for c in self.coils])
        self.turns = np.array([float(c.turns) for c in self.coils])
        self.gains = np.array([float(c.gain) for c in self.coils])
        # field scale per ampere, gain mu0 N / (2 pi a), and moment per ampere
        self._scale_per_amp = MU0 * self.turns * self.gains / (2.0 * math.pi * self.radii)
        self._moment_per_amp = self.turns * self.gains * math.pi * self.radii ** 2
        self._rot_t = np.ascontiguousarray(np.swapaxes(self.rotations, 1, 2))
        self._d = np.empty((n, 3))
        self._pc = np.empty((n, 3))
        self._bc = np.empty((n, 3))
        self._jc = np.empty((n, 3, 3))
        self._jt = np.empty((n, 3, 3))
        self._jout = np.empty((n, 3, 3))  # for callers that discard J
        self._mom = np.empty((n, 3))
        self._scale = np.empty(n)

    def __len__(self):
        return self.n

    def moments(self, currents, out=None):
        """Dipole moments ``N_j I_j pi a_j^2 axis_j``, shape (n, 3), A m^2."""
        res = _out_buffer(out, (self.n, 3))
        np.multiply(self.axes, (self._moment_per_amp * np.asarray(currents, dtype=float))[:, None],
                    out=res)
        return res

    def fields(self, point, currents, model="exact", out_b=None, out_j=None):
        """Field and field gradient of every coil at one source-frame point.

        Parameters
        ----------
        point : array_like, shape (3,)
            Observer position in the source frame, m.
        currents : array_like, shape (n,)
            Current of each coil, A.
        model : {"exact", "dipole"}
        out_b : ndarray, shape (n, 3), optional
            Buffer for ``B[j]``, the field of coil j (T, source frame).
        out_j : ndarray, shape (n, 3, 3), optional
            Buffer for ``J[j] = dB[j]/dp`` (T/m, source frame).  The gradient
            is computed only when ``out_j`` is given.

        Returns
        -------
        B : ndarray, shape (n, 3)
        J : ndarray, shape (n, 3, 3) or None
        """
        n = self.n
        B = _out_buffer(out_b, (n, 3))
        np.subtract(point, self.centers, out=self._d)
        cur = np.asarray(currents, dtype=float)
        if model == "exact":
            # coil-frame points: R_j^T (p - c_j)
            np.einsum("nij,nj->ni", self._rot_t, self._d, out=self._pc)
            np.multiply(self._scale_per_amp, cur, out=self._scale)
            jc = self._jc if out_j is not None else None
            _loop_eval(self._pc, self.radii, self._scale, self._bc, jc)
            np.einsum("nij,nj->ni", self.rotations, self._bc, out=B)
            if out_j is not None:
                np.matmul(self.rotations, jc, out=self._jt)
                np.matmul(self._jt, self._rot_t, out=out_j)
        elif model == "dipole":
            mom = self.moments(cur, out=self._mom)
            _dipole_eval(self._d, mom, B, out_j)
        else:
            raise ValueError(f"unknown field model {model!r}")
        return B, out_j


def orthogonal_source(radius, turns, center=(0.0, 0.0, 0.0)):
    """Three co-centred coils with axes x, y, z (thesis ch. 5 source).

    Parameters
    ----------
    radius : float
        Coil radius, m (thesis: 0.055 m).
    turns : int
        Turns per coil (thesis: 50).
    center : array_like, shape (3,)
        Common centre, m.

    Returns
    -------
    list of Coil, length 3
    """
    return [Coil(center, ax, radius, turns) for ax in np.eye(3)]


# ---------------------------------------------------------------------------
# one point, Python floats (allocation-free kernels for the firmware's solver)
# ---------------------------------------------------------------------------
def loop_point(x, y, z, radius, scale, jac=True):
    """Exact loop field (and gradient) at one coil-frame point, Python floats.

    The kernel of ``loop_field`` / ``loop_jacobian`` (Schepers & Veltink eqs
    6-7 in the AGM form of ``_loop_core``) for a single point, without any
    array: the firmware's pose solver (``coiltrack.firmware.pose.solver``) calls it in its
    steady-state loop, where no numpy array may be allocated.

    Parameters
    ----------
    x, y, z : float
        Point in the coil frame, m.
    radius : float
        Loop radius ``a``, m.
    scale : float
        ``mu0 N I / (2 pi a)``, T.
    jac : bool

    Returns
    -------
    tuple of float
        ``(bx, by, bz)`` in T, followed when ``jac`` by the six distinct
        gradient entries ``(jxx, jyy, jzz, jxy, jxz, jyz)`` in T/m
        (the gradient is symmetric and traceless).
    """
    inv_a = 1.0 / radius
    xn = x * inv_a
    yn = y * inv_a
    zn = z * inv_a
    u = xn * xn + yn * yn
    if not jac:
        F, G = _loop_core(u, zn, False, math.sqrt, max, _unconverged_scalar)
        Fc = scale * F
        return xn * Fc, yn * Fc, scale * G
    F, G, Fz, H = _loop_core(u, zn, True, math.sqrt, max, _unconverged_scalar)
    Fc = scale * F
    g = scale * inv_a
    F2, H2, Fz2 = F * g, H * g, Fz * g
    return (xn * Fc, yn * Fc, scale * G,
            F2 + xn * xn * H2, F2 + yn * yn * H2, -2.0 * F2 - u * H2,
            xn * yn * H2, xn * Fz2, yn * Fz2)


def dipole_point(px, py, pz, mx, my, mz, jac=True):
    """Dipole field (and gradient) at one point relative to the dipole, Python
    floats; the single-point kernel of ``dipole_field`` / ``dipole_jacobian``
    (Schepers & Veltink eq 8 and the general form of eq 10). Returns the same
    tuple layout as :func:`loop_point`."""
    r2 = px * px + py * py + pz * pz
    inv_r2 = 1.0 / r2
    c = _MU0_4PI * inv_r2 / math.sqrt(r2)
    mp = mx * px + my * py + mz * pz
    k = 3.0 * mp * inv_r2
    b = (c * (k * px - mx), c * (k * py - my), c * (k * pz - mz))
    if not jac:
        return b
    c5 = 3.0 * c * inv_r2
    f = 5.0 * mp * inv_r2
    return b + (c5 * (2.0 * mx * px + mp - f * px * px),
                c5 * (2.0 * my * py + mp - f * py * py),
                c5 * (2.0 * mz * pz + mp - f * pz * pz),
                c5 * (mx * py + my * px - f * px * py),
                c5 * (mx * pz + mz * px - f * px * pz),
                c5 * (my * pz + mz * py - f * py * pz))


def dipole_polar(ux, uy, uz, rho, mx, my, mz, jac=True):
    """Dipole field (and gradient) at the point ``rho u`` relative to the dipole,
    given by its unit direction ``u`` and range ``rho``, Python floats: Raab
    et al. 1979 (``seeds/004_86267342cd7488ce.txt``) eq 5 in vector form,
    ``B = (C / 2 rho^3)(3 (m.u) u - m)`` with ``C = mu0 / 2 pi`` (eq 3,
    :data:`MU0_2PI`), and ``dB/dp = (C / 2 rho^4)(3 (u m^T + (m.u) I + m
    u^T) - 15 (m.u) u u^T)``; Schepers & Veltink eqs 8 and 10 written in
    ``(u, rho)``. The same field as :func:`dipole_point` at ``p = rho u``
    (to rounding: that kernel takes the point, this one the direction and the
    range a tracker in Raab's coordinates holds). Returns the tuple layout of
    :func:`loop_point`: ``(bx, by, bz)`` T and, when ``jac``, ``(jxx, jyy,
    jzz, jxy, jxz, jyz)`` T/m."""
    kd = 0.5 * MU0_2PI / (rho * rho * rho)
    mu = mx * ux + my * uy + mz * uz
    b = (kd * (3.0 * mu * ux - mx), kd * (3.0 * mu * uy - my), kd * (3.0 * mu * uz - mz))
    if not jac:
        return b
    kj = kd / rho
    f = 15.0 * mu
    return b + (kj * (6.0 * ux * mx + 3.0 * mu - f * ux * ux), kj * (6.0 * uy * my + 3.0 * mu - f * uy * uy),
                kj * (6.0 * uz * mz + 3.0 * mu - f * uz * uz), kj * (3.0 * (ux * my + mx * uy) - f * ux * uy),
                kj * (3.0 * (ux * mz + mx * uz) - f * ux * uz), kj * (3.0 * (uy * mz + my * uz) - f * uy * uz))
