"""Bench physics against closed-form references.

The references here are written out independently of ``hil.physics`` (textbook
formulas, scipy quadrature and elliptic integrals); tolerances are stated at
each assertion.
"""

from __future__ import annotations

import magpylib
import numpy as np
import pytest
from scipy import integrate, special

from coiltrack.hil import physics as ph

MU0 = 4e-7 * np.pi  # textbook value; magpylib's CODATA value differs by 5e-10 relative


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def random_directions(rng, n):
    d = rng.standard_normal((n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# ---------------------------------------------------------------------------
# Coil fields
# ---------------------------------------------------------------------------


def test_single_turn_on_axis():
    """B_z = mu0 I a^2 / (2 (a^2 + z^2)^1.5); the filament model is exact: rel. tol 1e-9."""
    a, current = 0.05, 1.7
    axis = unit([1.0, -2.0, 0.5])
    center = np.array([0.1, -0.2, 0.3])
    coil = ph.SourceCoil(center=center, axis=axis, radius=a, turns=1)
    z = np.array([-0.4, -0.1, -0.01, 0.0, 0.02, 0.05, 0.3, 1.0])
    pts = center + z[:, None] * axis
    B = coil.field(pts, current)
    ref = MU0 * current * a**2 / (2.0 * (a**2 + z**2) ** 1.5)
    np.testing.assert_allclose(B @ axis, ref, rtol=1e-9)
    # no transverse component on the axis
    assert np.max(np.linalg.norm(B - np.outer(B @ axis, axis), axis=1)) < 1e-12 * ref.max()


def test_thin_multi_turn_scales_with_turns():
    """A thin coil of N turns is N single turns (exact, rel. tol 1e-12)."""
    pts = np.array([[0.1, 0.05, -0.02], [0.3, 0.3, 0.3]])
    one = ph.SourceCoil(np.zeros(3), [0, 0, 1], 0.055, 1)
    fifty = ph.SourceCoil(np.zeros(3), [0, 0, 1], 0.055, 50)
    np.testing.assert_allclose(fifty.unit_field(pts), 50 * one.unit_field(pts), rtol=1e-12)


def test_finite_solenoid_on_axis():
    """Single-layer solenoid: B = mu0 n I / 2 (cos a1 - cos a2).

    400 turns over 0.1 m at radius 0.02 m (pitch 0.25 mm). The turns are the
    midpoint rule of the current sheet; the difference is O((pitch/a)^2) = 1e-5
    relative: tolerance 1e-4 of the centre field, inside and outside the coil.
    """
    a, L, N, current = 0.02, 0.1, 400, 0.5
    coil = ph.SourceCoil(np.zeros(3), [0, 0, 1], a, N, length=L)
    assert coil.grid == (1, N)
    z = np.linspace(-0.2, 0.2, 41)
    B = coil.field(np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1), current)[:, 2]
    n = N / L
    cos1 = (z + L / 2) / np.sqrt(a**2 + (z + L / 2) ** 2)
    cos2 = (z - L / 2) / np.sqrt(a**2 + (z - L / 2) ** 2)
    ref = MU0 * n * current / 2.0 * (cos1 - cos2)
    assert np.max(np.abs(B - ref)) < 1e-4 * ref.max()


def thick_coil_on_axis(z, r1, r2, L, N, current):
    """On-axis field of a thick coil with uniform current density (derivation in the test below).

    B(z) = mu0 J / 2 [F(x2) - F(x1)],  J = N I / (L (r2 - r1)),
    F(x) = x ln((r2 + sqrt(r2^2 + x^2)) / (r1 + sqrt(r1^2 + x^2))),  x2 = L/2 - z, x1 = -L/2 - z.
    From the loop field mu0 I r^2 / (2 (r^2 + x^2)^1.5): the axial integral is
    [x / sqrt(r^2 + x^2)], and the radial integral of x / sqrt(r^2 + x^2) is x ln(r + sqrt(r^2 + x^2)).
    """
    J = N * current / (L * (r2 - r1))

    def F(x):
        return x * np.log((r2 + np.sqrt(r2**2 + x**2)) / (r1 + np.sqrt(r1**2 + x**2)))

    return MU0 * J / 2.0 * (F(L / 2 - z) - F(-L / 2 - z))


def test_thick_coil_formula_matches_quadrature():
    """The closed form above equals a direct double integral of loop fields (scipy, rel 1e-9)."""
    r1, r2, L, N, current = 0.03, 0.05, 0.04, 1000, 0.2
    J = N * current / (L * (r2 - r1))
    for z in (0.0, 0.015, 0.07):
        val, _ = integrate.dblquad(
            lambda zeta, r: MU0 * J * r**2 / (2 * (r**2 + (zeta - z) ** 2) ** 1.5),
            r1, r2, -L / 2, L / 2, epsabs=0, epsrel=1e-12,
        )
        assert thick_coil_on_axis(z, r1, r2, L, N, current) == pytest.approx(val, rel=1e-9)


def test_thick_coil_converges_with_subturns():
    """Filament grid -> continuous winding (midpoint rule, error ~ 1/n^2).

    r1 = 3 cm, r2 = 5 cm, L = 4 cm (a fat coil, points inside its bore).
    Error on the axis relative to the centre field: below 5e-3 for a 4 x 4
    grid (measured 4.5e-3), shrinking 4x per doubling; below 1e-4 for 32 x 32
    (measured 6.9e-5).
    """
    r1, r2, L, N, current = 0.03, 0.05, 0.04, 1000, 0.2
    z = np.array([0.0, 0.01, 0.025, 0.05, 0.1, 0.3])
    pts = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    ref = thick_coil_on_axis(z, r1, r2, L, N, current)
    errs = []
    for n in (4, 8, 16, 32):
        coil = ph.SourceCoil(np.zeros(3), [0, 0, 1], 0.04, N, r1, r2, L, grid=(n, n))
        B = coil.field(pts, current)
        errs.append(np.max(np.abs(B[:, 2] - ref)) / ref[0])
    assert errs[0] < 5e-3
    for e0, e1 in zip(errs, errs[1:]):
        assert 3.5 < e0 / e1 < 4.5
    assert errs[-1] < 1e-4
    # Gauss-Legendre 4 x 4 filaments (16) beat the 16 x 16 midpoint grid (256) on this coil
    gauss = ph.SourceCoil(np.zeros(3), [0, 0, 1], 0.04, N, r1, r2, L, grid=(4, 4), quadrature="gauss")
    assert np.max(np.abs(gauss.field(pts, current)[:, 2] - ref)) / ref[0] < errs[2]


def test_dipole_far_field_limit():
    """Thin coil vs dipole m = N I pi a^2: relative error <= 2 (a/r)^2, and ~4x smaller per doubling of r."""
    a, N, current = 0.055, 50, 1.5
    axis = unit([0.3, 0.4, 1.0])
    coil = ph.SourceCoil(np.zeros(3), axis, a, N)
    m = N * current * np.pi * a**2 * axis
    rng = np.random.default_rng(3)
    dirs = random_directions(rng, 50)
    prev = None
    for ratio in (4.0, 8.0, 16.0, 32.0):
        r = ratio * a
        pts = r * dirs
        B = coil.field(pts, current)
        mr = pts @ m
        ref = MU0 / (4 * np.pi) * (3 * pts * mr[:, None] / r**2 - m) / r**3
        err = np.max(np.linalg.norm(B - ref, axis=1) / np.linalg.norm(ref, axis=1))
        assert err <= 2.0 * (a / r) ** 2
        if prev is not None:
            assert 3.5 < prev / err < 4.5
        prev = err


def test_thesis_source_geometry_and_dipole_moments():
    """Three orthogonal 50-turn coils at the origin; moment per amp = sum w_i pi r_i^2 ~ 50 pi 0.055^2."""
    src = ph.thesis_source()
    assert len(src) == 3
    M = src.moments_per_amp
    assert np.allclose(M @ M.T, np.diag(np.diag(M @ M.T)), atol=1e-15)
    thin = 50 * np.pi * 0.055**2
    r_turns = 0.055 + (np.arange(5) + 0.5) * 0.003 / 5 - 0.0015  # 5 layers over 3 mm
    np.testing.assert_allclose(np.linalg.norm(M, axis=1), 10 * np.pi * np.sum(r_turns**2), rtol=1e-12)
    assert np.allclose(np.linalg.norm(M, axis=1), thin, rtol=5e-4)  # + depth^2/(12 r^2) = 2.5e-4
    for c in src:
        assert c.turns == 50 and c.radius == 0.055
        assert c.grid[0] * c.grid[1] == 50
        assert 1.5 <= c.resistance <= 2.5
        assert 0.2e-3 < c.tau_s < 0.5e-3  # L ~ 0.66 mH, tau = L/R ~ 0.33 ms << 60 ms pulses
    # far field at 0.8 m matches the dipole of the summed moment to (a/r)^2 ~ 0.5 %
    p = np.array([[0.5, 0.4, 0.3]])
    for k, c in enumerate(src):
        B = c.unit_field(p)[0]
        r = np.linalg.norm(p)
        ref = MU0 / (4 * np.pi) * (3 * p[0] * (p[0] @ M[k]) / r**2 - M[k]) / r**3
        assert np.linalg.norm(B - ref) < 0.01 * np.linalg.norm(ref)


def test_fast_path_equals_magpylib_collection():
    """Precomputed-array evaluation == magpylib Collection of Circle objects (rel. 1e-10)."""
    coil = ph.SourceCoil(
        center=[0.01, -0.02, 0.03], axis=[0.2, 1.0, 0.1], radius=0.05, turns=24,
        inner_radius=0.048, outer_radius=0.052, length=0.006, misalignment=[0.01, -0.02, 0.005],
    )
    assert len(coil.collection().children) == 24
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.4, 0.4, (30, 3))
    fast = coil.unit_field(pts)
    ref = coil.unit_field_magpylib(pts)
    assert np.max(np.abs(fast - ref)) < 1e-10 * np.max(np.abs(ref))


def test_misalignment_rotates_the_axis():
    """A misaligned coil is the nominal coil with its axis rotated (rel. 1e-12); 10 mrad changes B by ~1 %."""
    mis = np.array([0.0, 0.01, 0.0])
    c_mis = ph.SourceCoil(np.zeros(3), [0, 0, 1], 0.055, 50, misalignment=mis)
    rotated_axis = np.array([np.sin(0.01), 0.0, np.cos(0.01)])
    c_rot = ph.SourceCoil(np.zeros(3), rotated_axis, 0.055, 50)
    c_nom = ph.SourceCoil(np.zeros(3), [0, 0, 1], 0.055, 50)
    pts = np.array([[0.2, 0.1, 0.3], [0.0, 0.4, -0.1]])
    np.testing.assert_allclose(c_mis.true_axis, rotated_axis, atol=1e-15)
    np.testing.assert_allclose(c_mis.unit_field(pts), c_rot.unit_field(pts), rtol=1e-12, atol=1e-20)
    rel = np.linalg.norm(c_mis.unit_field(pts) - c_nom.unit_field(pts), axis=1) / np.linalg.norm(
        c_nom.unit_field(pts), axis=1)
    assert np.all((rel > 1e-3) & (rel < 5e-2))


def test_gauss_quadrature_close_to_turn_by_turn():
    """2 x 2 Gauss filaments vs 50 individual turns of the thesis coil: rel. difference < 1e-4 beyond 8 cm."""
    turns, gauss = ph.thesis_source(), ph.thesis_source(quadrature="gauss")
    rng = np.random.default_rng(5)
    for r in (0.08, 0.15, 0.4, 0.8):
        pts = r * random_directions(rng, 40)
        a, b = turns.unit_fields(pts), gauss.unit_fields(pts)
        assert np.max(np.linalg.norm(a - b, axis=-1) / np.linalg.norm(a, axis=-1)) < 1e-4


def test_field_is_divergence_and_curl_free():
    """Central-difference Jacobian of the summed field: |div|, |curl| < 1e-6 |J| (FD error ~ (h/r)^2 = 1e-8)."""
    src = ph.thesis_source()
    rng = np.random.default_rng(7)
    currents = np.array([1.5, -0.7, 1.1])
    for p in rng.uniform(0.08, 0.5, (8, 1)) * random_directions(rng, 8):
        h = 1e-4 * np.linalg.norm(p)
        pts = np.concatenate([p + h * np.eye(3), p - h * np.eye(3)])
        B = src.field(pts, currents)
        Jac = ((B[:3] - B[3:]) / (2 * h)).T  # J[i, j] = dB_i / dx_j
        scale = np.linalg.norm(Jac)
        assert abs(np.trace(Jac)) < 1e-6 * scale
        assert np.linalg.norm(Jac - Jac.T) < 1e-6 * scale


def test_field_linear_in_current_and_shapes():
    src = ph.thesis_source()
    pts = np.array([[0.2, 0.0, 0.1], [0.1, 0.3, -0.2]])
    U = src.unit_fields(pts)
    assert U.shape == (3, 2, 3)
    np.testing.assert_allclose(src.field(pts, [2.0, 0, 0]), 2.0 * U[0], rtol=1e-14)
    np.testing.assert_allclose(src[1].field(pts, -1.5), -1.5 * U[1], rtol=1e-12)
    assert src[2].unit_field(pts[0]).shape == (1, 3)


def test_unit_fields_is_one_vectorised_kernel_call(monkeypatch):
    """All points and all coils' filaments (3 x 50 for the thesis source) go
    through one call of magpylib's circle kernel, whatever the number of
    points: the per-sample cost does not grow with Python loops over coils,
    filaments or points (a per-coil or per-point fallback would multiply the
    calls). Counted, not timed; the result equals the Collection.getB path."""
    import magpylib

    src = ph.thesis_source()
    calls = []
    kernel = magpylib.core.current_circle_Hfield

    def counting(**kw):
        calls.append(np.size(kw["r"]))
        return kernel(**kw)

    monkeypatch.setattr(magpylib.core, "current_circle_Hfield", counting)
    for n in (1, 7):
        pts = np.random.default_rng(n).uniform(-0.4, 0.4, (n, 3)) + np.array([0.5, 0.0, 0.0])
        calls.clear()
        U = src.unit_fields(pts)
        assert len(calls) == 1 and calls[0] == n * 150
        monkeypatch.setattr(magpylib.core, "current_circle_Hfield", kernel)
        for k, coil in enumerate(src.coils):
            np.testing.assert_allclose(U[k], coil.unit_field_magpylib(pts), rtol=1e-9, atol=1e-15)
        monkeypatch.setattr(magpylib.core, "current_circle_Hfield", counting)


def coaxial_mutual(a, b, d):
    """Mutual inductance of coaxial circles (Maxwell): mu0 sqrt(ab) [(2/k - k) K - (2/k) E]."""
    k2 = 4 * a * b / ((a + b) ** 2 + d**2)
    k = np.sqrt(k2)
    return MU0 * np.sqrt(a * b) * ((2 / k - k) * special.ellipk(k2) - 2 / k * special.ellipe(k2))


def test_ring_inductance_against_filament_sum():
    """Maxwell's GMD formula vs the mean mutual inductance over a fine filament grid (N^2 <M>), within 1 %.

    The self pair of each cell uses the same GMD idea for the cell (its share
    of the sum is 1/n_cells), so this checks the formula's cross-section
    averaging rather than repeating it.
    """
    a, c, N = 0.055, 0.003, 50
    n = 16
    h = c / n
    x = (np.arange(n) + 0.5) * h - c / 2
    rr, zz = np.meshgrid(a + x, x, indexing="ij")
    r, z = rr.ravel(), zz.ravel()
    A, B = np.meshgrid(r, r, indexing="ij")
    ZA, ZB = np.meshgrid(z, z, indexing="ij")
    off = ~np.eye(r.size, dtype=bool)
    M = np.zeros_like(A)
    M[off] = coaxial_mutual(A[off], B[off], ZA[off] - ZB[off])
    g_cell = 0.2235 * 2 * h
    M[~off] = MU0 * r * (np.log(8 * r / g_cell) - 2)
    L_sum = N**2 * M.mean()
    assert ph.ring_inductance(N, a, c, c) == pytest.approx(L_sum, rel=1e-2)
    # Wheeler's multilayer formula is within ~10 % for this flat ring
    assert ph.wheeler_inductance(N, a, c, c) == pytest.approx(L_sum, rel=0.1)


# ---------------------------------------------------------------------------
# Coil current
# ---------------------------------------------------------------------------


def test_lr_waveform_at_tau_multiples():
    """Rise I_T (1 - e^-k), fall I_end e^-k at t = k tau (tau = 1 ms, exact integer us): abs 1e-12 A."""
    cur = ph.CoilCurrent(tau_rise_s=1e-3, pulses=[(10_000, 60_000, 1.5)])
    for k in range(0, 8):
        assert cur.current_at(10_000 + 1000 * k) == pytest.approx(1.5 * (1 - np.exp(-k)), abs=1e-12)
    i_end = 1.5 * (1 - np.exp(-60))
    for k in range(0, 8):
        assert cur.current_at(70_000 + 1000 * k) == pytest.approx(i_end * np.exp(-k), abs=1e-12)
    assert cur.current_at(0) == 0.0 and cur.current_at(9_999) == 0.0
    # vectorised, same values
    t = np.array([9_999, 10_000, 11_000, 70_000, 71_000])
    np.testing.assert_allclose(cur.current_at(t), [cur.current_at(int(x)) for x in t], rtol=0, atol=0)


def test_lr_waveform_separate_fall_and_back_to_back_pulses():
    cur = ph.CoilCurrent(tau_rise_s=2e-3, tau_fall_s=0.5e-3)
    cur.add_pulse(0, 4_000, 1.0)
    cur.add_pulse(4_500, 3_000, -1.0)  # starts before the first has decayed
    i4 = 1 - np.exp(-2.0)
    i45 = i4 * np.exp(-1.0)
    assert cur.current_at(4_500) == pytest.approx(i45, abs=1e-12)
    assert cur.current_at(6_500) == pytest.approx(-1 + (i45 + 1) * np.exp(-1.0), abs=1e-12)
    # a later command that overlaps cuts the running pulse short; out of order is fine too
    ref = ph.CoilCurrent(2e-3, 0.5e-3, pulses=[(0, 4_000, 1.0), (4_500, 500, -1.0), (5_000, 1_000, 1.0)])
    cur.add_pulse(5_000, 1_000, 1.0)
    assert cur.pulses == ref.pulses == [(0, 4_000, 1.0), (4_500, 500, -1.0), (5_000, 1_000, 1.0)]
    shuffled = ph.CoilCurrent(2e-3, 0.5e-3, pulses=[(5_000, 1_000, 1.0), (0, 4_000, 1.0), (4_500, 3_000, -1.0)])
    t = np.arange(0, 9_000, 7)
    np.testing.assert_array_equal(cur.current_at(t), ref.current_at(t))
    np.testing.assert_array_equal(shuffled.current_at(t), ref.current_at(t))
    np.testing.assert_allclose(shuffled.highpass_at(t, 1e-3), ref.highpass_at(t, 1e-3), rtol=1e-12, atol=1e-15)
    # didt matches central differences (rel 1e-6) away from edges
    for t in (1_000, 4_200, 5_500, 7_000, 9_000):
        fd = (cur.current_at(t + 1) - cur.current_at(t - 1)) / 2e-6
        assert cur.didt_at(t) == pytest.approx(fd, rel=1e-6)


def test_coil_current_from_coil_uses_l_over_r():
    coil = ph.thesis_source()[0]
    cur = ph.CoilCurrent.from_coil(coil, pulses=[(0, 60_000, 1.5)])
    assert cur.tau_rise == pytest.approx(coil.inductance / coil.resistance)
    other = ph.CoilCurrent(resistance=coil.resistance, inductance=coil.inductance)
    other.schedule(0, 60_000, 1.5)
    assert other.tau_us == pytest.approx(coil.tau_s * 1e6)
    assert other.current_at(12_345) == cur.current_at(12_345)
    t_tau = int(round(coil.tau_s * 1e6))
    assert cur.current_at(t_tau) == pytest.approx(1.5 * (1 - np.exp(-t_tau * 1e-6 / coil.tau_s)), rel=1e-12)


def test_supply_voltage_limits_the_current():
    """Target above V/R is clipped to V/R (same sign)."""
    coil = ph.thesis_source()[0]  # R = 2 ohm
    cur = ph.CoilCurrent.from_coil(coil, v_supply=2.0, pulses=[(0, 60_000, 1.5), (100_000, 60_000, -3.0)])
    assert cur.current_at(59_000) == pytest.approx(1.0, rel=1e-9)
    assert cur.current_at(159_000) == pytest.approx(-1.0, rel=1e-9)


def test_highpass_matches_ode_integration():
    """Closed-form high-pass of a pulse train vs a direct integration of tau y' + y = tau I' (abs 1e-6 A).

    Reference: exponential integrator on a 1 us grid, ``y_k = y_{k-1} e^{-dt/tau} + dI_k e^{-dt/(2 tau)}``
    (the current increment applied at mid-step; local error O(dt^2 I''), total ~1e-7 A here).
    """
    tau_c, tau_e = 0.4e-3, 1.3e-3
    cur = ph.CoilCurrent(tau_c, 0.7e-3, pulses=[(1_000, 5_000, 1.5), (8_000, 3_000, -1.0)])
    t = np.arange(0, 16_001)
    dI = np.diff(cur.current_at(t))
    y = np.zeros(t.size)
    a, b = np.exp(-1e-6 / tau_e), np.exp(-0.5e-6 / tau_e)
    for k in range(1, t.size):
        y[k] = y[k - 1] * a + dI[k - 1] * b
    hp = cur.highpass_at(t, tau_e)
    assert np.max(np.abs(hp - y)) < 1e-6
    assert np.max(np.abs(hp)) > 0.5
    # several time constants at once == one at a time
    taus = np.array([0.2e-3, tau_c, 2e-3])
    many = cur.highpass_at(t[::97], taus)
    assert many.shape == (3, t[::97].size)
    for i, tau in enumerate(taus):
        np.testing.assert_allclose(many[i], cur.highpass_at(t[::97], tau), rtol=1e-12, atol=1e-15)
    # equal time constants use the limit form
    cur2 = ph.CoilCurrent(1e-3, pulses=[(0, 10_000, 1.0)])
    s = 0.7e-3
    assert cur2.highpass_at(700, 1e-3) == pytest.approx(1.0 * s / 1e-3 * np.exp(-s / 1e-3), rel=1e-9)


# ---------------------------------------------------------------------------
# Eddy currents, ferromagnetic and conducting spheres
# ---------------------------------------------------------------------------


def test_eddy_dipole_decays_after_each_edge():
    """Ideal step: eddy moment = -kappa m_c dI e^{-t/tau_e} (rel 1e-6); zero in steady state."""
    coil = ph.thesis_source()[2]
    cur = ph.CoilCurrent(0.0, pulses=[(0, 60_000, 1.5)])  # ideal edges
    eddy = ph.EddyConductor(position=[0.0, 0.0, -0.1], coupling=2e-3, tau_s=1e-3)
    p = np.array([[0.0, 0.0, 0.0]])
    m = -2e-3 * coil.moment_per_amp
    u = MU0 / (4 * np.pi) * 2 * m / 0.1**3  # on the dipole axis: B = mu0 2 m / (4 pi r^3)
    for t in (1, 500, 1_000, 3_000):
        B = eddy.field(p, coil, cur, t)[0]
        np.testing.assert_allclose(B, 1.5 * np.exp(-t * 1e-6 / 1e-3) * u, rtol=1e-5, atol=1e-15)
    assert np.linalg.norm(eddy.field(p, coil, cur, 59_000)) < 1e-20
    # the falling edge induces the opposite sign
    assert eddy.field(p, coil, cur, 60_100)[0] @ u < 0
    # anisotropic coupling matrix
    eddy2 = ph.EddyConductor(position=[0.0, 0.0, -0.1], coupling=np.diag([0.0, 0.0, 2e-3]), tau_s=1e-3)
    np.testing.assert_allclose(eddy2.field(p, coil, cur, 500), eddy.field(p, coil, cur, 500), rtol=1e-12)


@pytest.mark.parametrize("mu_r", [1.0, 5.0, 1000.0])
def test_ferro_sphere_boundary_conditions(mu_r):
    """Dipole outside + uniform 3 mu_r/(mu_r + 2) B0 inside satisfy the interface conditions.

    Normal B continuous at the poles, tangential H continuous at the equator
    (evaluated 1e-9 a outside): rel. 1e-6.
    """
    a = 0.01
    c = np.array([0.2, 0.1, 0.0])
    B0 = np.array([0.0, 0.0, 3e-5])
    s = ph.FerroSphere(c, a, mu_r)
    B_in = 3 * mu_r / (mu_r + 2) * B0
    pole = c + np.array([0, 0, a * (1 + 1e-9)])
    equator = c + np.array([a * (1 + 1e-9), 0, 0])
    Bp = B0 + s.field(pole[None], B0)[0]
    Be = B0 + s.field(equator[None], B0)[0]
    assert Bp[2] == pytest.approx(B_in[2], rel=1e-6)
    assert Be[2] / MU0 == pytest.approx(B_in[2] / (MU0 * mu_r), rel=1e-6)
    if mu_r == 1.0:
        assert s.polarizability == 0.0


def test_ferro_sphere_matches_magpylib_uniformly_polarised_sphere():
    """Outside, the induced dipole equals magpylib's Sphere with J = 3 (mu_r - 1)/(mu_r + 2) B0 (rel 1e-9)."""
    a, mu_r = 0.02, 50.0
    c = np.array([0.1, 0.0, 0.2])
    B0 = np.array([1e-5, -2e-5, 4e-5])
    s = ph.FerroSphere(c, a, mu_r)
    J = 3 * (mu_r - 1) / (mu_r + 2) * B0
    ref = magpylib.magnet.Sphere(polarization=J, diameter=2 * a, position=c)
    rng = np.random.default_rng(2)
    pts = c + rng.uniform(0.03, 0.3, (20, 1)) * random_directions(rng, 20)
    np.testing.assert_allclose(s.field(pts, B0), ref.getB(pts), rtol=1e-9, atol=1e-18)


def test_ferro_sphere_in_coil_field_uniform_limit():
    """Using B0 at the centre is the exact dipole term even in the coil's non-uniform field.

    Each solid-harmonic order of the applied potential responds independently
    in a sphere, and the order-1 term is the field at the centre, which for a
    harmonic field equals its average over any sphere around it (mean-value
    property). Checked on the thesis coil field: the surface average over a
    2 cm sphere 12 cm from the source equals the centre value to 1e-5 relative,
    although the field varies by ~40 % across the sphere.
    """
    src = ph.thesis_source()
    s = ph.FerroSphere([0.09, 0.05, 0.06], 0.02, 200.0)
    n = 4000
    i = np.arange(n) + 0.5
    cz = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    dirs = np.stack([np.sqrt(1 - cz**2) * np.cos(phi), np.sqrt(1 - cz**2) * np.sin(phi), cz], axis=1)
    I = [1.5, -0.5, 0.8]
    surf = src.field(s.position + s.radius * dirs, I)
    B0 = src.field(s.position[None], I)[0]
    spread = np.max(np.linalg.norm(surf - B0, axis=1)) / np.linalg.norm(B0)
    assert spread > 0.2
    assert np.linalg.norm(surf.mean(axis=0) - B0) < 1e-5 * np.linalg.norm(B0)
    pts = np.array([[0.3, 0.0, 0.1]])
    np.testing.assert_allclose(s.field(pts, 2 * B0), 2 * s.field(pts, B0), rtol=1e-12)
    assert np.allclose(s.moment(B0), 4 * np.pi * 0.02**3 / ph.MU0 * (199 / 202) * B0, rtol=1e-12)


def test_conducting_sphere_mode_series():
    """Mode weights sum to 1 (perfect diamagnet at t = 0+); series vs closed-form frequency response."""
    s = ph.ConductingSphere([0, 0, 0], radius=0.02, sigma=5.8e7, n_modes=2000)
    c, tau = s.modes()
    assert c.sum() == pytest.approx(1.0, abs=1e-3)  # tail 6/(pi^2 N)
    assert tau[0] == pytest.approx(MU0 * 5.8e7 * 0.02**2 / np.pi**2, rel=1e-8)
    # t = 0+ moment equals the mu_r -> 0 limit of the magnetic sphere: -2 pi a^3 B0 / mu0
    B0 = np.array([0, 0, 1e-4])
    m0 = s.step_moment(0.0, B0)
    assert m0[2] == pytest.approx(ph.FerroSphere([0, 0, 0], 0.02, 0.0).moment(B0)[2], rel=1e-3)
    # closed form F = 1 - 3/x^2 + 3 cot(x)/x, x^2 = -i w mu0 sigma a^2, vs sum c_n i w tau_n/(1 + i w tau_n)
    for wt in (0.01, 0.3, 1.0, 5.0, 30.0):
        w = wt / tau[0]
        series = np.sum(c * 1j * w * tau / (1 + 1j * w * tau))
        assert abs(series - s.response(w)) < 2e-3 * abs(s.response(w))
    # the first mode dominates after ~tau_1: first-mode model within 1.5 % of the series at
    # 1 tau_1 (higher modes: (e^-4/4) / e^-1 = 1.2 %) and 0.1 % at 2 tau_1
    s1 = ph.ConductingSphere([0, 0, 0], radius=0.02, sigma=5.8e7, n_modes=1)
    assert s1.step_moment(tau[0], B0)[2] == pytest.approx(s.step_moment(tau[0], B0)[2], rel=1.5e-2)
    assert s1.step_moment(2 * tau[0], B0)[2] == pytest.approx(s.step_moment(2 * tau[0], B0)[2], rel=1e-3)


def test_conducting_sphere_driven_by_pulse():
    """Coil step (ideal edge): moment equals step_moment with dB0 = I u(c) (rel 1e-6)."""
    src = ph.thesis_source()
    s = ph.ConductingSphere([0.0, 0.0, 0.2], radius=0.01, sigma=3.5e7, n_modes=30)
    currents = [ph.CoilCurrent(0.0), ph.CoilCurrent(0.0), ph.CoilCurrent(0.0, pulses=[(0, 60_000, 1.5)])]
    dB0 = 1.5 * src.unit_fields(s.position[None])[2, 0]
    for t_us in (100, 1_000, 5_000):
        m = s.moment_from_coils(src, currents, t_us)
        np.testing.assert_allclose(m, s.step_moment(t_us * 1e-6, dB0), rtol=1e-6, atol=1e-16)


# ---------------------------------------------------------------------------
# Earth field, frames and the scene
# ---------------------------------------------------------------------------


def test_sensor_frame_and_earth():
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # sensor x -> world y
    B = ph.sensor_frame(ph.EARTH_FIELD_T, R)
    np.testing.assert_allclose(B, [0.0, -20e-6, -45e-6], atol=1e-20)
    Bn = ph.sensor_frame(np.tile(ph.EARTH_FIELD_T, (4, 1)), np.tile(R, (4, 1, 1)))
    assert Bn.shape == (4, 3) and np.allclose(Bn, B)
    assert ph.EarthField().field(np.zeros((5, 3))).shape == (5, 3)


def test_scene_sums_contributions():
    src = ph.thesis_source()
    currents = [ph.CoilCurrent.from_coil(c) for c in src]
    currents[0].add_pulse(0, 60_000, 1.5)
    currents[1].add_pulse(200_000, 60_000, 1.5)
    eddy = ph.EddyConductor([0.0, 0.2, 0.0], 1e-3, 2e-3)
    ferro = ph.FerroSphere([0.1, -0.2, 0.0], 0.01, 100.0)
    sphere = ph.ConductingSphere([0.0, 0.0, 0.25], 0.02, 3.5e7, n_modes=10)
    scene = ph.MagneticScene(src, currents, ph.EarthField(), [eddy], [ferro], [sphere])
    pts = np.array([[0.3, 0.1, 0.05], [0.25, -0.1, 0.2]])
    # steady state: coil + earth + ferro (eddy and conducting sphere have decayed)
    t = 50_000
    B = scene.field(pts, t)
    Bc = src.field(pts, [currents[0].current_at(t), 0.0, 0.0])
    B0 = src.field(ferro.position[None], [currents[0].current_at(t), 0, 0])[0] + ph.EARTH_FIELD_T
    ref = Bc + ph.EARTH_FIELD_T + ferro.field(pts, B0)
    np.testing.assert_allclose(B, ref, rtol=1e-9, atol=1e-15)
    # per-point times give the same as separate calls
    tt = np.array([1_000, 201_000])
    Bt = scene.field(pts, tt)
    for i in range(2):
        np.testing.assert_allclose(Bt[i], scene.field(pts[i:i + 1], int(tt[i]))[0], rtol=1e-12, atol=1e-18)
