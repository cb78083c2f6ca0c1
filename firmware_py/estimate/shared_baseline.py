"""Pulse amplitudes that share baseline samples: the variance each must carry.

A pulse's amplitude is its in-pulse mean minus the earth-field baseline fitted
to the quiet samples before and after it (``coiltrack.firmware.measure.pulse``;
thesis ``seeds/002_cd7f1fdb7fc67471.txt`` sec. 5.4; Schepers & Veltink 2010,
``seeds/000_e46ec0e8bf7ea271.txt`` sec. 3.1, ``sigma/sqrt(n)``), with the variance
``sigma^2 (1/n_u + 1/n_b)`` per component. When the next pulse starts less than
two baselines after this one ends (the single-coil mode fires back to back,
``fall + baseline + guard`` apart), its *before* samples are this pulse's
*after* samples: the two amplitudes carry the same baseline error, with the
same sign. The filter (Schepers eq 4) takes each as independent and gains
information the pulses do not hold: two amplitudes sharing one side have
correlation ``(1/(2 n_b)) / (1/n_u + 1/n_b)``, about 0.22 for a 60 ms pulse at
100 Hz (5.5 used samples, 7 baseline samples), and a chain of them averages
like pulses of variance ``sigma^2 (1/n_u + 2/n_b)``, 44 % more than each claims.

The bound. With the errors ``e_k = a_k + b`` and ``e_{k+1} = c + b`` (``b`` the
shared samples' part, covariance ``B``), ``(x + y)(x + y)^T <= 2 x x^T + 2 y y^T``
gives, in the Loewner order,

    Cov[e_k, e_{k+1}] = [[A + B, B], [B, C + B]] <= [[A + 2B, 0], [0, C + 2B]],

so updates that each count the shared part twice, taken as independent, leave a
covariance no smaller than the error's (the Kalman filter with a measurement
covariance bounding the true one bounds its error covariance). Both pulses of a
pair must count it: the later one alone cannot (``[[0, -B], [-B, B]]`` is not
positive semi-definite). A pulse's after side is therefore counted as shared
when the next pulse is already commanded and its before samples overlap it, or,
when none is yet, when the earliest pulse that may still be commanded
(``earliest_next_us``) would overlap it; the before side when the previous
pulse's after samples overlap it.

The shared part. The baseline is a least-squares line predicted at the middle
of the used in-pulse samples; with the sides equal that point is the baseline
samples' mean time, every sample weighs ``1/n_b`` and one side contributes
``sigma^2 / (2 n_b)``; a fraction ``f`` of a side shared adds ``f sigma^2 /
(2 n_b)``. Both sides shared: ``sigma^2 (1/n_u + 2/n_b)``, the chain's variance.
"""
from __future__ import annotations

import numpy as np

__all__ = ["span_overlap", "next_start", "SharedBaselines"]


def span_overlap(a0: int, a1: int, b0: int, b1: int) -> float:
    """The fraction of ``[a0, a1]`` covered by ``[b0, b1]`` (0 for an empty ``[a0, a1]``)."""
    if a1 <= a0:
        return 0.0
    lo = a0 if a0 > b0 else b0
    hi = a1 if a1 < b1 else b1
    if hi <= lo:
        return 0.0
    return (hi - lo) / (a1 - a0)


def next_start(slots, sl) -> int:
    """The start of the earliest pulse in ``slots`` (active ``PulseSlot``s) after ``sl``'s, or -1."""
    best = -1
    for o in slots:
        if o.active and o is not sl and o.start > sl.start and (best < 0 or o.start < best):
            best = o.start
    return best


class SharedBaselines:
    """The sides of each closed pulse window shared with a neighbour, and the variance its
    amplitude then carries (module docstring).

    ``fall_us``, ``baseline_us``, ``guard_us``: the window's quiet spans (``[pulse]``: before
    ``[start - baseline, start - guard]``, after ``[end + fall, end + fall + baseline]``);
    ``sigma_t``: the magnetometer's per-sample noise std (T); ``period_us``: its sample period
    (the nominal ``n_b = 2 baseline / T`` of a decision's prediction, as
    ``actuate.pulse_length.fixed_amplitude_variance``); ``enabled``: False keeps the
    amplitudes' own variances (``[adaptive] baseline_sharing = "ignore"``).

    Windows are closed in the order of their pulses: :meth:`close` takes one (its edges, the
    start of the next pulse if one is commanded, else ``-1``, and the earliest start a pulse
    not yet commanded may have) and remembers its end for the next; :meth:`variance` then
    gives each sensor's amplitude variance for it (a buffer of this object, refilled per call).
    """

    def __init__(self, fall_us: int, baseline_us: int, guard_us: int, sigma_t: float, period_us: float,
                 enabled: bool = True):
        self.fall_us = int(fall_us)
        self.baseline_us = int(baseline_us)
        self.guard_us = int(guard_us)
        self.sigma2 = float(sigma_t) * float(sigma_t)
        self.enabled = bool(enabled)
        self.n_base = max(2, 2 * int(self.baseline_us / float(period_us)))
        self.prev_end = None          # the end of the pulse whose window was closed last
        self.shared = 0.0             # the window being closed: shared sides, 0..2 (before + after)
        self.var = np.zeros(3)

    def before_after(self, start: int, end: int, prev_end, next_start: int) -> tuple[float, float]:
        """Fractions of the before and after spans of the pulse ``[start, end]`` covered by
        the previous pulse's after span (``prev_end``: its end, or None) and the next pulse's
        before span (``next_start``: its start, or -1 for none)."""
        b0, b1 = start - self.baseline_us, start - self.guard_us
        a0, a1 = end + self.fall_us, end + self.fall_us + self.baseline_us
        fb = 0.0
        if prev_end is not None:
            fb = span_overlap(b0, b1, prev_end + self.fall_us, prev_end + self.fall_us + self.baseline_us)
        fa = 0.0
        if next_start >= 0:
            fa = span_overlap(a0, a1, next_start - self.baseline_us, next_start - self.guard_us)
        return fb, fa

    def close(self, start: int, end: int, next_start: int, earliest_next_us: int) -> float:
        """The window of the pulse ``[start, end]`` is being closed: ``next_start`` is the start
        of the next pulse if one is commanded (else -1; then a pulse starting at
        ``earliest_next_us`` may still follow, -1: none may). Sets and returns
        :attr:`shared` (before + after fractions)."""
        nxt = next_start if next_start >= 0 else earliest_next_us
        fb, fa = self.before_after(start, end, self.prev_end, nxt)
        self.prev_end = end
        self.shared = (fb + fa) if self.enabled else 0.0
        return self.shared

    def variance(self, amp_var, n_base: int):
        """``amp_var`` (3,) plus the shared sides' baseline variance counted once more,
        ``shared sigma^2 / (2 n_b)`` per component, into :attr:`var` (returned)."""
        v = self.var
        extra = 0.0
        if self.shared > 0.0 and n_base > 0:
            extra = self.shared * self.sigma2 / (2.0 * n_base)
        v[0] = float(amp_var[0]) + extra
        v[1] = float(amp_var[1]) + extra
        v[2] = float(amp_var[2]) + extra
        return v

    def predicted(self, var_amp: float, start: int, prev_end: int) -> float:
        """The variance a pulse starting at ``start`` will be taken with (a decision's
        prediction, nominal ``n_b``): its before side as the previous pulse (ending at
        ``prev_end``; 0 or less: none) leaves it, its after side shared (a pulse may follow
        back to back)."""
        if not self.enabled:
            return var_amp
        fb = 0.0
        if prev_end > 0:
            fb = span_overlap(start - self.baseline_us, start - self.guard_us, prev_end + self.fall_us,
                              prev_end + self.fall_us + self.baseline_us)
        return var_amp + (fb + 1.0) * self.sigma2 / (2.0 * self.n_base)

    def chained(self, var_amp: float) -> float:
        """The variance of a pulse in flight as a decision predicts it: both sides shared."""
        return var_amp + 2.0 * self.sigma2 / (2.0 * self.n_base) if self.enabled else var_amp
