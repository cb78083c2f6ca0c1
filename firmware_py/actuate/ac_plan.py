"""The AC frequency plan and its start-up check.

Frequency division (Raab et al. 1979, ``004_86267342cd7488ce.txt``: each coil
excited at its own frequency so that one sensor sample carries all of them;
the Anser EMT multiplexes eight coils this way) needs every coil frequency
separable from everything else the magnetometer samples:

* the earth field and the sensor's slow motion (DC and a ramp): a block of
  ``T_w`` holds at least one cycle of every coil, ``f T_w >= 1``;
* the other coils: ``|f_i - f_j| >= max(sep, 1 / T_w)`` (resolved within one
  demodulation block);
* the coils' harmonics ``m f_j`` (``m = 2..H``: driver non-linearity, a
  saturating core) and the mains ``m f_mains`` (``m = 1..M``; 50 / 60 Hz
  and their harmonics): at least ``sep`` from every coil frequency;
* the magnetometer's sampling: every frequency is compared after folding
  into ``[0, f_s / 2]`` (``f_s`` the output data rate), and the coils stay
  ``sep`` below the Nyquist frequency.

:func:`check_plan` returns the first violation as ``(key, message)`` (the
configuration refuses it with a ``ConfigError`` naming ``ac.key``) or None.
"""
from __future__ import annotations

import math

__all__ = ["fold", "check_plan"]


def fold(f_hz: float, fs_hz: float) -> float:
    """Apparent frequency (Hz, in ``[0, fs/2]``) of ``f_hz`` sampled at ``fs_hz``."""
    f = math.fmod(abs(f_hz), fs_hz)
    return fs_hz - f if f > 0.5 * fs_hz else f


def check_plan(freqs, n_coils: int, fs_hz: float, window_us: int, sep_hz: float, harmonics: int,
               mains_hz, mains_harmonics: int):
    """First violation of the frequency plan ``freqs`` (Hz, one per coil) as ``(key, message)``, else None."""
    freqs = tuple(freqs)
    if len(freqs) != n_coils:
        return "ac_freqs_hz", f"needs one frequency per coil ({n_coils}), got {len(freqs)}"
    tw = window_us * 1e-6
    nyq = 0.5 * fs_hz
    for i, f in enumerate(freqs):
        if not (isinstance(f, (int, float)) and math.isfinite(f) and f > 0):
            return "ac_freqs_hz", f"coil {i}: must be a positive frequency, got {f!r}"
        if f * tw < 1.0:
            return "ac_freqs_hz", (f"coil {i}: {f} Hz makes less than one cycle in ac_window_us={window_us} "
                                   f"(need >= {1.0 / tw:g} Hz to reject the earth field as DC)")
        if f > nyq - sep_hz:
            return "ac_freqs_hz", (f"coil {i}: {f} Hz is within {sep_hz:g} Hz of the magnetometer's Nyquist "
                                   f"frequency {nyq:g} Hz (mag_rate_hz={fs_hz:g})")
    resolve = max(sep_hz, 1.0 / tw)
    for i in range(n_coils):
        for j in range(i + 1, n_coils):
            if abs(freqs[i] - freqs[j]) < resolve:
                return "ac_freqs_hz", (f"coils {i} and {j}: {freqs[i]} and {freqs[j]} Hz are closer than "
                                       f"{resolve:g} Hz (ac_min_separation_hz, 1/ac_window_us)")
    for j, fj in enumerate(freqs):
        for m in range(2, harmonics + 1):
            h = fold(m * fj, fs_hz)
            for i, fi in enumerate(freqs):
                if abs(h - fi) < sep_hz:
                    return "ac_freqs_hz", (f"coil {j}'s harmonic {m} ({m * fj:g} Hz, seen at {h:g} Hz) is within "
                                           f"{sep_hz:g} Hz of coil {i} ({fi} Hz)")
    for fm in mains_hz:
        for m in range(1, mains_harmonics + 1):
            h = fold(m * fm, fs_hz)
            for i, fi in enumerate(freqs):
                if abs(h - fi) < sep_hz:
                    return "ac_freqs_hz", (f"coil {i} ({fi} Hz) is within {sep_hz:g} Hz of mains {fm:g} Hz "
                                           f"harmonic {m} ({m * fm:g} Hz, seen at {h:g} Hz)")
    return None
