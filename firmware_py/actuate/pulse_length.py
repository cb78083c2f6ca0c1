"""Pulse lengths of the single-coil mode, and what a window of each length yields.

The pulse-window extraction (``coiltrack.firmware.measure.pulse``) uses the
magnetometer samples in ``[start + settle_us, end - guard_us]`` that are
neither the first nor the last sample inside ``[start, end]`` (Schepers &
Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt`` sec. 3.1: "all samples except
the first and the last of each pulse"), and the quiet samples in
``[start - baseline_us, start - guard_us]`` and ``[end + fall_us, end + fall_us
+ baseline_us]``; an amplitude component then has the variance
``sigma^2 (1/n_u + 1/n_b)`` (Schepers sec. 3.1, ``sigma/sqrt(n)``).

A pulse costs ``I^2 R L`` joules and brings ``I^2 |h|^2 / (sigma^2 (1/n_u + 1/n_b))``
of information (eq 4, before the model error saturates it), so the information
per joule of a length ``L`` is ``1 / (L (1/n_u + 1/n_b))``. With the samples at an
arbitrary phase, a 60 ms pulse at 100 Hz keeps 4 samples and a 50 ms one 3:
about the same information per joule. The window wastes least when a sample
falls just after the start edge (inside the settle time, where it would not be
used anyway, and counted as the first) and another just before the end edge
(inside the guard, the last): a pulse of ``m`` sample periods plus those two
margins keeps ``m - 1`` samples, so ``L = a + m T + b`` instead of ``(m + 1) T``.
:class:`PulseLengths` lists the lengths the policy may choose (``pulse_length =
"chosen"``), each with its expected amplitude variance and measurement time,
every one giving the extraction at least ``min_pulse_samples`` used samples, and
aligns a start to the sensor's sample clock (:meth:`PulseLengths.align`). With
``pulse_length = "fixed"`` there is one length, ``adaptive_pulse_us`` (or
``pulse_us``), at whatever phase.
"""
from __future__ import annotations

import math

__all__ = ["window_samples", "fixed_amplitude_variance", "PulseLengths"]


def window_samples(length_us: int, phase_us: float, period_us: float, settle_us: int, guard_us: int,
                   fall_us: int, baseline_us: int) -> tuple[int, int]:
    """``(n_used, n_base)`` of a pulse ``[0, length_us]`` whose magnetometer samples are at
    ``phase_us + k period_us`` (any integer ``k``), by the extraction's rules (module
    docstring)."""
    k0 = math.floor((-baseline_us - phase_us) / period_us) - 1
    k1 = math.ceil((length_us + fall_us + baseline_us - phase_us) / period_us) + 1
    inside = []
    n_base = 0
    for k in range(k0, k1 + 1):
        t = phase_us + k * period_us
        if 0.0 <= t <= length_us:
            inside.append(t)
        elif -baseline_us <= t <= -guard_us or length_us + fall_us <= t <= length_us + fall_us + baseline_us:
            n_base += 1
    n_used = 0
    for i, t in enumerate(inside):
        if 0 < i < len(inside) - 1 and settle_us <= t <= length_us - guard_us:
            n_used += 1
    return n_used, n_base


def fixed_amplitude_variance(cfg, pulse_us: int) -> float:
    """The variance the single-coil mode has always assumed for a ``pulse_us`` pulse at an
    arbitrary phase (T^2): ``n_u = (pulse - settle - guard) / T - 1`` (the first and last
    samples), ``n_b = 2 baseline / T``."""
    per = 1e6 / cfg.pulse.mag_rate_hz
    n_used = max(1, int((pulse_us - cfg.pulse.settle_us - cfg.pulse.guard_us) / per) - 1)
    n_base = max(2, 2 * int(cfg.pulse.baseline_us / per))
    return cfg.pulse.mag_sigma_t ** 2 * (1.0 / n_used + 1.0 / n_base)


class PulseLengths:
    """The pulse lengths a policy may choose, shortest first.

    ``lengths_us``, ``var_amp`` (expected variance of one amplitude component, T^2) and
    ``mid_us`` (the mean time of the used samples after the start edge), one entry per
    length; ``aligned``: whether starts are put on the sample clock (:meth:`align`).
    """

    def __init__(self, lengths_us, var_amp, mid_us, aligned: bool, lead_in_us: float, period_us: float):
        self.lengths_us = tuple(int(x) for x in lengths_us)
        self.var_amp = tuple(float(x) for x in var_amp)
        self.mid_us = tuple(int(x) for x in mid_us)
        self.n = len(self.lengths_us)
        self.aligned = bool(aligned)
        self.lead_in_us = float(lead_in_us)
        self.period_us = float(period_us)

    @classmethod
    def fixed(cls, cfg, pulse_us: int) -> "PulseLengths":
        """One length at an arbitrary phase (``pulse_length = "fixed"``)."""
        return cls((pulse_us,), (fixed_amplitude_variance(cfg, pulse_us),),
                   ((cfg.pulse.settle_us + pulse_us - cfg.pulse.guard_us) // 2,), False, 0.0, 1e6 / cfg.pulse.mag_rate_hz)

    @classmethod
    def chosen(cls, cfg, max_us: int) -> "PulseLengths":
        """Lengths ``a + m T + b`` (``a`` = half the settle time: a sample there is not used
        and is the first; ``b`` = half the guard: the last) keeping ``m - 1`` samples, from
        ``min_pulse_samples`` used samples up to the longest not above ``max_us`` (at least
        one): each with the variance and mid time its window gives at that phase."""
        per = 1e6 / cfg.pulse.mag_rate_hz
        a = 0.5 * cfg.pulse.settle_us
        b = 0.5 * cfg.pulse.guard_us
        lengths, var, mid = [], [], []
        m = cfg.pulse.min_pulse_samples + 1
        while True:
            length = int(math.ceil(a + m * per + b))
            if lengths and length > max_us:
                break
            n_u, n_b = window_samples(length, a, per, cfg.pulse.settle_us, cfg.pulse.guard_us, cfg.pulse.fall_us, cfg.pulse.baseline_us)
            lengths.append(length)
            var.append(cfg.pulse.mag_sigma_t ** 2 * (1.0 / max(n_u, 1) + 1.0 / max(n_b, 1)))
            mid.append(int(round(a + 0.5 * m * per)))          # samples a + T ... a + (m - 1) T
            m += 1
        return cls(lengths, var, mid, True, a, per)

    def longest(self) -> int:
        return self.lengths_us[-1]

    def index_of(self, length_us: int) -> int:
        """The entry nearest a pulse of ``length_us`` (edges as the driver reported them)."""
        best, k = math.inf, 0
        for i in range(self.n):
            d = abs(self.lengths_us[i] - length_us)
            if d < best:
                best, k = d, i
        return k

    def align(self, start_us: int, sample_t_us: int) -> int:
        """The earliest start at or after ``start_us`` with a magnetometer sample
        ``lead_in_us`` after it, the samples being at ``sample_t_us + k T``."""
        if not self.aligned:
            return start_us
        per = self.period_us
        x = (start_us + self.lead_in_us - sample_t_us) / per
        k = math.ceil(x - 1e-9)
        return int(round(sample_t_us + k * per - self.lead_in_us))
