"""Tests of coiltrack.firmware.model.field against independent references.

References: scipy.special elliptic integrals, magpylib (its own loop and
dipole implementations), a 60-digit ``decimal`` evaluation of the Smythe
formula, closed-form limits (axis, dipole, straight wire) and Maxwell's
equations checked by finite differences.  All random inputs are seeded.

magpylib uses ``scipy.constants.mu_0`` (CODATA 2018, 1 + 5.5e-10 times
4e-7 pi) while the firmware uses ``4e-7 pi``; magpylib results are rescaled
by ``MU0 / mu_0`` before comparison.
"""
from __future__ import annotations

import math
from decimal import Decimal, localcontext

import magpylib
import numpy as np
import pytest
import scipy.constants
import scipy.special as sp
from scipy.spatial.transform import Rotation

from coiltrack.firmware.model.field import (
    MU0,
    Coil,
    CoilSet,
    agm_ellipke,
    dipole_field,
    dipole_jacobian,
    loop_field,
    loop_jacobian,
    orthogonal_source,
)

A = 0.055  # loop radius, m (thesis Table 5.1 source)
N = 50  # turns
I = 1.5  # current, A
MAGPY_SCALE = MU0 / scipy.constants.mu_0


# ---------------------------------------------------------------------------
# references
# ---------------------------------------------------------------------------
def ref_loop_scipy(p, a, n, i):
    """Smythe form (Schepers & Veltink eqs 6-7) with scipy's K and E.

    alpha^2 is formed as (a - rho)^2 + z^2 and K from ``ellipkm1(1 - m)``
    so the reference itself is accurate near the wire; it is not used on or
    very near the axis, where this form cancels.
    """
    p = np.atleast_2d(p)
    x, y, z = p.T
    rho = np.hypot(x, y)
    al2 = (a - rho) ** 2 + z ** 2
    be2 = (a + rho) ** 2 + z ** 2
    be = np.sqrt(be2)
    m = 4.0 * a * rho / be2
    K = sp.ellipkm1(al2 / be2)
    E = sp.ellipe(m)
    r2 = rho ** 2 + z ** 2
    c = MU0 * n * i / math.pi
    brho = c * z / (2 * al2 * be * rho) * ((a * a + r2) * E - al2 * K)
    bz = c / (2 * al2 * be) * ((a * a - r2) * E + al2 * K)
    return np.stack([brho * x / rho, brho * y / rho, bz], axis=1)


def ref_loop_decimal(p, a, n, i, digits=60):
    """The same formula evaluated with 60 significant digits (``decimal``).

    The float inputs are converted exactly, so the result is the correctly
    rounded field at exactly those inputs; cancellation in the textbook form
    costs at most ~30 of the 60 digits at the points used here.
    """
    out = []
    with localcontext() as ctx:
        ctx.prec = digits
        pi = Decimal("3.14159265358979323846264338327950288419716939937510582097494459")

        def ellipke(m):
            aa, bb = Decimal(1), (1 - m).sqrt()
            s, w = m / 2, Decimal(1) / 2
            for _ in range(200):
                aa, bb, c = (aa + bb) / 2, (aa * bb).sqrt(), (aa - bb) / 2
                w *= 2
                s += w * c * c
                if abs(aa - bb) < Decimal(10) ** (-digits + 5):
                    break
            k = pi / (2 * aa)
            return k, k * (1 - s)

        ad = Decimal(float(a))
        c = 4 * pi * Decimal(10) ** -7 * Decimal(n) * Decimal(float(i)) / pi
        for x, y, z in np.atleast_2d(p):
            x, y, z = Decimal(float(x)), Decimal(float(y)), Decimal(float(z))
            rho = (x * x + y * y).sqrt()
            r2 = rho * rho + z * z
            al2 = (ad - rho) ** 2 + z * z
            be2 = (ad + rho) ** 2 + z * z
            be = be2.sqrt()
            K, E = ellipke(4 * ad * rho / be2)
            bz = c / (2 * al2 * be) * ((ad * ad - r2) * E + al2 * K)
            if rho == 0:
                bx = by = Decimal(0)
            else:
                brho = c * z / (2 * al2 * be * rho) * ((ad * ad + r2) * E - al2 * K)
                bx, by = brho * x / rho, brho * y / rho
            out.append([float(bx), float(by), float(bz)])
    return np.array(out)


def magpy_loop(p, a=A, n=N, i=I, position=(0, 0, 0), rotation=None):
    kw = {} if rotation is None else {"orientation": Rotation.from_matrix(rotation)}
    loop = magpylib.current.Circle(current=i, diameter=2 * a, position=position, **kw)
    return loop.getB(p) * n * MAGPY_SCALE


def rel_err(b, ref):
    """Per-point ``|b - ref| / |ref|``."""
    return np.linalg.norm(b - ref, axis=-1) / np.linalg.norm(ref, axis=-1)


def fd_jacobian(f, p, h):
    """Central finite differences ``J[n, i, j] = dB_i/dp_j`` (error O(h^2))."""
    p = np.atleast_2d(p)
    J = np.empty((len(p), 3, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        J[:, :, j] = (f(p + e) - f(p - e)) / (2 * h)
    return J


def random_points(rng, n, lo, hi, min_wire_distance):
    """Points with |x|, |y|, |z| < hi*A, |p| > lo*A and away from the wire."""
    pts = []
    while len(pts) < n:
        q = rng.uniform(-hi, hi, 3) * A
        if np.linalg.norm(q) < lo * A:
            continue
        if math.hypot(math.hypot(q[0], q[1]) - A, q[2]) < min_wire_distance * A:
            continue
        pts.append(q)
    return np.array(pts)


# ---------------------------------------------------------------------------
# elliptic integrals
# ---------------------------------------------------------------------------
def test_agm_ellipke_matches_scipy():
    m = np.concatenate([
        np.linspace(-10.0, 0.999, 4001),
        1.0 - np.logspace(-16, -1, 200),
        np.logspace(-300, -1, 200),
        [0.0, -1e-300],
    ])
    K, E = agm_ellipke(m)
    # relative 1e-13 (observed <= 6e-15)
    np.testing.assert_allclose(K, sp.ellipk(m), rtol=1e-13, atol=0)
    np.testing.assert_allclose(E, sp.ellipe(m), rtol=1e-13, atol=0)


def test_agm_ellipke_special_values_and_buffers():
    assert agm_ellipke(0.0) == (math.pi / 2, math.pi / 2)
    k1, e1 = agm_ellipke(1.0)
    assert k1 == math.inf and e1 == 1.0
    k2, e2 = agm_ellipke(2.0)
    assert math.isnan(k2) and math.isnan(e2)
    m = np.array([[0.1, 0.5], [0.9, 0.99]])
    ok, oe = np.empty((2, 2)), np.empty((2, 2))
    K, E = agm_ellipke(m, out_k=ok, out_e=oe)
    assert K is ok and E is oe
    np.testing.assert_allclose(K, sp.ellipk(m), rtol=1e-14)


# ---------------------------------------------------------------------------
# exact loop field
# ---------------------------------------------------------------------------
def test_loop_field_vs_scipy_reference():
    rng = np.random.default_rng(11)
    pts = random_points(rng, 2000, 0.05, 3.0, 0.02)
    rho = np.hypot(pts[:, 0], pts[:, 1])
    pts = pts[rho > 0.05 * A]  # the reference cancels near the axis
    B = loop_field(pts, A, N, I)
    # relative 1e-12 (observed ~1e-14, mostly the reference's own rounding)
    assert rel_err(B, ref_loop_scipy(pts, A, N, I)).max() < 1e-12


def test_loop_field_vs_magpylib_all_regimes():
    rng = np.random.default_rng(12)
    generic = random_points(rng, 500, 0.01, 4.0, 1e-3)
    dirs = rng.normal(size=(60, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    far = dirs * np.repeat([10.0, 100.0, 1e3, 1e4], 15)[:, None] * A
    t = rng.uniform(0, 2 * np.pi, 40)
    rho = np.repeat([1e-12, 1e-9, 1e-6, 1e-3], 10) * A
    near_axis = np.column_stack([rho * np.cos(t), rho * np.sin(t), rng.uniform(-3, 3, 40) * A])
    d = np.repeat([1e-6, 1e-4, 1e-2], 10) * A  # distance to the wire
    ang = rng.uniform(0, 2 * np.pi, 30)
    near_wire = np.column_stack([(A + d * np.cos(ang)) * np.cos(t[:30]),
                                 (A + d * np.cos(ang)) * np.sin(t[:30]), d * np.sin(ang)])
    for name, pts in [("generic", generic), ("far", far), ("near_axis", near_axis),
                      ("near_wire", near_wire)]:
        err = rel_err(loop_field(pts, A, N, I), magpy_loop(pts))
        # relative 1e-9 (observed: ~1e-14, near the wire at d = 1e-6 a ~3e-10,
        # where both are limited by rounding of the position: cond ~ a/d)
        assert err.max() < 1e-9, (name, err.max())


def test_loop_field_vs_60_digit_reference():
    pts = []
    for r in [1e-12, 1e-9, 1e-6, 1e-3]:
        pts += [[r * A, 0, 0.5 * A], [0, r * A, -2 * A], [r * A, r * A, 0]]
    for d in [1e-9, 1e-6, 1e-3]:  # exactly above / below the wire
        pts += [[A, 0, d * A], [0, A, -d * A]]
    for R in [10.0, 100.0, 1e3, 1e4]:
        pts += [[0.6 * R * A, 0, 0.8 * R * A], [0, R * A, 0],
                [0.3 * R * A, 0.4 * R * A, -math.sqrt(0.75) * R * A]]
    pts += list(np.random.default_rng(13).uniform(-2 * A, 2 * A, (20, 3)))
    pts = np.array(pts)
    B = loop_field(pts, A, N, I)
    ref = ref_loop_decimal(pts, A, N, I)
    # relative 2e-14 on |B| (observed <= 5e-15) ...
    assert rel_err(B, ref).max() < 2e-14
    # ... and on the small B_x component alone near the axis (observed 7e-16)
    sel = ref[:, 0] != 0.0
    assert np.max(np.abs(B[sel, 0] / ref[sel, 0] - 1.0)) < 2e-14


def test_loop_field_on_axis():
    z = np.linspace(-5, 5, 101) * A
    pts = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    B = loop_field(pts, A, N, I)
    assert np.all(B[:, :2] == 0.0)  # exactly zero, no NaN
    bz = MU0 * N * I * A ** 2 / (2 * (A ** 2 + z ** 2) ** 1.5)
    np.testing.assert_allclose(B[:, 2], bz, rtol=1e-14, atol=0)  # observed 4e-16


@pytest.mark.parametrize("rho_rel", [1e-12, 1e-10, 1e-8, 1e-6])
def test_loop_field_near_axis_expansion(rho_rel):
    """Off-axis expansion of an axisymmetric field:
    B_rho = -rho/2 b'(z) + rho^3/16 b'''(z) + O(rho^5),
    B_z = b(z) - rho^2/4 b''(z) + O(rho^4),
    b(z) = mu0 N I a^2 / (2 (a^2 + z^2)^1.5).  With rho <= 1e-6 a the
    truncation is < 1e-20 relative."""
    z = np.linspace(-3, 3, 25) * A
    rho = rho_rel * A
    t = np.linspace(0, 2 * np.pi, 25)
    pts = np.column_stack([rho * np.cos(t), rho * np.sin(t), z])
    B = loop_field(pts, A, N, I)
    c = MU0 * N * I * A ** 2 / 2
    s = A ** 2 + z ** 2
    b1 = -3 * c * z / s ** 2.5
    b2 = c * (12 * z ** 2 - 3 * A ** 2) / s ** 3.5
    b3 = c * z * (45 * A ** 2 - 60 * z ** 2) / s ** 4.5
    brho = -0.5 * rho * b1 + rho ** 3 / 16 * b3
    bz = c / s ** 1.5 - rho ** 2 / 4 * b2
    nz = z != 0
    # relative 1e-12 per component (observed ~1e-15)
    np.testing.assert_allclose(B[nz, 0], brho[nz] * np.cos(t[nz]), rtol=1e-12, atol=0)
    np.testing.assert_allclose(B[nz, 1], brho[nz] * np.sin(t[nz]), rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(B[:, 2], bz, rtol=1e-12, atol=0)


@pytest.mark.parametrize("d_rel", [1e-8, 1e-6, 1e-4])
def test_loop_field_near_wire_is_straight_wire(d_rel):
    """At distance d << a the loop looks like a straight wire:
    |B| = mu0 N I / (2 pi d) (1 + O(d/a ln(a/d)))."""
    d = d_rel * A
    ang = np.linspace(0, 2 * np.pi, 13)
    pts = np.column_stack([A + d * np.cos(ang), np.zeros_like(ang), d * np.sin(ang)])
    B = loop_field(pts, A, N, I)
    wire = MU0 * N * I / (2 * math.pi * d)
    tol = 2 * d_rel * math.log(8 / d_rel)  # first-order curvature correction bound
    assert np.max(np.abs(np.linalg.norm(B, axis=1) / wire - 1)) < tol
    # field circulates around the wire: B perpendicular to the radial offset
    off = pts - np.array([A, 0, 0])
    cosang = np.abs(np.einsum("ij,ij->i", B, off)) / (np.linalg.norm(B, axis=1) * d)
    assert cosang.max() < tol


@pytest.mark.parametrize("npts", [3, 30])  # float path and array path
def test_loop_field_on_the_wire_does_not_raise(npts):
    t = np.linspace(0, 2 * np.pi, npts)
    pts = np.column_stack([A * np.cos(t), A * np.sin(t), np.zeros(npts)])
    pts[0] = [A, 0, 0]  # exactly on the wire
    with np.errstate(all="raise"):
        B = loop_field(pts, A, N, I)
        J = loop_jacobian(pts, A, N, I)
    assert not np.any(np.isnan(B)) and not np.any(np.isnan(J))


def test_float_and_array_kernels_agree():
    """Few points run the kernel on Python floats, many on numpy arrays: same
    formulas, different rounding order (agreement 1e-14 relative to each
    point's largest component; observed ~3e-15)."""
    rng = np.random.default_rng(21)
    pts = np.concatenate([random_points(rng, 200, 0.01, 3.0, 1e-6),
                          [[0, 0, 0.01], [0, 0, 0], [A, 0, 1e-9], [1e-12, 0, 0.02],
                           [1e3, 2e3, -1e3]]])
    B = loop_field(pts, A, N, I)
    J = loop_jacobian(pts, A, N, I)
    Bs = np.array([loop_field(q, A, N, I) for q in pts])
    Js = np.array([loop_jacobian(q, A, N, I) for q in pts])
    bn = np.abs(B).max(axis=1, keepdims=True)
    jn = np.abs(J).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(B - Bs) <= 1e-14 * bn)
    assert np.all(np.abs(J - Js) <= 1e-14 * jn)


def test_loop_field_far_away_approaches_dipole():
    rng = np.random.default_rng(14)
    dirs = rng.normal(size=(200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    moment = np.array([0, 0, N * I * math.pi * A ** 2])
    scaled = []
    for R in [10.0, 100.0, 1000.0]:
        pts = dirs * R * A
        err = rel_err(loop_field(pts, A, N, I), dipole_field(pts, moment)).max()
        scaled.append(err * R ** 2)
    # leading correction is the octupole, relative (a/R)^2 times an O(1)
    # angular factor (observed max ~1.1): the scaled error is the same
    # constant at every distance (10 % tolerance, the O((a/R)^4) term at
    # R = 10 a) and below 2.
    scaled = np.array(scaled)
    assert scaled.max() < 2.0
    assert np.all(np.abs(scaled / scaled[-1] - 1) < 0.1)


def test_loop_field_shapes_and_out():
    p = np.array([0.01, 0.02, 0.03])
    B1 = loop_field(p, A, N, I)
    assert B1.shape == (3,)
    out = np.empty((4, 3))
    pts = np.tile(p, (4, 1))
    res = loop_field(pts, A, N, I, out=out)
    assert res is out
    np.testing.assert_array_equal(out[2], B1)
    J1 = loop_jacobian(p, A, N, I)
    assert J1.shape == (3, 3)
    outj = np.empty((4, 3, 3))
    assert loop_jacobian(pts, A, N, I, out=outj) is outj
    np.testing.assert_array_equal(outj[1], J1)
    # linear in turns and current
    np.testing.assert_allclose(loop_field(p, A, 2 * N, -I), -2 * B1, rtol=1e-15)


# ---------------------------------------------------------------------------
# dipole
# ---------------------------------------------------------------------------
def test_dipole_field_vs_magpylib():
    rng = np.random.default_rng(15)
    pts = rng.normal(size=(300, 3)) * 0.3
    m = np.array([0.3, -1.1, 0.7])
    B = dipole_field(pts, m)
    ref = magpylib.misc.Dipole(moment=m).getB(pts) * MAGPY_SCALE
    assert rel_err(B, ref).max() < 1e-13  # observed ~3e-16
    # Schepers & Veltink eq 8 for a z-directed coil
    p = pts[0]
    r = np.linalg.norm(p)
    eq8 = MU0 * N * I * A ** 2 / (4 * r ** 5) * np.array(
        [3 * p[0] * p[2], 3 * p[1] * p[2], 2 * p[2] ** 2 - p[0] ** 2 - p[1] ** 2])
    np.testing.assert_allclose(dipole_field(p, [0, 0, N * I * math.pi * A ** 2]), eq8,
                               rtol=1e-13)


# ---------------------------------------------------------------------------
# Jacobians and Maxwell
# ---------------------------------------------------------------------------
def test_loop_jacobian_vs_finite_differences():
    rng = np.random.default_rng(16)
    generic = random_points(rng, 300, 0.05, 3.0, 0.2)
    z = np.linspace(-3, 3, 7) * A
    z = z[z != 0]  # the gradient vanishes at the loop centre
    axis = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    near_axis = axis + np.array([1e-9 * A, 2e-9 * A, 0])
    dirs = rng.normal(size=(20, 3))
    far = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * 50 * A

    def f(q):
        return loop_field(q, A, N, I)

    for name, pts, h in [("generic", generic, 1e-5 * A), ("axis", axis, 1e-5 * A),
                         ("near_axis", near_axis, 1e-5 * A), ("far", far, 1e-5 * 50 * A)]:
        J = loop_jacobian(pts, A, N, I)
        Jf = fd_jacobian(f, pts, h)
        err = np.linalg.norm(J - Jf, axis=(1, 2)) / np.linalg.norm(Jf, axis=(1, 2))
        # relative (Frobenius) 1e-7: O(h^2) truncation + rounding/h (observed ~1e-9)
        assert err.max() < 1e-7, (name, err.max())


def test_dipole_jacobian_vs_finite_differences():
    rng = np.random.default_rng(17)
    pts = rng.normal(size=(100, 3)) * 0.3
    m = np.array([0.3, -1.1, 0.7])
    J = dipole_jacobian(pts, m)
    Jf = fd_jacobian(lambda q: dipole_field(q, m), pts, 1e-7)
    err = np.linalg.norm(J - Jf, axis=(1, 2)) / np.linalg.norm(Jf, axis=(1, 2))
    assert err.max() < 1e-7  # as above (observed ~1e-9)
    # Schepers & Veltink eq 10 (d/dp_x of a z-directed coil's field)
    p = pts[0]
    r = np.linalg.norm(p)
    px, py, pz = p
    eq10 = MU0 * N * I * A ** 2 / (4 * r ** 7) * np.array(
        [-12 * px ** 2 * pz + 3 * py ** 2 * pz + 3 * pz ** 3, -15 * px * py * pz,
         3 * px ** 3 + 3 * px * py ** 2 - 12 * px * pz ** 2])
    # eq 10 as printed has the exponent 5/2 in the denominator; differentiating
    # eq 8 (and the units, T/m) require 7/2, used here
    np.testing.assert_allclose(dipole_jacobian(p, [0, 0, N * I * math.pi * A ** 2])[:, 0],
                               eq10, rtol=1e-12)


def test_loop_field_is_curl_and_divergence_free():
    """Maxwell in vacuum, from finite differences of the FIELD (independent of
    the analytic Jacobian): |div B| and |curl B| below 1e-7 |grad B|."""
    rng = np.random.default_rng(18)
    pts = random_points(rng, 300, 0.05, 3.0, 0.2)
    Jf = fd_jacobian(lambda q: loop_field(q, A, N, I), pts, 1e-5 * A)
    norm = np.linalg.norm(Jf, axis=(1, 2))
    div = np.trace(Jf, axis1=1, axis2=2)
    curl = np.linalg.norm(Jf - np.swapaxes(Jf, 1, 2), axis=(1, 2))
    assert np.max(np.abs(div) / norm) < 1e-7  # observed ~3e-9 (difference rounding)
    assert np.max(curl / norm) < 1e-7
    # the analytic Jacobians are symmetric and traceless to rounding (1e-14)
    for J in (loop_jacobian(pts, A, N, I), dipole_jacobian(pts, [0.1, 0.2, 0.3])):
        n = np.linalg.norm(J, axis=(1, 2))
        assert np.max(np.abs(np.trace(J, axis1=1, axis2=2)) / n) < 1e-14
        assert np.max(np.linalg.norm(J - np.swapaxes(J, 1, 2), axis=(1, 2)) / n) < 1e-14


# ---------------------------------------------------------------------------
# Coil, CoilSet, orthogonal_source
# ---------------------------------------------------------------------------
def test_coil_tilted_offset_vs_magpylib():
    rng = np.random.default_rng(19)
    center = np.array([0.02, -0.01, 0.03])
    axis = np.array([0.3, -0.5, 0.8])
    coil = Coil(center, axis, A, N)
    R = coil.rotation
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
    assert abs(np.linalg.det(R) - 1) < 1e-15
    np.testing.assert_allclose(R[:, 2], axis / np.linalg.norm(axis), atol=1e-16)
    pts = center + random_points(rng, 300, 0.05, 4.0, 0.01)
    B = coil.field(pts, I)
    ref = magpy_loop(pts, position=center, rotation=R)
    assert rel_err(B, ref).max() < 1e-9  # observed ~1e-14
    # the dipole model of the coil vs magpylib's dipole with the same moment
    mom = coil.moment(I)
    np.testing.assert_allclose(mom, N * I * math.pi * A ** 2 * axis / np.linalg.norm(axis),
                               rtol=1e-15)
    Bd = coil.field(pts, I, model="dipole")
    refd = magpylib.misc.Dipole(moment=mom, position=center).getB(pts) * MAGPY_SCALE
    assert rel_err(Bd, refd).max() < 1e-13
    # the loop field does not depend on the in-plane completion of the axis
    other = Rotation.from_rotvec(axis / np.linalg.norm(axis) * 0.7).as_matrix() @ R
    assert rel_err(B, magpy_loop(pts, position=center, rotation=other)).max() < 1e-9


@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_coil_jacobian_vs_finite_differences(model):
    rng = np.random.default_rng(20)
    coil = Coil([0.01, 0.02, -0.01], [1.0, 2.0, -0.5], 0.04, 30)
    pts = coil.center + random_points(rng, 100, 0.15, 3.0, 0.3)
    J = coil.jacobian(pts, 2.0, model=model)
    Jf = fd_jacobian(lambda q: coil.field(q, 2.0, model=model), pts, 1e-6)
    err = np.linalg.norm(J - Jf, axis=(1, 2)) / np.linalg.norm(Jf, axis=(1, 2))
    assert err.max() < 1e-7  # central differences, as above


def test_coilset_matches_individual_coils():
    coils = orthogonal_source(A, N, center=(0.01, 0, 0)) + [Coil([0, 0.01, 0], [1, 1, 1], 0.03, 20)]
    for c, ax in zip(coils[:3], np.eye(3)):
        np.testing.assert_allclose(c.axis, ax)
    cs = CoilSet(coils)
    cur = np.array([1.5, -1.0, 0.5, 2.0])
    p = np.array([0.2, -0.1, 0.15])
    for model in ("exact", "dipole"):
        B, J = cs.fields(p, cur, model, out_j=np.empty((4, 3, 3)))
        for j, c in enumerate(coils):
            np.testing.assert_allclose(B[j], c.field(p, cur[j], model), rtol=1e-14, atol=0)
            np.testing.assert_allclose(J[j], c.jacobian(p, cur[j], model), rtol=1e-13,
                                       atol=1e-15 * np.abs(J[j]).max())
    np.testing.assert_allclose(cs.moments(cur)[1], coils[1].moment(cur[1]))


def test_bad_inputs_raise():
    with pytest.raises(ValueError):
        loop_field(np.zeros((3, 2)), A, N, I)
    with pytest.raises(ValueError):
        Coil([0, 0, 0], [0, 0, 0], A, N)
    with pytest.raises(ValueError):
        Coil([0, 0, 0], [0, 0, 1], 0.0, N)
    with pytest.raises(ValueError):
        orthogonal_source(A, N)[0].field([0.1, 0, 0], I, model="quadrupole")
