"""Conductors at an AC excitation frequency: complex (amplitude and phase) responses.

Phasor convention throughout the AC bench: a quantity ``x(t) = Re[X exp(i omega t)]``
(engineering sign, the same as the coil's ``I = V / (R + i omega L)`` in
:mod:`hil.ac`), so a lagging response has a negative phase.

* :func:`sphere_response`: exact induced dipole of a conducting, optionally
  permeable sphere in a uniform AC field (J. R. Wait, "A conducting sphere in a
  time varying magnetic field", Geophysics 16, 666-672, 1951; W. R. Smythe,
  *Static and Dynamic Electricity*, the sphere in an alternating field).
* :func:`highpass_response`, :func:`eddy_moment_phasor`: the lumped eddy
  conductor of :class:`hil.physics.EddyConductor` (a first-order L/R loop) at
  one frequency.
* :func:`dipole_field_phasor`: the field of a complex dipole moment, from the
  bench's one dipole formula (:func:`hil.physics.dipole_field`) applied to the
  real and imaginary parts.

Numerics: numpy only (scipy is a test dependency, not a bench one); the
spherical Bessel functions of order 0 and 1 enter only through
``x j0(x) / j1(x) = x^2 / (1 - x cot x)``, evaluated by its Taylor series for
small ``|x|`` and with a decaying exponential for ``cot`` otherwise, so the
result is accurate from DC to the skin-effect limit.
"""
from __future__ import annotations

import numpy as np

from coiltrack.hil.physics import MU0, EddyConductor, SourceCoil, dipole_field

__all__ = ["sphere_response", "sphere_moment_phasor", "highpass_response", "eddy_moment_phasor",
           "dipole_field_phasor"]

#: Taylor coefficients of ``(1 - x cot x) / x^2 - 1/3`` in powers of ``x^2`` (from x^2 on):
#: x cot x = 1 - x^2/3 - x^4/45 - 2 x^6/945 - x^8/4725 - 2 x^10/93555 - 1382 x^12/638512875 ...
_E_SERIES = (1.0 / 45.0, 2.0 / 945.0, 1.0 / 4725.0, 2.0 / 93555.0, 1382.0 / 638512875.0)
_SERIES_BELOW = 0.2


def _excess(x: np.ndarray) -> np.ndarray:
    """``E(x) = (1 - x cot x) / x^2 - 1/3`` (complex ``x`` with ``Im x <= 0``)."""
    x2 = x * x
    small = np.abs(x) < _SERIES_BELOW
    series = sum(c * x2 ** (k + 1) for k, c in enumerate(_E_SERIES))
    xs = np.where(small, 1.0, x)
    q = np.exp(-2j * xs)                      # |q| = exp(2 Im x) <= 1: no overflow
    cot = 1j * (1.0 + q) / (1.0 - q)
    direct = (1.0 - xs * cot) / (xs * xs) - 1.0 / 3.0
    return np.where(small, series, direct)


def sphere_response(omega, radius: float, sigma: float, mu_r: float = 1.0):
    """Normalised complex moment ``R = m / (-2 pi a^3 H0)`` of a sphere in a uniform field ``H0 e^{i omega t}``.

    Sphere of radius ``a``, conductivity ``sigma`` (S/m), relative permeability
    ``mu_r``. Inside, the vector potential is ``A_phi = C j1(k r) sin(theta)``
    with ``k^2 = -i omega mu_r mu0 sigma``; matching ``B_r`` and ``H_theta`` at
    ``r = a`` to the uniform field plus an outer dipole gives (Wait 1951, with
    ``x = k a``, ``G = x j0(x)/j1(x) - 1``)

        m = 2 pi a^3 H0 (2 mu_r - G) / (mu_r + G),

    written here with ``E = (1 - x cot x)/x^2 - 1/3`` (``G = x^2/(1 - x cot x) - 1``) as

        R = -(2 (mu_r - 1) + 3 (1 + 2 mu_r) E) / ((mu_r + 2) + 3 (mu_r - 1) E).

    Limits: DC (``E = 0``) ``m = 4 pi a^3 H0 (mu_r - 1)/(mu_r + 2)``, the static
    magnetic sphere of :class:`hil.physics.FerroSphere`; ``mu_r = 1``:
    ``R = 1 - 3/x^2 + 3 cot(x)/x`` (Wait 1951; :meth:`hil.physics.ConductingSphere.response`),
    at low frequency ``m = -i omega (2 pi/15) mu0 sigma a^5 H0``; perfect conductor
    (``|x| -> inf``, any ``mu_r``): ``R -> 1``, ``m = -2 pi a^3 H0``, approached as
    ``R = 1 - (3/2) mu_r (1 - i) delta / a`` with the skin depth
    ``delta = sqrt(2 / (omega mu_r mu0 sigma))``. ``omega`` scalar or array (rad/s).
    """
    w = np.asarray(omega, dtype=float)
    if np.any(w < 0.0) or radius <= 0.0 or sigma < 0.0 or mu_r <= 0.0:
        raise ValueError("need omega >= 0, radius > 0, sigma >= 0, mu_r > 0")
    x = np.sqrt(-1j * w * mu_r * MU0 * sigma) * radius   # principal root: Im x <= 0
    e = _excess(x)
    r = -(2.0 * (mu_r - 1.0) + 3.0 * (1.0 + 2.0 * mu_r) * e) / ((mu_r + 2.0) + 3.0 * (mu_r - 1.0) * e)
    return complex(r) if r.ndim == 0 else r


def sphere_moment_phasor(omega: float, radius: float, sigma: float, mu_r: float, B0) -> np.ndarray:
    """Complex moment (A m^2) for the applied field phasor ``B0`` (T, (3,), complex) at the centre."""
    R = sphere_response(omega, radius, sigma, mu_r)
    return -2.0 * np.pi * radius**3 / MU0 * R * np.asarray(B0, dtype=complex)


def highpass_response(omega, tau_s: float):
    """``H(i omega) = i omega tau / (1 + i omega tau)``: the L/R loop's current per unit of its DC coupling.

    A shorted loop ``L_e I_e' + R_e I_e = -M I_c'`` has ``I_e = -(M/L_e) H I_c``
    with ``tau = L_e/R_e`` (the time-domain high-pass of :class:`hil.physics.EddyConductor`).
    """
    if tau_s <= 0.0:
        raise ValueError("tau_s must be positive")
    wt = 1j * np.asarray(omega, dtype=float) * tau_s
    h = wt / (1.0 + wt)
    return complex(h) if h.ndim == 0 else h


def eddy_moment_phasor(conductor: EddyConductor, coil: SourceCoil, omega: float, current) -> np.ndarray:
    """Complex eddy moment (A m^2, (3,)) of ``conductor`` for a coil current phasor ``current`` (A).

    ``m_e = -kappa m_c H(i omega) I``: the steady state of ``EddyConductor.field``
    for ``I_c(t) = Re[I e^{i omega t}]``; at high frequency it tends to the
    step response ``-kappa m_c I``, at low frequency it vanishes as ``i omega tau``.
    """
    return conductor.moment_per_amp(coil) * highpass_response(omega, conductor.tau_s) * complex(current)


def dipole_field_phasor(points: np.ndarray, position: np.ndarray, moment) -> np.ndarray:
    """Field phasor (T, complex (n, 3)) of a complex dipole ``moment`` (the field is linear in it)."""
    m = np.asarray(moment, dtype=complex)
    pts = np.atleast_2d(points)
    return dipole_field(pts, position, m.real) + 1j * dipole_field(pts, position, m.imag)
