"""The least-energy bound of ``tools/analyses/energy_bound.py`` against closed forms."""
import math

import numpy as np
import pytest

from coiltrack.tools.analyses import energy_bound as eb
from coiltrack.tools.analyses.pulse_cost import Kinds, Timing, WindowCost, pulse_samples, pulse_weight

#: the firmware's extraction timing at the bench's 100 Hz (settle 3 ms, guard 2 ms, fall 3 ms)
TM100 = Timing(100.0, 3e-3, 2e-3, 3e-3)


class _AxialDipole:
    """A one-coil source: a point dipole of 1e-7 T m^3 per A along z (mu0/4pi m = 1e-7), in closed form."""

    def __len__(self):
        return 1

    def unit_fields(self, points):
        p = np.atleast_2d(points)
        r = np.linalg.norm(p, axis=1)[:, None]
        m = np.array([0.0, 0.0, 1e-7])
        return ((3.0 * p * (p @ m)[:, None] / r ** 2 - m) / r ** 3)[None]


def _axis_H(z, k=1e-7, R=np.eye(3)):
    """Per-ampere Jacobian [R^T G, [u]x] of the dipole on its axis at z, and the field u."""
    G = np.diag([3.0, 3.0, -6.0]) * k / z ** 4
    u = R.T @ np.array([0.0, 0.0, 2.0 * k / z ** 3])
    ux = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    return np.hstack([R.T @ G, ux]), u


def test_pulse_information_on_the_dipole_axis():
    """On the axis of a z dipole at distance z the field is 2k/z^3 along z and dB/dp = diag(3, 3, -6) k / z^4:
    J = H^T H with H = [R^T G, [h]x]. Catches a dropped R^T, the cross-product block's sign or place, and a
    gradient with the wrong step (tolerance 1e-6 relative, the central difference's error at h = 1e-5 m)."""
    z = 0.3
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])    # sensor turned 90 deg about x
    J = eb.pulse_information(_AxialDipole(), np.array([2.0]), np.array([[0.0, 0.0, z]]), R[None])[0, 0]
    H, _ = _axis_H(z, R=R)
    H = 2.0 * H
    np.testing.assert_allclose(J, H.T @ H, rtol=1e-6, atol=1e-6 * np.abs(H.T @ H).max())


# --------------------------------------------------------------- samples per pulse
def test_samples_of_todays_pulse_counted_by_hand():
    """60 ms at 100 Hz, settle 3 ms, guard 2 ms: 6 or 7 samples lie in [start, end]; whatever the phase,
    removing those outside [3, 58] ms and the first and the last leaves 4. Baselines [-35, -2] ms and
    [63, 98] ms hold 3.3 + 3.5 = 6.8 on average. A 60.5 ms pulse at its best phase (a sample just after
    the start) uses 5 (10..50 ms), on average 4.05. Catches a count that keeps the first or last sample
    inside the settled window (5.5) and a baseline side counted from the wrong edge."""
    assert pulse_samples(0.06, 0.035, TM100) == pytest.approx((4.0, 6.8), abs=1e-9)
    assert pulse_samples(0.06, 0.035, TM100, "aligned")[0] == 4
    assert pulse_samples(0.0605, 0.035, TM100, "aligned")[0] == 5
    assert pulse_samples(0.0605, 0.035, TM100)[0] == pytest.approx(4.05, abs=1e-9)
    # 1 kHz: the first and last samples are within 1 ms of the edges, outside the settled window
    assert pulse_samples(0.03, 0.035, Timing(1000.0, 3e-3, 2e-3, 3e-3)) == pytest.approx((25.0, 68.0), abs=1e-9)


def test_a_window_the_extraction_refuses_counts_no_sample():
    """``min_pulse_samples`` 3 (the firmware's): a 30.5 ms pulse with a sample just after its start uses
    two (10, 20 ms; 0 and 30 are the first and the last), which the extractor refuses, so it counts none,
    and the best phase of a 30.5 ms pulse then brings nothing; a 40.5 ms one uses three (10, 20, 30 ms).
    By hand on the 100 Hz clock the mean count of a 50 ms pulse is 3 at every phase (kept), of a 45 ms
    one 2.5 (2 or 3 used, half the phases each) without the minimum and 1.5 with it. Catches a bound
    crediting windows the extraction drops (the optimum's 30 ms pulses)."""
    tm3 = Timing(100.0, 3e-3, 2e-3, 3e-3, 3)
    assert pulse_samples(0.0305, 0.035, TM100, "aligned")[0] == 2
    assert pulse_samples(0.0305, 0.035, tm3, "aligned")[0] == 0
    assert pulse_samples(0.0405, 0.035, tm3, "aligned")[0] == 3
    assert pulse_samples(0.05, 0.035, tm3)[0] == pytest.approx(3.0, abs=1e-9)
    assert pulse_samples(0.045, 0.035, TM100)[0] == pytest.approx(2.5, abs=1e-9)
    assert pulse_samples(0.045, 0.035, tm3)[0] == pytest.approx(1.5, abs=1e-9)
    assert pulse_samples(0.06, 0.035, tm3) == pytest.approx((4.0, 6.8), abs=1e-9)


def test_seed_model_reads_the_sectioned_configuration():
    """The scenario's world and configuration at a short duration: the fixed cycle's information weight
    per coil and window equals the closed form ``I^2 / (sigma^2 (1/4 + 1/6.8) + ((rho I)^2 + tau^2) |u|^2)``
    (60 ms pulses, 35 ms baselines at 100 Hz), the extraction's minimum comes from the configuration,
    and the saturated share is the share of coil-windows whose model error exceeds the white noise."""
    m = eb.SeedModel(1, 1, 3.0)
    c = m.cfg
    assert m.tm.min_used == c.pulse.min_pulse_samples
    a = c.pulse.mag_sigma_t ** 2 * (1 / 4 + 1 / 6.8)
    rho, tau = c.adaptive.field_model_rel_sigma, c.limits.current_tolerance_a
    want = m.I0 ** 2 / (a + ((rho * m.I0) ** 2 + tau ** 2) * m.u2)
    np.testing.assert_allclose(m.x0, want, rtol=1e-9)
    model = ((rho * m.I0) ** 2 + tau ** 2) * m.u2
    assert m.saturated_share() == pytest.approx(float(np.mean(model > a)), abs=1e-12)
    assert m.cost(Kinds.fixed(0.06, 0.035, m.tm)).D == pytest.approx(0.6)


def test_used_samples_never_fall_with_the_length():
    """The optimistic kinds of ``Kinds.chosen`` are below every length of their interval only if the
    count never falls with the length; checked on a 0.1 ms grid."""
    n = [pulse_samples(t, 0.035, TM100)[0] for t in np.arange(0.006, 0.2, 1e-4)]
    assert np.all(np.diff(n) >= -1e-12)


# --------------------------------------------------------------- regression anchor: the 60 ms bound of before
def _closed_form(s, a, ratio):
    """Least energy for J_w = s_w I (one coil) and mse_w ~ (1 / (s_w e_w))^a: e_w ~ s_w^(-a/(a+1)) (Lagrange),
    fraction (mean s^(-a/(a+1)))^((a+1)/a) / (ratio^(2/a) (mean s^-a)^(1/a))."""
    s = np.asarray(s, float)
    return np.mean(s ** (-a / (a + 1))) ** ((a + 1) / a) / (ratio ** (2 / a) * np.mean(s ** -a) ** (1 / a))


def _white_problem(s, kinds, sigma2=1.0, D=100.0, T0=0.06, B0=0.035, tm=TM100):
    """One coil, no model error, no limits: the fixed cycle's pulse (1 A, T0, B0) has weight 1/a0."""
    W = len(s)
    Jt = np.asarray(s, float)[:, None, None, None] * np.eye(6)[None, None]
    nu, nb = pulse_samples(T0, B0, tm)
    x0 = np.full((W, 1), 1.0 / (sigma2 * (1 / nu + 1 / nb)))
    cost = WindowCost(kinds, sigma2, np.ones((W, 1)), 0.0, 0.0, np.full((W, 1), np.inf), D)
    return Jt, x0, cost, T0


@pytest.mark.parametrize("a,ratio", [(1.0, 1.0), (0.5, 1.0), (0.75, 1.1)])
def test_sixty_ms_bound_without_model_error_is_the_lagrange_solution(a, ratio):
    """With today's 60 ms pulses and 35 ms baselines, no model error and slack limits, the bound is the one
    before: windows whose information differs by a factor 16, the optimum spends less where a pulse buys
    more, fraction from the Lagrange solution. Catches a constraint on the RMS instead of the mean square,
    a wrong gradient, a fraction normalised per coil-window wrongly, and a pulse model that changes the
    60 ms case. Tolerance 1e-4 relative (SLSQP's ftol 1e-10)."""
    s = np.array([1.0, 16.0, 4.0, 1.0, 2.0])
    Jt, x0, cost, T0 = _white_problem(s, Kinds.fixed(0.06, 0.035, TM100))
    got = eb.least_energy(Jt, x0, cost, T0, a, a, ratio)
    assert got["converged"]
    assert got["energy_fraction"] == pytest.approx(_closed_form(s, a, ratio), rel=1e-4)
    assert got["position_rms_ratio"] == pytest.approx(ratio, rel=1e-4)


def test_equal_windows_save_nothing_but_the_slack():
    """Every window alike and one coil: no policy beats the cycle except by the allowed RMS, fraction
    ratio^(-2/a). Catches a bound that invents a saving from nothing."""
    Jt, x0, cost, T0 = _white_problem(np.ones(8), Kinds.fixed(0.06, 0.035, TM100))
    assert eb.least_energy(Jt, x0, cost, T0, 0.75, 0.75, 1.0)["energy_fraction"] == pytest.approx(1.0, rel=1e-6)
    assert eb.least_energy(Jt, x0, cost, T0, 0.75, 0.75, 1.1)["energy_fraction"] == pytest.approx(
        1.1 ** (-2 / 0.75), rel=1e-4)


# --------------------------------------------------------------- shorter pulses must win
@pytest.mark.parametrize("rate,B,c_over,p", [(1000.0, 0.035, 5e-3, 1e-3), (100.0, 0.035, 20e-3, 10e-3),
                                             (100.0, 0.100, 20e-3, 10e-3)])
def test_pulse_length_chosen_where_information_per_joule_peaks(rate, B, c_over, p):
    """One coil, one window, no model error, the fixed cycle's information asked (ratio 1): the energy
    is ``I^2 T`` for the weight ``I^2 / (sigma^2 (1/n_u + 1/n_b))``, so the best length minimises
    ``T (1/n_u(T) + 1/n_b)``. With ``n_u = (T - c) / p`` (c = settle + guard at 1 kHz, two sample periods
    at 100 Hz where the first and last samples are dropped) the minimum is at ``T* = c + sqrt(c p n_b)``:
    23.4 ms at 1 kHz (shorter than 60 ms wins), 56.9 ms at 100 Hz with 35 ms baselines (60 ms is near
    the best) and 82.9 ms with 100 ms baselines (longer pulses win). The bound's length within 0.2 ms
    of T* and its fraction of the 60 ms pulse's cost at most the closed form's and within 1e-3 of it
    (the 0.05 ms grid credits each interval with its shorter end's time: about 0.05 ms / T* of the
    baseline's part, 4.5e-4 at 1 kHz). Catches an overhead left
    out, the baseline's samples not counted, and a grid whose credit exceeds a real pulse's."""
    tm = Timing(rate, 3e-3, 2e-3, 3e-3)
    nb = (2 * B - tm.guard_s) / p
    T_star = c_over + math.sqrt(c_over * p * nb)
    f = lambda T: T * (p / (T - c_over) + 1 / nb)  # noqa: E731
    kinds = Kinds.chosen(np.arange(0.0005, 0.15, 0.00005), [B], tm)
    Jt, x0, cost, T0 = _white_problem([1.0], kinds, T0=0.06, B0=B, tm=tm)
    got = eb.least_energy(Jt, x0, cost, T0, 1.0, 1.0, 1.0)
    closed = f(T_star) / f(0.06)
    assert got["energy_fraction"] <= closed * (1 + 1e-9)
    assert got["energy_fraction"] == pytest.approx(closed, rel=1e-3)
    assert kinds.T[got["detail"]["kind"][0, 0]] == pytest.approx(T_star, abs=2e-4)
    if rate == 1000.0:
        assert closed < 0.83           # shorter pulses must win: 23 ms needs 0.82 of the 60 ms pulse's energy


@pytest.mark.parametrize("rate,phase", [(100.0, "mean"), (1000.0, "mean"), (100.0, "aligned")])
def test_credit_between_grid_lengths_is_below_every_length(rate, phase):
    """Each kind of ``Kinds.chosen`` costs at most what every pulse length of its interval costs (time
    ``T + gap``, white noise ``c``, energy factor ``T c``): checked against ``Kinds.fixed`` at 11 lengths
    per interval, the shortest pulses (where the count is not affine in the length) included. Catches a
    credit above a real pulse (the bound would then not be one) and a credit looser than needed."""
    tm = Timing(rate, 3e-3, 2e-3, 3e-3)
    grid = np.arange(0.005, 0.09, 0.005)
    ch = Kinds.chosen(grid, [0.035], tm, phase)
    for T0, slot, c, tc in zip(ch.T, ch.slot, ch.c, ch.tc):
        for t in np.linspace(T0, T0 + 0.005, 11):
            if min(pulse_samples(float(t), 0.035, tm, phase)) <= 0:
                continue
            k = Kinds.fixed(float(t), 0.035, tm, phase)
            assert slot <= k.slot[0] + 1e-15 and c <= k.c[0] + 1e-12 and tc <= k.tc[0] + 1e-12
    if phase == "aligned":
        return
    # tight where the count is affine: below the interval's best length by at most the baseline's part
    # of the step, 5 ms / n_b (the T / n_u part exact at an end)
    i = int(np.argmin(np.abs(ch.T - 0.06)))
    best = min(Kinds.fixed(float(t), 0.035, tm).tc[0] for t in np.linspace(0.06, 0.065, 11))
    nb = pulse_samples(0.06, 0.035, tm)[1]
    assert best - 0.005 / nb - 1e-12 <= ch.tc[i] <= best


# --------------------------------------------------------------- model error saturates the information
def test_information_saturates_with_current_at_the_model_error():
    """A pulse's information ``I^2 H_u^T H_u / (a + (rho I |u|)^2)`` tends to ``H_u^T H_u / (rho |u|)^2`` as
    the current grows, whatever the distance (h^0: the limit of ``s |u|^2`` is ``1 / rho^2``); at small
    currents it is ``I^2 H_u^T H_u / a``. On the dipole's axis at 0.2 and 0.35 m, rho = 3e-3, a the
    white noise of today's pulse at 3e-8 T. Catches a model error added to the standard deviation
    instead of the variance, or scaled with the current twice."""
    rho, sigma = 3e-3, 3e-8
    nu, nb = pulse_samples(0.06, 0.035, TM100)
    a = sigma ** 2 * (1 / nu + 1 / nb)
    for z in (0.2, 0.35):
        H, u = _axis_H(z)
        u2 = float(u @ u)
        Jt, uu = eb.unit_model(_AxialDipole(), np.array([[0.0, 0.0, z]]), np.eye(3)[None])
        assert float(np.sum(uu ** 2)) == pytest.approx(u2, rel=1e-9)
        J_big = pulse_weight(1e6, a, rho * rho * u2) * Jt[0, 0]
        np.testing.assert_allclose(J_big, H.T @ H / (rho * rho * u2), rtol=1e-6, atol=1e-12 * np.abs(J_big).max())
        assert pulse_weight(1e6, a, rho * rho * u2) * u2 == pytest.approx(1 / rho ** 2, rel=1e-6)
        assert pulse_weight(1e-4, a, rho * rho * u2) == pytest.approx(1e-8 / a, rel=1e-6)


def test_window_energy_with_saturation_and_shared_time():
    """One coil, 60 ms pulses in a 0.6 s window (six 100 ms slots): the pulses fill the time, so the
    energy of the weight x is ``T a x m / (m - b x)`` with m = 6; the window holds at most ``m / b``.
    Two coils sharing the window: the dual's energy equals the primal's optimum over the split of the
    pulses, found by scipy on ``sum_k T a_k x_k m_k / (m_k - b_k x_k)``, ``m_1 + m_2 = 6``.
    Catches a time price that does not bind, a saturation term with the wrong power and a dual value
    above the primal."""
    from scipy.optimize import minimize_scalar

    kinds = Kinds.fixed(0.06, 0.035, TM100)
    a0 = 1 / 4 + 1 / 6.8
    b = 0.7
    cost = WindowCost(kinds, 1.0, np.array([[b]]), 1.0, 0.0, np.array([[np.inf]]), 0.6)
    for x in (1.0, 4.0, 8.0):
        E, _, d = cost.energy(np.array([[x]]))
        assert E[0] == pytest.approx(0.06 * a0 * x * 6 / (6 - b * x), rel=1e-9)
        assert d["time"][0, 0] == pytest.approx(0.6, rel=1e-9)
    assert cost.psi[0, 0] * (6 / b) == pytest.approx(0.6, rel=1e-12)
    u2 = np.array([[0.7, 0.2]])
    cost2 = WindowCost(kinds, 1.0, u2, 1.0, 0.5, np.full((1, 2), np.inf), 0.6)
    x = np.array([[3.0, 9.0]])
    E2, grad, _ = cost2.energy(x)
    aa, bb = a0 + 0.25 * u2[0], u2[0]
    prim = lambda m1: sum(0.06 * aa[k] * x[0, k] * m / (m - bb[k] * x[0, k])  # noqa: E731
                          for k, m in enumerate((m1, 6.0 - m1)))
    r = minimize_scalar(prim, bounds=(bb[0] * 3.0 + 1e-9, 6.0 - bb[1] * 9.0 - 1e-9), method="bounded",
                        options={"xatol": 1e-12})
    assert E2[0] == pytest.approx(r.fun, rel=1e-7)
    assert E2[0] <= r.fun * (1 + 1e-12)
    h = 1e-6
    num = (cost2.energy(x + [[h, 0.0]])[0][0] - cost2.energy(x - [[h, 0.0]])[0][0]) / (2 * h)
    assert grad[0, 0] == pytest.approx(num, rel=1e-5)


def test_model_error_lowers_the_bound_where_the_cycle_is_saturated():
    """The fixed cycle's 1 A pulse with (rho |u|)^2 = 9 a brings x0 = 1 / (10 a); six weaker pulses in
    the same window bring it for ``T a x0 6 / (6 - b x0)`` = 0.1176 of its energy (ratio 1, one window).
    Without model error the same window needs all of it. The docstring before said model error only
    raises the energy; catches that."""
    kinds = Kinds.fixed(0.06, 0.035, TM100)
    a0 = 1 / 4 + 1 / 6.8
    for b, want in ((9 * a0, 0.1 * 6 / 5.1), (0.0, 1.0)):
        Jt = np.eye(6)[None, None]
        x0 = np.array([[1.0 / (a0 + b)]])
        cost = WindowCost(kinds, 1.0, np.array([[1.0]]), math.sqrt(b), 0.0, np.array([[np.inf]]), 0.6)
        got = eb.least_energy(Jt, x0, cost, 0.06, 1.0, 1.0, 1.0)
        assert got["energy_fraction"] == pytest.approx(want, rel=1e-5)


# --------------------------------------------------------------- limits and exponents
def test_current_limit_of_the_range_with_the_earth_field():
    """u = (2, -1, 0) uT/A, earth (30, 40, -45) uT, range 100 uT, driver 100 A: a positive pulse leaves
    70/2 = 35 A on x and 140/1 on y; a negative one 130/2 = 65 on x and 60/1 on y: 60 A. The driver's
    2 A then limits. Catches the earth field ignored or added on the wrong side."""
    u = np.array([[[2e-6, -1e-6, 0.0]]])
    earth = np.array([[30e-6, 40e-6, -45e-6]])
    assert eb.current_limit(u, earth, 100e-6, 100.0)[0, 0] == pytest.approx(60.0, rel=1e-12)
    assert eb.current_limit(u, earth, 100e-6, 2.0)[0, 0] == 2.0


def test_exponent_of_a_power_law():
    """rms ~ E^(-a/2) gives back a; catches an exponent of the RMS instead of the mean square."""
    assert eb.exponent(2.0, 2.0 * 4.0 ** (0.7 / 2), 8.0, 2.0) == pytest.approx(0.7, rel=1e-12)


def test_fitted_exponent_without_saturation_is_the_energy_ratio_one():
    """J_lo = J_hi / q in every window: the fit is the closed form log(rms ratio^2) / log q; with windows
    unequal as well. Catches a fit on the RMS instead of the mean square."""
    rng = np.random.default_rng(3)
    M = rng.normal(size=(7, 6, 6))
    J = M @ np.transpose(M, (0, 2, 1)) + 6 * np.eye(6)
    q = (0.91 / 0.45) ** 2
    got = eb.fit_exponent(J, J / q, 2.0, 2.0 * q ** (0.65 / 2), eb.POS)
    assert got == pytest.approx(0.65, rel=1e-8)


@pytest.mark.parametrize("argv", [["--ratio", "0.5"], ["--length-step-ms", "0"], ["--a-pos", "-1", "--a-rot", "1"],
                                  ["--seeds", "1", "--sweeps", "/nonexistent"], ["--columns", "fixed,short"]])
def test_bad_arguments_exit_2(argv, capsys):
    assert eb.main(argv) == 2
    assert "energy_bound:" in capsys.readouterr().err


def test_the_bound_is_taken_on_the_trajectory_the_bench_runs():
    """``SeedModel(seed)`` samples the world the bench builds for ``seed`` (``BenchSetup`` draws the
    world's seed from ``SeedSequence(seed)``): the same positions at the same instants. Catches a bound
    taken on ``build_world(seed)``, another trajectory than the runs it is compared with."""
    from coiltrack.tools import scenarios
    from coiltrack.tools.analyses import energy_bound as eb
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.bench.runner import BenchSetup

    m = eb.SeedModel(2, 1, 60.0)
    bench = BenchSetup(scenarios.get("schepers-adaptive"), 2, 60.0, inproc_pair()[1])
    t = ((np.arange(m.p.shape[0]) + 0.5) * m.D * 1e6).astype(np.int64)
    np.testing.assert_allclose(bench.world.sensor_kinematics(t).position, m.p, rtol=0, atol=1e-12)
