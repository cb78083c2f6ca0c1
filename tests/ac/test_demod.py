"""Synchronous demodulation (``firmware_py/measure/demod.py``) against analytic signals.

The samples are made by the bench's magnetometer model (``hil.magnetometers.FastMagProfile``:
the field averaged over 0.5 ms by 8-point Gauss-Legendre quadrature, not the
firmware's closed-form ``sinc``), from carriers whose phasors are known, plus a
DC earth field and a ramp (a turning sensor) and seeded white noise. The
reference variance of each amplitude is numpy's least-squares covariance of
the same design (``hil.ac_nodes.ac_amplitude_sigma``).
"""
import math

import numpy as np
import pytest

from coiltrack.firmware.measure.demod import Demodulator
from coiltrack.hil.ac_nodes import ac_amplitude_sigma
from coiltrack.hil.magnetometers import FastMagProfile

FREQS = (215.0, 315.0, 465.0)
WINDOW_US, HOP_US = 18_000, 9_000
PROF = FastMagProfile.mmc5983ma(0b11, 1000.0)
SIGMA = PROF.noise_rms_t
REF_US = 1_234_567


def _field(t_s, amp, cur_phase, phasors, earth, ramp):
    """(m, 3) field: earth + ramp + sum_k Re[A_k e^{i phi_k} c_k e^{i w_k (t - ref)}] (c_k complex (3,))."""
    t = np.asarray(t_s)
    B = earth[None, :] + ramp[None, :] * (t - 2.0)[:, None]
    for k, f in enumerate(FREQS):
        rot = np.exp(1j * (2 * np.pi * f * (t - REF_US * 1e-6) + cur_phase[k]))
        B = B + np.real(amp[k] * phasors[k][None, :] * rot[:, None])
    return B


def _run(n_blocks, phasors, amp, cur_phase, noise, seed, earth=(20e-6, -5e-6, 42e-6), ramp=(3e-6, -2e-6, 1e-6)):
    """Demodulate ``n_blocks`` non-overlapping blocks; returns (S, Q, var) stacked per block."""
    rng = np.random.default_rng(seed)
    earth, ramp = np.array(earth), np.array(ramp)
    t0 = 2_000_000
    d = Demodulator(FREQS, WINDOW_US, HOP_US, SIGMA, 500)
    d.start(t0, REF_US, amp, cur_phase)
    n = int((n_blocks + 1) * WINDOW_US * 1e-3) + 4
    t_us = t0 + 7 + np.arange(n) * 1000 + rng.integers(-3, 4, n)        # 1 kHz with a little jitter
    B = PROF.filtered(lambda tt: _field(tt, amp, cur_phase, phasors, earth, ramp), t_us * 1e-6)
    B = B + rng.normal(0.0, noise, B.shape)
    out = []
    for i in range(n):
        k = d.push(int(t_us[i]), float(B[i, 0]), float(B[i, 1]), float(B[i, 2]), 0)
        if k >= 0 and d.finish(k) and k % 2 == 0:       # every other block: independent samples
            out.append((d.S.copy(), d.Q.copy(), d.var.copy(), d.block_mid(k)))
        if len(out) == n_blocks:
            break
    return out


def test_amplitude_phase_and_sign_without_noise():
    """In-phase and quadrature of each coil and axis from noise-free samples, to 2e-4 of the
    amplitude (the ramp's leak into the carriers is fitted away; the 0.5 ms averaging is
    corrected): catches a dropped magnetometer-response correction (a 2-9 % droop and 17-42 deg of
    phase), a wrong sign of the quadrature, a lost current phase, or the earth field left in."""
    phasors = [np.array([0.8, -0.3, 0.1]) * 1e-6 + 1j * np.array([0.02, 0.05, -0.04]) * 1e-6,
               np.array([-0.2, 0.6, 0.3]) * 1e-6 + 0j,
               np.array([0.1, 0.2, -0.9]) * 1e-6 - 1j * np.array([0.0, 0.1, 0.03]) * 1e-6]
    amp = np.array([1.5, 1.2, 0.9])
    cur_phase = np.array([0.3, -2.0, 1.1])
    out = _run(6, phasors, amp, cur_phase, 0.0, 1)
    want_S = np.stack([amp[k] * phasors[k].real for k in range(3)], axis=1)
    want_Q = np.stack([amp[k] * phasors[k].imag for k in range(3)], axis=1)
    for S, Q, _, _ in out:
        np.testing.assert_allclose(S, want_S, atol=2e-4 * np.abs(want_S).max())
        np.testing.assert_allclose(Q, want_Q, atol=2e-4 * np.abs(want_S).max())


def test_stated_variance_matches_the_scatter_and_the_reference():
    """Seeded Monte Carlo, 400 independent blocks: the stated variance equals numpy's least-squares
    covariance of the design (within 3 %: the jittered sample grid), and the scatter of the
    in-phase amplitudes about the truth agrees with it (each of the 9 elements' sample variance
    within the 99.9 % chi-square band of 400 samples, 0.79-1.24 of the stated one; the mean
    error within 3.3 standard errors): catches a wrong noise scaling, a dropped |H| in the variance,
    a variance taken from the wrong diagonal element, or a bias."""
    phasors = [np.array([0.8, -0.3, 0.1]) * 1e-6 + 0j, np.array([-0.2, 0.6, 0.3]) * 1e-6 + 0j,
               np.array([0.1, 0.2, -0.9]) * 1e-6 + 0j]
    amp = np.array([1.5, 1.5, 1.5])
    cur_phase = np.array([0.0, 0.7, -1.3])
    out = _run(400, phasors, amp, cur_phase, SIGMA, 7)
    assert len(out) == 400
    S = np.stack([o[0] for o in out])
    var = np.stack([o[2] for o in out])
    want = np.stack([amp[k] * phasors[k].real for k in range(3)], axis=1)
    ref_sd = ac_amplitude_sigma(FREQS, 1000.0, WINDOW_US * 1e-6, SIGMA, 0.5e-3)
    np.testing.assert_allclose(np.sqrt(var.mean(axis=0)), np.broadcast_to(ref_sd, (3, 3)), rtol=0.03)
    err = S - want
    ratio = err.var(axis=0, ddof=1) / var.mean(axis=0)
    assert np.all((ratio > 0.79) & (ratio < 1.24)), ratio
    assert np.all(np.abs(err.mean(axis=0)) < 3.3 * np.sqrt(var.mean(axis=0) / 400)), err.mean(axis=0)


def test_quadrature_of_a_lagging_response_is_negative_imaginary():
    """A conductor's field lags the current (phasor ``c (a - i b)``, ``b > 0``): the demodulated
    quadrature is ``-b`` times the current amplitude, the in-phase ``a``: catches a conjugated
    reference (which would report a lead)."""
    lag = 0.2
    phasors = [np.array([1.0, 0.0, 0.0]) * 1e-6 * np.exp(-1j * lag), np.array([0.0, 1.0, 0.0]) * 1e-6 + 0j,
               np.array([0.0, 0.0, 1.0]) * 1e-6 + 0j]
    out = _run(2, phasors, np.array([1.0, 1.0, 1.0]), np.zeros(3), 0.0, 3)
    S, Q, _, _ = out[0]
    assert S[0, 0] == pytest.approx(1e-6 * math.cos(lag), rel=1e-3)
    assert Q[0, 0] == pytest.approx(-1e-6 * math.sin(lag), rel=1e-3)
