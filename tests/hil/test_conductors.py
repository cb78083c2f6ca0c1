"""AC conductor responses against their limits and against time-domain references.

References are written out here independently of ``hil.conductors``: the
small-argument and skin-depth expansions of the sphere, the static magnetic
sphere, scipy's spherical Bessel functions, the existing mode series of
``hil.physics.ConductingSphere``, and a scipy ODE integration of the eddy loop.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, special

from coiltrack.hil import conductors as C
from coiltrack.hil import physics as ph

A, SIGMA = 0.02, 3.5e7              # 2 cm aluminium sphere
MU0 = ph.MU0


def _x(omega, mu_r=1.0):
    return np.sqrt(-1j * omega * mu_r * MU0 * SIGMA) * A


def test_sphere_low_frequency_is_minus_i_omega():
    """mu_r = 1, |x| << 1: R = i w mu0 sigma a^2 / 15 + 2 (w mu0 sigma a^2)^2 / 315 (rel 1e-6 incl. the next term)."""
    for omega in (1e-3, 1.0, 30.0):
        y = omega * MU0 * SIGMA * A**2
        R = C.sphere_response(omega, A, SIGMA)
        ref = 1j * y / 15.0 + 2.0 * y**2 / 315.0
        assert abs(R - ref) <= 1e-6 * abs(ref) + 0.1 * y**3
        m = -2 * np.pi * A**3 * R                      # per unit H0: the moment lags the field by 90 deg
        assert np.angle(m) == pytest.approx(-np.pi / 2, abs=2 * y)


def test_sphere_high_frequency_is_perfect_conductor():
    """|x| >> 1: R = 1 - (3/2) mu_r (1 - i) delta / a + O((delta/a)^2) for mu_r = 1 and 50; m -> -2 pi a^3 H0."""
    for mu_r in (1.0, 50.0):
        for omega in (1e7, 1e9, 1e12):
            delta = np.sqrt(2.0 / (omega * mu_r * MU0 * SIGMA))
            R = C.sphere_response(omega, A, SIGMA, mu_r)
            ref = 1.0 - 1.5 * mu_r * (1 - 1j) * delta / A
            assert abs(R - ref) <= 5.0 * (mu_r * delta / A) ** 2 + 1e-12
    assert C.sphere_response(1e14, A, SIGMA, 200.0) == pytest.approx(1.0, abs=1e-3)


def test_permeable_sphere_at_dc_is_the_magnetostatic_sphere():
    """omega = 0 (or sigma = 0): m = 4 pi a^3 (mu_r - 1)/(mu_r + 2) H0, as FerroSphere (rel 1e-12)."""
    B0 = np.array([0.0, 0.0, 1e-5])
    for mu_r in (0.5, 1.0, 3.0, 1000.0):
        m = C.sphere_moment_phasor(0.0, A, SIGMA, mu_r, B0)
        np.testing.assert_allclose(m.real, ph.FerroSphere([0, 0, 0], A, mu_r).moment(B0), rtol=1e-12, atol=1e-30)
        assert np.all(m.imag == 0.0)
        assert C.sphere_response(5.0, A, 0.0, mu_r) == pytest.approx(-2 * (mu_r - 1) / (mu_r + 2), rel=1e-12)


def test_sphere_matches_spherical_bessel_form_everywhere():
    """Between the limits: m = 2 pi a^3 H0 (2 mu_r - G)/(mu_r + G), G = x j0/j1 - 1 (scipy, rel 1e-9)."""
    for mu_r in (1.0, 4.0, 100.0):
        for omega in np.geomspace(1.0, 1e6, 13):
            x = _x(omega, mu_r)
            if abs(x) > 300.0:                              # sin, cos overflow beyond; covered by the limit test
                continue
            j0 = np.sin(x) / x                              # scipy's spherical_jn is real-only
            j1 = np.sin(x) / x**2 - np.cos(x) / x
            G = x * j0 / j1 - 1.0
            ref = -(2 * mu_r - G) / (mu_r + G)
            assert C.sphere_response(omega, A, SIGMA, mu_r) == pytest.approx(ref, rel=1e-9)
    xr = np.array([0.7, 2.0, 3.5])                        # real arguments: the closed forms are scipy's
    np.testing.assert_allclose(np.sin(xr) / xr, special.spherical_jn(0, xr), rtol=1e-13)
    np.testing.assert_allclose(np.sin(xr) / xr**2 - np.cos(xr) / xr, special.spherical_jn(1, xr), rtol=1e-13)


def test_sphere_matches_transient_mode_series():
    """mu_r = 1: the exact response equals the time-domain model's modes, sum c_n i w tau_n/(1 + i w tau_n)."""
    s = ph.ConductingSphere([0, 0, 0], radius=A, sigma=SIGMA, n_modes=4000)
    c, tau = s.modes()
    w = np.geomspace(0.03, 30.0, 9) / tau[0]
    series = np.array([np.sum(c * 1j * wk * tau / (1 + 1j * wk * tau)) for wk in w])
    R = C.sphere_response(w, A, SIGMA)
    np.testing.assert_allclose(R, series, rtol=3e-3)     # series tail 6/(pi^2 N) at high w
    np.testing.assert_allclose(R[:4], [s.response(wk) for wk in w[:4]], rtol=1e-9)


def test_eddy_loop_transfer_function_against_ode():
    """Lumped loop tau y' + y = tau I', I = cos(w t) from rest: steady amplitude and phase of y equal
    H = i w tau/(1 + i w tau) (least-squares fit over the last 4 periods after 30 tau; rel 1e-6, 1e-6 rad)."""
    tau = 2e-3
    for f in (10.0, 80.0, 400.0):
        w = 2 * np.pi * f
        t_end = 30 * tau + 4 / f
        sol = integrate.solve_ivp(lambda t, y: (-tau * w * np.sin(w * t) - y) / tau, (0.0, t_end), [0.0],
                                  method="DOP853", rtol=1e-12, atol=1e-14, dense_output=True)
        t = np.linspace(t_end - 4 / f, t_end, 400)
        M = np.column_stack([np.cos(w * t), -np.sin(w * t)])
        (re, im), *_ = np.linalg.lstsq(M, sol.sol(t)[0], rcond=None)
        H = C.highpass_response(w, tau)
        assert abs(re + 1j * im) == pytest.approx(abs(H), rel=1e-6)
        assert np.angle(re + 1j * im) == pytest.approx(np.angle(H), abs=1e-6)
        assert np.angle(H) == pytest.approx(np.pi / 2 - np.arctan(w * tau), abs=1e-12)   # leads the current


def test_eddy_moment_phasor_is_the_eddy_conductors_steady_state():
    """EddyConductor.moment_per_amp times H: at high frequency the step response -kappa m_c, at DC zero."""
    coil = ph.thesis_source()[2]
    eddy = ph.EddyConductor([0.0, 0.0, -0.1], coupling=2e-3, tau_s=1e-3)
    m_step = eddy.moment_per_amp(coil)
    np.testing.assert_allclose(C.eddy_moment_phasor(eddy, coil, 1e9, 1.5), 1.5 * m_step, rtol=1e-5)
    assert np.all(np.abs(C.eddy_moment_phasor(eddy, coil, 0.0, 1.5)) == 0.0)
    w = 1.0 / eddy.tau_s                                 # corner: |H| = 1/sqrt 2, phase +45 deg
    m = C.eddy_moment_phasor(eddy, coil, w, 1.0)
    np.testing.assert_allclose(m, m_step * (0.5 + 0.5j), rtol=1e-12)
    pts = np.array([[0.2, 0.1, 0.0]])
    B = C.dipole_field_phasor(pts, eddy.position, m)
    np.testing.assert_allclose(B, 0.5 * (1 + 1j) * ph.dipole_field(pts, eddy.position, m_step), rtol=1e-12)
