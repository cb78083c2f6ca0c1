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

The shared part. The baseline is a least-squares line through the quiet samples
``t_j`` predicted at the used samples' mean time ``t_m``: sample ``j`` weighs
``w_j = 1/n_b + (t_m - t_bar)(t_j - t_bar)/S_tt`` (``1/n_b`` for a constant
baseline), and the shared samples add ``sigma^2 sum_shared w_j^2`` (the bound's
``B``; by Cauchy-Schwarz each pulse of a pair counting its own weights' part twice
is enough). The samples are put back on the sampling grid from the window's first
and last used sample times (``measure.windows.SensorChannel.info``); if the count
differs from the extraction's (a gap in the stream), each shared fraction ``f`` of a
side adds ``f sigma^2 / n_b`` instead (twice the even split's share). With the sides
equal, ``t_m = t_bar``, every weight is ``1/n_b`` and both sides shared give
``sigma^2 (1/n_u + 2/n_b)``: the chain's variance.
"""
from __future__ import annotations

import numpy as np

__all__ = ["span_overlap", "next_start", "pulse_gap_us", "SharedBaselines", "CompiledSharedBaselines",
           "shared_baselines"]


def pulse_gap_us(cfg) -> int:
    """The quiet time the single-coil mode keeps after a pulse's end: its fall and after-baseline
    and a guard (``fall + baseline + guard``: the next pulse's before-baseline is then this one's
    after-baseline); with ``[adaptive] baseline_sharing = "apart"`` one baseline and guard more,
    so the next pulse's before-baseline ``[s - baseline, s - guard]`` starts after this one's
    after-baseline ends and no sample serves two amplitudes. Back to back, a chain of pulses
    averages like ``sigma^2 (1/n_u + 2/n_b)`` per pulse; apart, each keeps ``sigma^2 (1/n_u +
    1/n_b)``: for a 60 ms pulse at 100 Hz 1.44 times the information at the same current (the
    same joules) for 1.35 times the time between pulses."""
    p = cfg.pulse
    gap = p.fall_us + p.baseline_us + p.guard_us
    if cfg.adaptive.baseline_sharing == "apart":
        gap += p.baseline_us + p.guard_us
    return gap


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
    amplitudes' own variances (``[adaptive] baseline_sharing = "ignore"``; ``"bound"`` and
    ``"apart"`` count the shared part).

    Windows are closed in the order of their pulses: :meth:`close` takes one (its edges, the
    start of the next pulse if one is commanded, else ``-1``, and the earliest start a pulse
    not yet commanded may have) and remembers its end for the next; :meth:`variance` then
    gives each sensor's amplitude variance for it (a buffer of this object, refilled per call;
    pure float arithmetic, nothing allocated).
    """

    def __init__(self, fall_us: int, baseline_us: int, guard_us: int, sigma_t: float, period_us: float,
                 enabled: bool = True, apart: bool = False):
        self.fall_us = int(fall_us)
        self.baseline_us = int(baseline_us)
        self.guard_us = int(guard_us)
        self.sigma2 = float(sigma_t) * float(sigma_t)
        self.period_us = float(period_us)
        self.enabled = bool(enabled)
        #: pulses are kept apart (``pulse_gap_us``): a decision predicts no side shared
        self.apart = bool(apart)
        self.n_base = max(2, 2 * int(self.baseline_us / self.period_us))
        self.prev_end = None          # the end of the pulse whose window was closed last
        self.shared = 0.0             # the window being closed: shared fractions, 0..2 (before + after)
        self.fb = 0.0
        self.fa = 0.0
        self._start = self._end = 0
        self._b0 = self._b1 = 0       # the window's before samples shared: [b0, b1] (empty: b1 < b0)
        self._a0 = self._a1 = 0       # its after samples shared: [a0, a1]
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
        ``earliest_next_us`` or later may still follow, -1: none may). Sets and returns
        :attr:`shared` (before + after fractions)."""
        prev = self.prev_end
        self.prev_end = end
        self._start, self._end = start, end
        self._b0, self._b1 = 1, 0
        self._a0, self._a1 = 1, 0
        if next_start >= 0:
            fb, fa = self.before_after(start, end, prev, next_start)
            self._a0, self._a1 = next_start - self.baseline_us, next_start - self.guard_us
        else:
            # any later start s >= earliest: its before span [s - baseline, s - guard] lies in
            # [earliest - baseline, inf)
            fb, _ = self.before_after(start, end, prev, -1)
            fa = 0.0
            if earliest_next_us >= 0:
                fa = span_overlap(end + self.fall_us, end + self.fall_us + self.baseline_us,
                                  earliest_next_us - self.baseline_us, 1 << 62)
                self._a0, self._a1 = earliest_next_us - self.baseline_us, 1 << 62
        if prev is not None:
            self._b0, self._b1 = prev + self.fall_us, prev + self.fall_us + self.baseline_us
        if not self.enabled:
            fb = fa = 0.0
        self.fb, self.fa = fb, fa
        self.shared = fb + fa
        return self.shared

    def shared_variance(self, n_used: int, n_base: int, first_us: int, last_us: int) -> float:
        """``sigma^2 sum_shared w_j^2``: the shared samples' part of the amplitude variance of
        the window just closed (module docstring), its samples put back on the grid of period
        ``period_us`` through the first and last used sample times; the fraction rule when they
        do not give ``n_base`` samples."""
        if self.shared <= 0.0 or n_base <= 0:
            return 0.0
        T = self.period_us
        if n_used <= 0 or last_us < first_us:
            return self.shared * self.sigma2 / n_base
        b_lo, b_hi = self._start - self.baseline_us, self._start - self.guard_us
        a_lo, a_hi = self._end + self.fall_us, self._end + self.fall_us + self.baseline_us
        # the baseline samples: first - k T (before), last + k T (after), k = 1, 2, ...
        n = 0
        st = stt = 0.0
        for side in (0, 1):
            k = 1
            while True:
                t = first_us - k * T if side == 0 else last_us + k * T
                if (side == 0 and t < b_lo) or (side == 1 and t > a_hi):
                    break
                if (side == 0 and t <= b_hi) or (side == 1 and t >= a_lo):
                    n += 1
                    st += t
                    stt += t * t
                k += 1
        if n != n_base:
            return self.shared * self.sigma2 / n_base
        tbar = st / n
        sxx = stt - n * tbar * tbar
        tm = 0.5 * (first_us + last_us)
        slope = (tm - tbar) / sxx if sxx > 1e-9 * T * T else 0.0
        acc = 0.0
        for side in (0, 1):
            lo, hi = (self._b0, self._b1) if side == 0 else (self._a0, self._a1)
            if hi < lo:
                continue
            k = 1
            while True:
                t = first_us - k * T if side == 0 else last_us + k * T
                if (side == 0 and t < b_lo) or (side == 1 and t > a_hi):
                    break
                inside = (side == 0 and t <= b_hi) or (side == 1 and t >= a_lo)
                if inside and lo <= t <= hi:
                    w = 1.0 / n + slope * (t - tbar)
                    acc += w * w
                k += 1
        return self.sigma2 * acc

    def variance(self, amp_var, info):
        """``amp_var`` (3,) plus the shared samples' part counted once more
        (:meth:`shared_variance`; ``info``: the window's n_used, n_base, first and last used
        sample times), into :attr:`var` (returned)."""
        v = self.var
        extra = self.shared_variance(int(info[0]), int(info[1]), int(info[2]), int(info[3]))
        v[0] = float(amp_var[0]) + extra
        v[1] = float(amp_var[1]) + extra
        v[2] = float(amp_var[2]) + extra
        return v

    def channel_variance(self, k: int, amp_var, info):
        """:meth:`variance` of sensor channel ``k``'s last window (``amp_var``, ``info``: that
        channel's, ``measure.windows.SensorChannel``); on the compiled core one call on the
        channels bound once (:meth:`CompiledSharedBaselines.bind_channels`)."""
        return self.variance(amp_var, info)

    def predicted(self, var_amp: float, start: int, prev_end: int) -> float:
        """The variance a pulse starting at ``start`` will be taken with (a decision's
        prediction, nominal ``n_b``, sides even): its before side as the previous pulse
        (ending at ``prev_end``; 0 or less: none) leaves it, its after side shared (a pulse may
        follow back to back; not when pulses are kept apart)."""
        if not self.enabled:
            return var_amp
        fb = 0.0
        if prev_end > 0:
            fb = span_overlap(start - self.baseline_us, start - self.guard_us, prev_end + self.fall_us,
                              prev_end + self.fall_us + self.baseline_us)
        return var_amp + (fb + (0.0 if self.apart else 1.0)) * self.sigma2 / (2.0 * self.n_base)

    def chained(self, var_amp: float) -> float:
        """The variance of a pulse in flight as a decision predicts it: both sides shared (none
        when pulses are kept apart)."""
        return var_amp + self.sigma2 / self.n_base if self.enabled and not self.apart else var_amp


# the slots of the state arrays (core/include/ct_sc_window.h CT_SB_*)
_FALL, _BASE, _GUARD, _ENABLED, _HAS_PREV, _PREV_END, _START, _END, _B0, _B1, _A0, _A1, _NBASE, _APART, _NI = range(15)
_SIGMA2, _PERIOD, _SHARED, _FB, _FA, _NF = range(6)


def _int_slot(k: int) -> property:
    def get(self) -> int:
        return self._iv[k]

    def put(self, v) -> None:
        self._iv[k] = v
    return property(get, put)


def _float_slot(k: int) -> property:
    def get(self) -> float:
        return self._fv[k]

    def put(self, v) -> None:
        self._fv[k] = v
    return property(get, put)


class CompiledSharedBaselines(SharedBaselines):
    """:class:`SharedBaselines` whose :meth:`close`, :meth:`variance`, :meth:`predicted` and
    :meth:`chained` run compiled (``core/src/sc_window.c``: ``ct_sb_close``, ``ct_sb_variance`` with
    ``ct_sb_shared_variance``, ``ct_sb_predicted``, ``ct_sb_chained``,
    the same operations in the same order: the same bits). Its state lives in two arrays (integers,
    floats) the kernels read and write, read and written through properties under the reference's
    names; ``ext``: the compiled extension (``coiltrack.firmware.core.Core.ext``), the other
    parameters :class:`SharedBaselines`'."""

    fall_us = _int_slot(_FALL)
    baseline_us = _int_slot(_BASE)
    guard_us = _int_slot(_GUARD)
    _start = _int_slot(_START)
    _end = _int_slot(_END)
    _b0 = _int_slot(_B0)
    _b1 = _int_slot(_B1)
    _a0 = _int_slot(_A0)
    _a1 = _int_slot(_A1)
    n_base = _int_slot(_NBASE)
    sigma2 = _float_slot(_SIGMA2)
    period_us = _float_slot(_PERIOD)
    shared = _float_slot(_SHARED)
    fb = _float_slot(_FB)
    fa = _float_slot(_FA)

    @property
    def enabled(self) -> bool:
        return self._iv[_ENABLED] != 0

    @enabled.setter
    def enabled(self, v) -> None:
        self._iv[_ENABLED] = 1 if v else 0

    @property
    def apart(self) -> bool:
        return self._iv[_APART] != 0

    @apart.setter
    def apart(self, v) -> None:
        self._iv[_APART] = 1 if v else 0

    @property
    def prev_end(self):
        """The end of the pulse whose window was closed last (None before the first)."""
        return self._iv[_PREV_END] if self._iv[_HAS_PREV] else None

    @prev_end.setter
    def prev_end(self, v) -> None:
        self._iv[_HAS_PREV] = 0 if v is None else 1
        self._iv[_PREV_END] = 0 if v is None else v

    def __init__(self, ext, *args, **kw):
        assert (ext.SB_NI, ext.SB_NF) == (_NI, _NF)
        self._si = np.zeros(_NI, dtype=np.int64)
        self._sf = np.zeros(_NF)
        self._iv = memoryview(self._si)
        self._fv = memoryview(self._sf)
        super().__init__(*args, **kw)
        self._ck = ext.SharedBaselinesCore(self._si, self._sf, self.var)
        self._var_k = self._ck.variance
        # the window's close and a decision's variances: one call each (``ct_sb_close``,
        # ``ct_sb_predicted``, ``ct_sb_chained``), no Python layer, no property read
        self.close = self._ck.close
        self.predicted = self._ck.predicted
        self.chained = self._ck.chained
        self._bound = 0

    def bind_channels(self, channels) -> None:
        """Bind the sensor channels' last windows (``SensorChannel.amp_var``, ``info``), in the order
        :meth:`channel_variance` numbers them, once."""
        chs = tuple(channels)
        self._ck.bind_channels(tuple(a for ch in chs for a in (ch.amp_var, ch.info)))
        self._bound = len(chs)

    def variance(self, amp_var, info):
        """:meth:`SharedBaselines.variance` in one call of ``ct_sb_variance``."""
        self._ck.variance_of(amp_var, info)
        return self.var

    def channel_variance(self, k: int, amp_var, info):
        """:meth:`SharedBaselines.channel_variance` on the channels bound (:meth:`bind_channels`):
        one call of ``ct_sb_variance``."""
        if k < self._bound:
            self._var_k(k)
            return self.var
        return self.variance(amp_var, info)


def shared_baselines(core, *args, **kw) -> SharedBaselines:
    """The shared baselines of ``core`` (``coiltrack.firmware.core.Core``): the compiled twin where
    the extension is loaded, else the reference; the arguments are :class:`SharedBaselines`'."""
    if core.ext is not None and hasattr(core.ext, "SharedBaselinesCore"):
        return CompiledSharedBaselines(core.ext, *args, **kw)
    return SharedBaselines(*args, **kw)
