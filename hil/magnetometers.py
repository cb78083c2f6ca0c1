"""Fast magnetometer profile from a real part's data sheet: MEMSIC MMC5983MA.

Data sheet: MEMSIC MMC5983MA Rev A (formal release 4/3/2019), "±8 Gauss, High
Performance 3-axis Magnetic Sensor": specification table and register
"Internal Control 1/2". Figures used (1 G = 1e-4 T):

======================  ===========================================  ==================
setting BW[1:0]          00      01      10      11
measurement time         8 ms    4 ms    2 ms    0.5 ms              (Internal Control 1)
bandwidth                100 Hz  200 Hz  400 Hz  800 Hz              (Internal Control 1)
total RMS noise          0.4 mG  0.6 mG  0.8 mG  1.2 mG              (specifications)
max output data rate     50 Hz   100 Hz  225 Hz  580 Hz; 1000 Hz with CM_Freq = 111 (BW = 11)
======================  ===========================================  ==================

Field range ±8 G per axis; output 18 bits, 16384 counts/G (0.0625 mG = 6.1 nT
per count), null field at 131072 counts (unsigned).

Internal filter: the data sheet says only that the BW bits "adjust the length
of the decimation filter" and "control the duration of each measurement". The
model is the simplest filter with that property, an average over the
measurement time ``T`` ending at the sample instant (X, Y, Z in parallel):

    H(f) = sinc(f T) exp(-i pi f T)        (sinc(u) = sin(pi u)/(pi u)),

a delay of ``T/2`` and a droop whose -3 dB point is ``0.443/T`` (886 Hz for
``T`` = 0.5 ms, against the stated 800 Hz bandwidth). Noise: white, Gaussian,
the data sheet's total RMS figure on each axis, independent between samples;
then quantisation to counts and clipping at the range (a saturated sample is
flagged). Set/reset flipping and offsets are :class:`hil.nodes.MagSpec`'s
business and are not modelled here.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["FastMagProfile", "MMC5983MA_SETTINGS"]

GAUSS_T = 1e-4

#: BW[1:0] -> (measurement time s, stated bandwidth Hz, total RMS noise T, max output data rate Hz)
MMC5983MA_SETTINGS: dict[int, tuple[float, float, float, float]] = {
    0b00: (8e-3, 100.0, 0.4e-3 * GAUSS_T, 50.0),
    0b01: (4e-3, 200.0, 0.6e-3 * GAUSS_T, 100.0),
    0b10: (2e-3, 400.0, 0.8e-3 * GAUSS_T, 225.0),
    0b11: (0.5e-3, 800.0, 1.2e-3 * GAUSS_T, 1000.0),
}

_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(8)


@dataclass(frozen=True)
class FastMagProfile:
    """A magnetometer that averages the field over ``integration_s`` and outputs quantised counts."""
    name: str
    rate_hz: float
    integration_s: float
    bandwidth_hz: float
    noise_rms_t: float
    lsb_t: float
    range_t: float
    null_counts: int

    @classmethod
    def mmc5983ma(cls, bw: int = 0b11, rate_hz: float = 1000.0) -> "FastMagProfile":
        """The MMC5983MA at setting ``bw`` (0..3) and output data rate ``rate_hz`` (continuous mode)."""
        if bw not in MMC5983MA_SETTINGS:
            raise ValueError(f"bw: need one of {sorted(MMC5983MA_SETTINGS)}, got {bw}")
        t_meas, band, noise, max_rate = MMC5983MA_SETTINGS[bw]
        if not 0.0 < rate_hz <= max_rate:
            raise ValueError(f"rate_hz: need 0 < rate_hz <= {max_rate} Hz at bw = {bw}, got {rate_hz}")
        return cls("MMC5983MA", float(rate_hz), t_meas, band, noise, GAUSS_T / 16384.0, 8.0 * GAUSS_T, 131072)

    @property
    def noise_density(self) -> float:
        """Equivalent white-noise density (T/sqrt(Hz)) over the sample rate's Nyquist band."""
        return self.noise_rms_t / np.sqrt(self.rate_hz / 2.0)

    def response(self, f_hz):
        """Complex amplitude and phase of the internal filter at ``f_hz`` (output phasor / input phasor)."""
        u = np.asarray(f_hz, dtype=float) * self.integration_s
        h = np.sinc(u) * np.exp(-1j * np.pi * u)
        return complex(h) if h.ndim == 0 else h

    def sample_times(self, n: int, start_s: float = 0.0) -> np.ndarray:
        """``n`` sample instants (s) at the output data rate from ``start_s``."""
        return start_s + np.arange(n) / self.rate_hz

    def filtered(self, field: Callable[[np.ndarray], np.ndarray], t_s: np.ndarray) -> np.ndarray:
        """The field averaged over ``[t - T, t]`` at each sample time (8-point Gauss-Legendre), (n, 3) T.

        ``field(t)`` takes times (s, shape (m,)) and returns (m, 3) tesla.
        """
        t = np.asarray(t_s, dtype=float)
        half = 0.5 * self.integration_s
        nodes = (t[:, None] - half + half * _NODES[None, :]).ravel()
        B = np.asarray(field(nodes), dtype=float).reshape(t.size, _NODES.size, 3)
        return 0.5 * np.einsum("j,nji->ni", _WEIGHTS, B)

    def sample(self, field: Callable[[np.ndarray], np.ndarray], t_s: np.ndarray,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """What the part outputs at ``t_s``: ``(counts (n, 3) int, saturated (n,) bool)``.

        Filtered field plus white noise (``noise_rms_t`` per axis), rounded to
        counts around ``null_counts`` and clipped to the range.
        """
        B = self.filtered(field, t_s) + rng.normal(0.0, self.noise_rms_t, (np.size(t_s), 3))
        full = self.range_t / self.lsb_t
        steps = np.round(B / self.lsb_t)
        # the 18-bit output spans -full .. full - 1 around the null: a step outside it is clipped
        saturated = np.any((steps > full - 1) | (steps < -full), axis=1)
        counts = np.clip(steps, -full, full - 1) + self.null_counts
        return counts.astype(np.int64), saturated

    def to_tesla(self, counts: np.ndarray) -> np.ndarray:
        """Counts back to tesla."""
        return (np.asarray(counts, dtype=float) - self.null_counts) * self.lsb_t
