"""MMC5983MA profile: data-sheet figures, filter response, noise, quantisation, range."""
from __future__ import annotations

import numpy as np
import pytest

from coiltrack.hil.magnetometers import FastMagProfile


def test_datasheet_figures():
    """BW = 11 at 1 kHz: 0.5 ms measurement, 1.2 mG rms, 16384 counts/G, +-8 G; rates beyond the table refused."""
    m = FastMagProfile.mmc5983ma()
    assert (m.rate_hz, m.integration_s, m.noise_rms_t) == (1000.0, 0.5e-3, 1.2e-7)
    assert m.lsb_t == pytest.approx(6.1035e-9, rel=1e-4) and m.range_t == 8e-4
    assert FastMagProfile.mmc5983ma(bw=0, rate_hz=50.0).noise_rms_t == pytest.approx(0.4e-7)
    with pytest.raises(ValueError, match="rate_hz"):
        FastMagProfile.mmc5983ma(bw=0, rate_hz=1000.0)
    with pytest.raises(ValueError, match="bw"):
        FastMagProfile.mmc5983ma(bw=4)


def test_filter_response_matches_sampled_sinusoid():
    """A noiseless sinusoid through filtered(): output phasor / input phasor = H(f) = sinc(fT) e^{-i pi f T}
    (1e-9); |H| at the -3 dB point 0.443/T and 0 at 1/T; the delay is T/2 (phase lag, not lead)."""
    m = FastMagProfile.mmc5983ma()
    T = m.integration_s
    for f in (37.0, 240.0, 470.0):
        w = 2 * np.pi * f
        t = m.sample_times(200, 0.01)
        out = m.filtered(lambda s: np.column_stack([np.cos(w * s), np.sin(w * s), np.zeros_like(s)]), t)
        ref = m.response(f) * np.exp(1j * w * t)
        np.testing.assert_allclose(out[:, 0], ref.real, atol=1e-9)
        np.testing.assert_allclose(out[:, 1], ref.imag, atol=1e-9)   # sin = Re[-i e^{iwt}]
    assert abs(m.response(0.4429 / T)) == pytest.approx(2 ** -0.5, abs=1e-3)
    assert abs(m.response(1.0 / T)) < 1e-12
    assert np.angle(m.response(100.0)) == pytest.approx(-np.pi * 100.0 * T, rel=1e-12)


def test_noise_quantisation_and_range():
    """Static field: sample std = rms noise (5 %, 3000 samples x 3 axes), mean = field (4 sigma/sqrt n),
    counts are integers around 131072; beyond +-8 G the output clips and the sample is flagged."""
    m = FastMagProfile.mmc5983ma()
    B = np.array([20e-6, -3e-6, -45e-6])
    t = m.sample_times(3000)
    counts, sat = m.sample(lambda s: np.tile(B, (s.size, 1)), t, np.random.default_rng(11))
    assert counts.dtype == np.int64 and not sat.any()
    err = m.to_tesla(counts) - B
    assert np.std(err) == pytest.approx(m.noise_rms_t, rel=0.05)
    assert np.all(np.abs(err.mean(axis=0)) < 4 * m.noise_rms_t / np.sqrt(t.size))
    big = np.array([9e-4, 0.0, -9e-4])
    counts, sat = m.sample(lambda s: np.tile(big, (s.size, 1)), t[:5], np.random.default_rng(1))
    assert sat.all() and np.all(counts[:, 0] == 262143) and np.all(counts[:, 2] == 0)
    a, b = m.sample(lambda s: np.tile(B, (s.size, 1)), t[:50], np.random.default_rng(5))
    c, d = m.sample(lambda s: np.tile(B, (s.size, 1)), t[:50], np.random.default_rng(5))
    assert np.array_equal(a, c)                              # seeded: reproducible
