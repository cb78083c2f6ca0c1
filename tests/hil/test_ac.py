"""AC coil driver: L/R amplitude and phase, limits, both schemes, and a two-coil
frequency-division drive read by the MMC5983MA profile and demodulated here
with a plain least-squares fit (no firmware code)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from coiltrack.hil import ac
from coiltrack.hil import physics as ph
from coiltrack.hil.magnetometers import FastMagProfile

SRC = ph.thesis_source(quadrature="gauss")      # R = 2 ohm, L ~ 0.66 mH: tau ~ 0.33 ms


def _fit(t, y, freqs):
    """Least squares y ~ c0 + sum_k Re[P_k e^{i w_k t}]: returns the phasors P_k (per column of y)."""
    cols = [np.ones_like(t)]
    for f in freqs:
        w = 2 * np.pi * f
        cols += [np.cos(w * t), -np.sin(w * t)]
    coef, *_ = np.linalg.lstsq(np.column_stack(cols), y, rcond=None)
    return [coef[1 + 2 * k] + 1j * coef[2 + 2 * k] for k in range(len(freqs))]


def test_phase_and_amplitude_follow_series_lr():
    """Current phasor = V/(R + i w L): |I| = V/sqrt(R^2 + w^2 L^2), lag atan(w L/R) (from the time
    series after 40 tau, fitted over 5 periods: rel 1e-9, 1e-9 rad)."""
    coil = SRC[0]
    R, L = coil.resistance, coil.inductance
    for f in (20.0, 300.0, 1500.0):
        drv = ac.ACCoilDriver(SRC, [ac.ACRequest(0, f, 2.0, phase_rad=0.3)], current_noise_a=0.0)
        assert drv.drives[0].flags == 0
        t = 40 * coil.tau_s + np.linspace(0.0, 5.0 / f, 500, endpoint=False)
        (P,) = _fit(t, drv.current_at(t)[0], [f])
        w = 2 * np.pi * f
        assert abs(P) == pytest.approx(2.0 / math.hypot(R, w * L), rel=1e-9)
        assert np.angle(P) == pytest.approx(0.3 - math.atan(w * L / R), abs=1e-9)
        assert np.all(drv.current_at(t)[1:] == 0.0)      # undriven coils stay at zero


def test_switch_on_is_continuous_and_settles_with_tau():
    """From rest the current starts at 0 (no step through an inductor) and the transient decays as exp(-t/tau)."""
    coil = SRC[1]
    drv = ac.ACCoilDriver(SRC, [ac.ACRequest(1, 50.0, 3.0)], start_s=0.01, current_noise_a=0.0)
    I = drv.drives[1].current
    assert drv.coil_current(1, np.array([0.0, 0.01]))[0] == 0.0
    assert abs(drv.coil_current(1, 0.01 + 1e-9)) < 1e-5 * abs(I)
    t = 0.01 + np.array([1.0, 3.0]) * coil.tau_s
    steady = np.real(I * np.exp(2j * np.pi * 50.0 * t))
    transient = drv.coil_current(1, t) - steady
    assert transient[1] / transient[0] == pytest.approx(math.exp(-2.0), rel=1e-9)


def test_limits_clip_and_flag():
    """Each limit clips its own request and sets its own flag; a request within every limit is untouched."""
    coil, lim = SRC[0], ac.ACLimits(max_voltage_v=12.0, max_current_a=2.0, max_power_w=3.0,
                                    min_freq_hz=5.0, max_freq_hz=2000.0)
    ok = ac.execute_request(ac.ACRequest(0, 100.0, 2.0), coil, lim)
    assert ok.flags == 0 and ok.voltage == 2.0
    hi_f = ac.execute_request(ac.ACRequest(0, 5000.0, 1.0), coil, lim)
    assert hi_f.flags == ac.FLAG_FREQUENCY and hi_f.freq_hz == 2000.0
    assert ac.execute_request(ac.ACRequest(0, 1.0, 1.0), coil, lim).freq_hz == 5.0
    v = ac.execute_request(ac.ACRequest(0, 1500.0, 50.0), coil, lim)   # |Z| ~ 6.5 ohm: 12 V, then 3.4 W
    assert v.flags == ac.FLAG_VOLTAGE | ac.FLAG_POWER and abs(v.voltage) < 12.0
    v = ac.execute_request(ac.ACRequest(0, 1500.0, 50.0), coil, ac.ACLimits(max_power_w=10.0))
    assert v.flags == ac.FLAG_VOLTAGE and abs(v.voltage) == 12.0
    i = ac.execute_request(ac.ACRequest(0, 10.0, 11.0), coil, ac.ACLimits(max_power_w=10.0))  # 5.5 A asked
    assert i.flags == ac.FLAG_CURRENT and abs(i.current) == pytest.approx(2.0, rel=1e-12)
    p = ac.execute_request(ac.ACRequest(0, 10.0, 11.0), coil, ac.ACLimits(max_power_w=1.0))
    assert p.flags == ac.FLAG_CURRENT | ac.FLAG_POWER
    assert abs(p.current) ** 2 * coil.resistance / 2 == pytest.approx(1.0, rel=1e-12)
    tdm = ac.execute_request(ac.ACRequest(0, 10.0, 11.0), coil, ac.ACLimits(max_power_w=1.0), duty=1 / 3)
    assert abs(tdm.current) == pytest.approx(math.sqrt(3.0) * abs(p.current), rel=1e-12)  # power is a mean
    with pytest.raises(ValueError, match="amplitude_v"):
        ac.execute_request(ac.ACRequest(0, 10.0, -1.0), coil, lim)
    with pytest.raises(ValueError, match="coil 3"):
        ac.ACCoilDriver(SRC, [ac.ACRequest(3, 100.0, 1.0)])


def test_time_multiplexing_slots():
    """One frequency, coil k on in slot k: off outside its slot (after the L/R tail), the L/R phasor inside."""
    with pytest.raises(ValueError, match="one frequency"):
        ac.ACCoilDriver(SRC, [ac.ACRequest(0, 100.0, 1.0), ac.ACRequest(1, 120.0, 1.0)], slot_s=0.01)
    with pytest.raises(ValueError, match="slot_s"):
        ac.ACCoilDriver(SRC, [ac.ACRequest(0, 100.0, 1.0)], slot_s=1e-3)   # tail e^{-2 S/tau} too large
    f, S = 200.0, 0.02
    drv = ac.ACCoilDriver(SRC, [ac.ACRequest(k, f, 1.0) for k in range(3)], slot_s=S, current_noise_a=0.0)
    tau = SRC[0].tau_s
    t = np.arange(0.0, 0.12, 1e-5)
    I = drv.current_at(t)
    slot = np.floor(t / S).astype(int) % 3
    settled = (t % S) > 25 * tau                     # 25 tau after any slot edge
    for k in range(3):
        assert np.max(np.abs(I[k][(slot != k) & settled])) < 1e-9
        inside = (slot == k) & settled
        steady = np.real(drv.drives[k].current * np.exp(2j * np.pi * f * t[inside]))
        np.testing.assert_allclose(I[k][inside], steady, atol=1e-9)
        off = (k + 1) * S                            # free L/R decay after the slot
        i_off = drv.coil_current(k, off)
        assert abs(i_off) > 0.1
        assert drv.coil_current(k, off + tau) == pytest.approx(i_off * np.exp(-1.0), rel=1e-9)


def test_measured_current_noise():
    """Reported current = true current + white noise of the stated rms (sample std within 5 %)."""
    drv = ac.ACCoilDriver(SRC, [ac.ACRequest(0, 100.0, 1.0)], current_noise_a=2e-3)
    t = np.linspace(0.01, 0.2, 4000)
    err = drv.measured_current(t, np.random.default_rng(3))[0] - drv.current_at(t)[0]
    assert np.std(err) == pytest.approx(2e-3, rel=0.05)


def test_two_coil_frequency_division_demodulated():
    """Coils X and Y at 110 and 170 Hz, sensor at a fixed point, MMC5983MA profile at 1 kHz, 0.5 s.

    The least-squares phasor of each frequency, divided by the coil current
    phasor and by the magnetometer's response H(f), is the coil's field per
    ampere: compared with magpylib's Collection.getB for 1 A. Bound per axis and
    quadrature: 5 sigma with sigma = sigma_noise sqrt(2/N) / (|H| |I|), sigma_noise
    the profile's rms noise with the quantisation step added (LSB^2/12).
    """
    mag = FastMagProfile.mmc5983ma()
    freqs = (110.0, 170.0)
    drv = ac.ACCoilDriver(SRC, [ac.ACRequest(0, freqs[0], 2.0, 0.4), ac.ACRequest(1, freqs[1], 2.0, -1.0)],
                          current_noise_a=0.0)
    p = np.array([0.18, 0.12, 0.08])
    earth = ph.EARTH_FIELD_T
    t = mag.sample_times(500, start_s=0.05)
    counts, sat = mag.sample(lambda s: ac.field_at(SRC, drv, p, s) + earth, t, np.random.default_rng(7))
    assert not sat.any()
    phasors = _fit(t, mag.to_tesla(counts), freqs)
    sigma_n = math.sqrt(mag.noise_rms_t**2 + mag.lsb_t**2 / 12.0)
    for k, f in enumerate(freqs):
        gain = mag.response(f) * drv.drives[k].current
        per_amp = phasors[k] / gain
        ref = SRC[k].unit_field_magpylib(p[None, :])[0]
        bound = 5.0 * sigma_n * math.sqrt(2.0 / t.size) / abs(gain)
        assert np.max(np.abs(per_amp.real - ref)) < bound
        assert np.max(np.abs(per_amp.imag)) < bound
        assert bound < 0.01 * np.linalg.norm(ref)      # the check is sharp: 1 % of the field


def test_field_at_moving_points_and_shape_check():
    """One point per time gives, at each time, the fixed-point field there (rel 1e-12); a wrong shape is refused."""
    drv = ac.ACCoilDriver(SRC, [ac.ACRequest(k, 90.0 + 40 * k, 1.5) for k in range(3)])
    t = np.linspace(0.01, 0.02, 4)
    pts = np.array([[0.2, 0.0, 0.05], [0.1, 0.25, 0.0], [-0.15, 0.1, 0.2], [0.0, -0.3, -0.1]])
    B = ac.field_at(SRC, drv, pts, t)
    for n in range(4):
        np.testing.assert_allclose(B[n], ac.field_at(SRC, drv, pts[n], t[n:n + 1])[0], rtol=1e-12)
    with pytest.raises(ValueError, match="points"):
        ac.field_at(SRC, drv, pts[:3], t)
