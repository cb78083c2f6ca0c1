"""The coil driver's regulation error, ripple and the winding's resistance rising with temperature
(``hil.nodes.DriverAccuracy``, ``CoilDriverNode``), against closed forms and a scipy ODE."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from coiltrack.hil import physics as ph
from coiltrack.hil.motion import StaticPose
from coiltrack.hil.nodes import COPPER_ALPHA_PER_K, CoilDriverNode, DriverAccuracy, DriverLimits
from coiltrack.hil.world import World

NO_ERRORS = DriverAccuracy(0.0, 0.0, 0.0, ripple=False)      # resistance law only


def _driver(accuracy, supply_v=6.0, seed=3):
    src = ph.thesis_source()
    world = World(src, StaticPose(np.array([0.3, 0.0, 0.0]), np.eye(3)), supply_v=supply_v)
    return CoilDriverNode(1, world, seed=seed, accuracy=accuracy, current_noise_a=0.0), world


def _fire(drv, c, t0, dur, amps, pulse_id=1):
    rec = {"coil": c, "pulse_id": pulse_id, "master_start_us": t0, "master_end_us": t0 + dur, "target_a": amps,
           "start_us": t0, "end_us": t0 + dur, "rx_true_us": t0 - 10_000, "lead_us": 10_000, "faults": 0}
    drv._commit(rec)
    out = []
    drv.step(t0 + dur, lambda node, msg: out.append(msg))
    return rec, out


@pytest.mark.parametrize("supply_v, want_limited", [(6.0, False), (3.2, True)])
def test_rl_step_with_the_resistance_of_a_hot_winding(supply_v, want_limited):
    """Coil 0 at 65 C: R = R_a (1 + a (65 - 20)) / (1 + a (25 - 20)) (copper 0.393 %/K) = 2.308 ohm; the
    current is I (1 - exp(-t R / L)) with I = 1.5 A while 1.5 R <= V (6 V) and I = V / R = 1.386 A at 3.2 V,
    and COIL_STATUS reports it (rel 1e-9): catches the cold resistance in the L/R or in the voltage limit,
    or a driver that holds the current beyond its compliance."""
    drv, world = _driver(NO_ERRORS, supply_v)
    t0 = 1_000_000
    drv.temp_c[0], drv._temp_t[0] = 65.0, t0
    r_hot = 2.0 * (1 + COPPER_ALPHA_PER_K * 45.0) / (1 + COPPER_ALPHA_PER_K * 5.0)
    rec, out = _fire(drv, 0, t0, 60_000, 1.5)
    L = world.coils[0].inductance
    i_ss = 1.5 if not want_limited else supply_v / r_hot
    assert rec["voltage_limited"] is want_limited
    assert rec["resistance_ohm"] == pytest.approx(r_hot, rel=1e-12)
    for dt in (50, 200, 600, 2_000, 59_000):
        want = i_ss * (1 - math.exp(-dt * 1e-6 * r_hot / L))
        assert world.currents[0].current_at(t0 + dt) == pytest.approx(want, rel=1e-9)
    assert out[0].current_ma * 1e-3 == pytest.approx(i_ss, abs=1e-3)      # reported within its 1 mA LSB
    if not want_limited:                                   # cold, the same pulse rises more slowly
        drv2, world2 = _driver(NO_ERRORS, supply_v)
        _fire(drv2, 0, t0, 60_000, 1.5)
        assert world2.currents[0].current_at(t0 + 200) < world.currents[0].current_at(t0 + 200) - 5e-3


def test_winding_temperature_follows_the_first_order_thermal_ode():
    """500 pulses of 1.5 A, 60 ms every 600 ms: the winding temperature after each pulse equals scipy's
    integration of C T' = u(t) I^2 R(T) - (T - T_a)/R_th (R(T) copper, R_th 20 K/W, tau 120 s) to 1e-6 K;
    at the end it is the duty-averaged first-order closed form's 8.5 K above ambient (to 0.05 K), 0.3 K more
    than with a constant resistance: catches the heating
    with the cold resistance, a wrong thermal time constant, or cooling left out between pulses."""
    drv, world = _driver(NO_ERRORS)
    lim = DriverLimits()
    C_th = lim.thermal_tau_s / lim.thermal_r_k_per_w
    r_a, amb = world.coils[0].resistance, lim.ambient_c

    def rhs(on):
        def f(t, T):
            r = r_a * (1 + COPPER_ALPHA_PER_K * (T - 20.0)) / (1 + COPPER_ALPHA_PER_K * (amb - 20.0))
            return [((1.5**2 * r if on else 0.0) - (T[0] - amb) / lim.thermal_r_k_per_w) / C_th]
        return f

    T = amb
    got, want = [], []
    for k in range(500):
        t0 = 1_000_000 + k * 600_000
        _fire(drv, 0, t0, 60_000, 1.5, pulse_id=k % 200)
        if k:
            T = integrate.solve_ivp(rhs(False), (0.0, 0.54), [T], rtol=1e-12, atol=1e-12).y[0, -1]
        T = integrate.solve_ivp(rhs(True), (0.0, 0.06), [T], rtol=1e-12, atol=1e-12).y[0, -1]
        got.append(drv.temp_c[0])
        want.append(T)
    np.testing.assert_allclose(got, want, atol=1e-6)
    # the duty-averaged closed form: T_a + D I^2 R_a R_th (1 - exp(-t/tau')) / (1 - D I^2 R_a k R_th),
    # tau' = tau / (1 - D I^2 R_a k R_th), within the 0.05 K a pulse heats the winding
    k = COPPER_ALPHA_PER_K / (1 + COPPER_ALPHA_PER_K * (amb - 20.0))
    gd = 0.1 * 1.5**2 * r_a * k * lim.thermal_r_k_per_w
    closed = 0.1 * 1.5**2 * r_a * lim.thermal_r_k_per_w / (1 - gd) * (1 - math.exp(-300.0 * (1 - gd) / lim.thermal_tau_s))
    assert got[-1] - amb == pytest.approx(closed, abs=0.05)
    const = 1.5**2 * r_a * 0.1 * lim.thermal_r_k_per_w * (1 - math.exp(-300.0 / lim.thermal_tau_s))
    assert got[-1] - amb - const > 0.2


def test_regulation_error_and_what_coil_status_shows():
    """2000 pulses at 1.5 A: the true current's relative error has the mean -g (the coil's static sense
    gain error, |g| <= 0.3 %) and the per-pulse spread sqrt(0.1 %^2 + (1 mA / 1.5 A)^2) (99.9 % chi-square
    band of the sample variance); COIL_STATUS reports (1 + g) times the true current at the end (the
    static error hidden, the pulse's error and ripple shown; to the 1 mA LSB); the seed fixes every draw;
    the ripple is the filtered bridge's, V D (1 - D) / (L f) (f_c / f)^2 / 2, D = I R / V: catches a
    gain error applied with the wrong sign, shown in the report, or drawn anew per pulse, or a
    one-sided offset (a sign taken with copysign)."""
    from scipy import stats

    acc = DriverAccuracy()
    drv, world = _driver(acc, seed=11)
    g = drv.gain_error[0]
    assert 0 < abs(g) <= 3e-3
    rel, rep = [], []
    for k in range(2000):
        t0 = 1_000_000 + k * 100_000
        drv.temp_c[0], drv._temp_t[0] = 25.0, t0          # hold the winding at ambient
        rec, out = _fire(drv, 0, t0, 60_000, 1.5, pulse_id=k % 200)
        rel.append(rec["current_a"] / 1.5 - 1.0)
        cur = world.currents[0]
        t_m = t0 + 60_000 - 1
        rep.append(out[0].current_ma * 1e-3 - (1 + g) * (cur.current_at(t_m) + cur.ripple_at(t_m)))
    rel = np.array(rel)
    sd = math.hypot(1e-3, 1e-3 / 1.5) / (1 + g)
    assert abs(rel.mean() + g) < 4 * sd / math.sqrt(rel.size)
    s2 = rel.var(ddof=1) / sd**2 * (rel.size - 1)
    assert stats.chi2.ppf(0.0005, rel.size - 1) < s2 < stats.chi2.ppf(0.9995, rel.size - 1)
    assert np.max(np.abs(rep)) <= 0.5e-3 + 1e-9
    drv2, _ = _driver(acc, seed=11)
    assert drv2.gain_error == drv.gain_error
    L, R = world.coils[0].inductance, world.coils[0].resistance
    d = 1.5 * R / 6.0
    amp = 0.5 * 6.0 * d * (1 - d) / (L * 20e3) * (2e3 / 20e3) ** 2
    cur = world.currents[0]
    t0 = 1_000_000 + 1999 * 100_000
    rip = np.array([cur.ripple_at(t0 + 30_000 + dt) for dt in range(50)])   # one 20 kHz period
    assert rip.max() == pytest.approx(amp, rel=2e-3) and rip.min() == pytest.approx(-amp, rel=2e-3)
    assert world.flat_start_us(0, t0, t0 + 60_000) < t0 + 3_000            # the ground truth ignores it
