"""The single-point field kernels the firmware's signal model runs on (``field.dipole_point``,
``field.loop_point``) against references that share nothing with them.

``dipole_point`` is the kernel of every dipole coil (``model.signal``) and of the
distortion map (``model.distortion``); its Jacobian is checked against its own
field elsewhere, so a slip made in the field and its Jacobian alike (a factor,
a sign, a moment component taken for another) needs a reference of its own:

* the closed form ``B = mu0 / (4 pi) (3 (m . r) r / r^5 - m / r^3)``
  (Schepers & Veltink ``000_e46ec0e8bf7ea271.txt`` eq 8 for any moment),
  written here in numpy;
* magpylib's functional core ``magpylib.core.dipole_Hfield`` (``B = mu0 H``;
  ``H`` carries no ``mu0``, so the firmware's ``MU0 = 4e-7 pi`` applies
  exactly);
* a small loop far away: magpylib's ``current_circle_Hfield`` (Ortner et al.
  2023, its own loop formula) for a loop of radius ``a`` at ``r >> a`` tends
  to the dipole ``m = I pi a^2``, the octupole correction being of relative
  order ``(a / r)^2``.

The Jacobians against central differences of magpylib's fields (not of the
kernel's own field). ``loop_point`` against the Smythe form (eqs 6-7) with
scipy's ``ellipk`` / ``ellipe`` and against magpylib's loop. Seeded points.
"""
from __future__ import annotations

import math

import magpylib
import numpy as np
import scipy.special as sp

from coiltrack.firmware.model.field import MU0, dipole_point, loop_point

A = 0.055          # loop radius, m (thesis Table 5.1)
N_TURNS = 50
CURRENT = 1.5


def _closed_form(p, m):
    """``mu0 / (4 pi) (3 (m . r) r / r^5 - m / r^3)``."""
    r = np.linalg.norm(p)
    return MU0 / (4 * math.pi) * (3 * (m @ p) * p / r ** 5 - m / r ** 3)


def _magpy_dipole(p, m):
    return MU0 * magpylib.core.dipole_Hfield(np.atleast_2d(p), np.atleast_2d(m))[0]


def _magpy_loop(p, a, i):
    """magpylib's loop in the z = 0 plane (cylindrical core, turned back to Cartesian), T."""
    rho = math.hypot(p[0], p[1])
    h = magpylib.core.current_circle_Hfield(np.array([a]), np.array([rho]), np.array([p[2]]), np.array([i]))[:, 0]
    c, s = (p[0] / rho, p[1] / rho) if rho > 0 else (1.0, 0.0)
    return MU0 * np.array([h[0] * c, h[0] * s, h[2]])


def _full(t):
    """(B, J) from a kernel's tuple ``(bx, by, bz, jxx, jyy, jzz, jxy, jxz, jyz)``."""
    bx, by, bz, jxx, jyy, jzz, jxy, jxz, jyz = t
    return np.array([bx, by, bz]), np.array([[jxx, jxy, jxz], [jxy, jyy, jyz], [jxz, jyz, jzz]])


def _central(f, p, h):
    """``J[i, j] = dB_i / dp_j`` by central differences of ``f``."""
    J = np.empty((3, 3))
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        J[:, j] = (f(p + d) - f(p - d)) / (2 * h)
    return J


def _points(rng, n, rmin, rmax):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(rmin, rmax, (n, 1))


def test_dipole_point_field_matches_the_closed_form_and_magpylib():
    """100 points at 5 cm - 2 m, random moments of 0.01-3 A m^2 in any direction: the field to
    1e-13 of its magnitude against the closed form and against magpylib's dipole (observed
    ~3e-16). Catches a factor or sign slip, a moment component taken for another, ``r^3`` for
    ``r^5``, made in the kernel alone or in it and its Jacobian together."""
    rng = np.random.default_rng(34)
    for p in _points(rng, 100, 0.05, 2.0):
        m = rng.normal(size=3) * rng.uniform(0.01, 3.0)
        b = np.array(dipole_point(*p, *m, jac=False))
        b_jac = np.array(dipole_point(*p, *m)[:3])
        for ref in (_closed_form(p, m), _magpy_dipole(p, m)):
            assert np.abs(b - ref).max() < 1e-13 * np.linalg.norm(ref), (p, m, b, ref)
        np.testing.assert_array_equal(b, b_jac)


def test_dipole_point_jacobian_matches_magpylib_differences():
    """The gradient against central differences of magpylib's dipole field (step ``1e-5 r``:
    truncation ``(h / r)^2`` and rounding ``1e-16 r / h``, both under 1e-8), to 1e-7 of the
    gradient's largest entry."""
    rng = np.random.default_rng(35)
    for p in _points(rng, 40, 0.05, 2.0):
        m = rng.normal(size=3)
        _, J = _full(dipole_point(*p, *m))
        ref = _central(lambda q: _magpy_dipole(q, m), p, 1e-5 * np.linalg.norm(p))
        assert np.abs(J - ref).max() < 1e-7 * np.abs(ref).max(), (p, J, ref)


def test_dipole_point_is_the_far_field_of_a_small_loop():
    """magpylib's loop of radius 5.5 cm (50 turns, 1.5 A as 75 A) turned to an arbitrary axis, at
    10, 30 and 100 radii: ``dipole_point`` with ``m = N I pi a^2`` along the axis agrees to
    ``2 (a / r)^2`` of the field's magnitude (the octupole term is ``(a / r)^2`` times a factor
    under 2 over all directions), and the relative error falls as ``(a / r)^2`` (within 10 %
    between 30 and 100 radii). Catches a dipole scaled or turned consistently with its Jacobian,
    which the loop, an independent formula, does not follow."""
    rng = np.random.default_rng(36)
    axis = np.array([0.3, -0.5, 0.81])
    axis /= np.linalg.norm(axis)
    # a rotation taking z to the axis (Rodrigues), to put the point in the loop's frame
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(z, axis), float(z @ axis)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    Rl = np.eye(3) + K + K @ K / (1 + c)           # loop frame -> source frame
    m = N_TURNS * CURRENT * math.pi * A * A * axis
    dirs = _points(rng, 60, 1.0, 1.0)
    scaled = {}
    for k in (10, 30, 100):
        worst = 0.0
        for d in dirs:
            p = d * k * A
            ref = Rl @ _magpy_loop(Rl.T @ p, A, N_TURNS * CURRENT)
            b = np.array(dipole_point(*p, *m, jac=False))
            rel = np.linalg.norm(b - ref) / np.linalg.norm(ref)
            assert rel < 2.0 / k ** 2, (k, d, rel)
            worst = max(worst, rel)
        scaled[k] = worst * k ** 2
    assert abs(scaled[30] / scaled[100] - 1) < 0.1, scaled


def _smythe(p, a, scale):
    """Schepers & Veltink eqs 6-7 (the Smythe form) with scipy's ``ellipk`` / ``ellipe``, T;
    ``scale = mu0 N I / (2 pi a)`` as ``loop_point`` takes it."""
    x, y, zz = p
    rho = math.hypot(x, y)
    al2 = (a - rho) ** 2 + zz ** 2
    be2 = (a + rho) ** 2 + zz ** 2
    k2 = 1 - al2 / be2
    K, E = sp.ellipk(k2), sp.ellipe(k2)
    c = scale * a / math.sqrt(be2)               # mu0 I / (2 pi beta)
    bz = c * ((a * a - rho * rho - zz * zz) * E / al2 + K)
    brho = c * zz / rho * ((a * a + rho * rho + zz * zz) * E / al2 - K) if rho > 0 else 0.0
    return np.array([brho * x / rho, brho * y / rho, bz]) if rho > 0 else np.array([0.0, 0.0, bz])


def test_loop_point_matches_scipy_elliptic_integrals_and_magpylib():
    """``loop_point`` at 60 points from 0.2 to 20 radii off the wire, off the axis: the field to
    1e-10 of its magnitude against the Smythe form with scipy's K and E and against magpylib's
    loop; its gradient to 1e-6 of the largest entry against central differences of magpylib's
    loop (step ``1e-5 a``)."""
    rng = np.random.default_rng(37)
    scale = MU0 * N_TURNS * CURRENT / (2 * math.pi * A)
    pts = _points(rng, 200, 0.3 * A, 20 * A)
    pts = [p for p in pts if math.hypot(math.hypot(*p[:2]) - A, p[2]) > 0.2 * A and math.hypot(*p[:2]) > 0.05 * A]
    assert len(pts) >= 60
    for p in pts[:60]:
        B, J = _full(loop_point(*p, A, scale))
        for ref in (_smythe(p, A, scale), _magpy_loop(p, A, N_TURNS * CURRENT)):
            assert np.abs(B - ref).max() < 1e-10 * np.linalg.norm(ref), (p, B, ref)
        ref_j = _central(lambda q: _magpy_loop(q, A, N_TURNS * CURRENT), p, 1e-5 * A)
        assert np.abs(J - ref_j).max() < 1e-6 * np.abs(ref_j).max(), (p, J, ref_j)
