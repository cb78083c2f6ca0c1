"""Magnetometer sample ring and pulse-window extraction.

A pulsed-DC source is only ever seen by the magnetometer as "earth field (plus
whatever else is static) + coil field while the coil is on". The firmware knows
exactly when it asked the coil driver to start and stop a pulse, so it extracts
one pulse amplitude per axis from the samples around that window:

Timeline of one window (integer microseconds, ``start``/``end`` = pulse edges)::

    before baseline          guard  settle                guard  fall        after baseline
    [start-baseline_us, start-guard_us]  [start+settle_us, end-guard_us]  [end+fall_us, end+fall_us+baseline_us]
    |<---- quiet ---->|      |      |<---- flat top ---->|      |<- decay ->|<---- quiet ---->|

In-pulse samples
    A sample is *used* only if it lies in the settled window
    ``start + settle_us <= t <= end - guard_us`` AND it is not the first or the
    last of the samples lying inside ``[start, end]``. Schepers & Veltink
    (seeds/000_e46ec0e8bf7ea271.txt, sec. 3.1) average "all samples except the
    first and the last of each pulse ... because they may have occurred in the
    rising or falling edge". The settle time additionally covers the L/R
    current rise and the eddy currents that "die out at an exponential rate
    after the pulse reaches its steady state value", so sampling farther from
    the leading edge sees less of them (thesis seeds/002_cd7f1fdb7fc67471.txt,
    sec. 5.5 and sec. 7.2). The guard before ``end`` and before ``start``
    absorbs the timing uncertainty between the driver's and the sensor's clocks.

Baseline (earth field)
    "Between the magnetic pulses, only the earth magnetic field is measured
    which can be subtracted from the measured pulses" (thesis sec. 5.2); the
    pulse magnitude is obtained "by evaluating the values of the earth magnetic
    field just before and after the pulse", and movement within a cycle makes
    that DC component vary (thesis sec. 5.4, Fig. 5.6). A rotating sensor sees
    a changing earth field, so the baseline is fitted *linearly in time* (least
    squares, per axis, over the quiet samples on both sides) and evaluated at
    the mean time of the used in-pulse samples. Because the model is linear,
    subtracting it at each used sample time and averaging is identical to
    subtracting it once at the mean in-pulse time ``t_m``. If only one side has
    samples the baseline is that side's mean (constant) and ``PULSE_TOO_FEW``
    is raised whenever a side holds fewer than ``min_baseline_samples``.

Amplitude and variance (per axis)
    ``amp = mean(used in-pulse samples) - baseline(t_m)``.
    ``var = sigma^2 / n_pulse + sigma^2 * (1/n_b + (t_m - t_bar)^2 / Sxx)``:
    the first term is the variance of a sample mean, sigma_m = sigma/sqrt(n)
    (Schepers & Veltink sec. 3.1, Fig. 5); the second is the textbook variance
    of a least-squares line predicted at ``t_m`` (``t_bar`` and ``Sxx`` are
    the mean and the centred sum of squares of the baseline sample times;
    for a constant baseline the factor is ``1/n_b``). ``sigma`` is the
    configured per-sample noise std ``sigma_t`` (about 0.5e-7 T for the
    thesis's flipped magnetoresistive sensor, sec. 5.2.1). The pulse and
    baseline samples are disjoint, hence independent, so the variances add.
    An empirical per-axis estimate (sample variance of the used in-pulse
    samples about the fitted baseline slope, divided by n_pulse) is kept for
    diagnostics, see ``last_empirical_var``.

Flags (bit field; the estimate is still written whenever it can be computed)
    ``PULSE_SATURATED``   a used sample (pulse or baseline) was saturated.
    ``PULSE_BASELINE_DRIFT`` ``|mean(before) - mean(after)|`` exceeds
        ``drift_limit_t + drift_nsigma * sigma * sqrt(1/n_before + 1/n_after)``
        on any axis, i.e. more than the limit beyond what noise explains: the
        earth field moved a lot during the window (thesis sec. 5.4, Fig. 5.6),
        so the linear model is suspect.
    ``PULSE_FLIP``        the set/reset flip state is not constant over the
        span ``[start - baseline_us, end + fall_us + baseline_us]``: flipping
        "can introduce oscillations during pulsing" and should be synchronised
        with actuation (thesis sec. 5.5 and sec. 7.2).
    ``PULSE_INCOMPLETE``  the span is not bracketed by a sample before its
        start and a sample after its end (not yet ``ready()``, or already
        overwritten in the ring), or consecutive samples across the span are
        further apart than ``max_gap_us`` (when 0: 1.5 times the smallest
        spacing seen in the span), i.e. samples are missing.
    ``PULSE_TOO_FEW``     fewer than ``min_pulse_samples`` used in-pulse
        samples or fewer than ``min_baseline_samples`` on a side.
    If no in-pulse sample or no baseline sample exists at all, ``amp_out`` is
    set to 0, ``var_out`` to +inf and ``PULSE_TOO_FEW`` is set.

Firmware rules: every array is allocated in ``__init__``; ``push`` and
``extract`` only read and write those buffers (through memoryviews, with plain
Python float arithmetic, since a window holds at most a few hundred samples)
and create no numpy arrays. Time is an integer count of microseconds. Bad data
never raises: ``push`` rejects (and counts) samples that are non-finite, not
later than the previous one or not integer-timed; ``extract`` reports flags.
"""

from __future__ import annotations

import math
import operator

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.fusion_rings import KernelRing

# quality flags (bit field, int)
PULSE_OK = 0
PULSE_TOO_FEW = 1         # fewer than min_pulse_samples usable in-pulse samples, or fewer than min_baseline per side
PULSE_SATURATED = 2       # any used sample saturated
PULSE_BASELINE_DRIFT = 4  # before/after baseline differ by more than drift_limit_t (beyond what noise explains)
PULSE_FLIP = 8            # a set/reset flip occurred inside the window (sample flip-state changed)
PULSE_INCOMPLETE = 16     # the window cannot be closed yet / samples missing (gap in the stream)
#: window flags after which an amplitude is not used by any tracker
PULSE_UNUSABLE = PULSE_TOO_FEW | PULSE_SATURATED | PULSE_FLIP

# per-sample flag bits stored in SampleRing.flags
SAMPLE_SATURATED = 1
SAMPLE_FLIP = 2

#: ``SampleRing.latest_t_us`` / ``oldest_t_us`` of an empty ring.
NO_TIME_US = -(1 << 63)
_INT64_MAX = (1 << 63) - 1
#: window times the compiled extraction takes (beyond: the reference, in Python's ints)
_T_FAR = 1 << 61
_INF = math.inf


class SampleRing(KernelRing):
    """Fixed-capacity ring of magnetometer samples (a :class:`~coiltrack.firmware.ring.Ring`
    with one field ``B``).

    Storage (allocated once): ``t_us`` int64 (capacity,), ``b`` float64
    (capacity, 3) tesla, ``flags`` uint8 (capacity,) with bit0 = saturated,
    bit1 = flip (set/reset) state. Timestamps are strictly increasing; a full
    ring overwrites its oldest sample. Logical index 0 is the oldest sample
    (``slot``, ``index_at_or_after`` are the ring's).

    The ring's state is a :class:`~coiltrack.firmware.estimate.fusion_rings.KernelRing`'s ``hc``
    with two more entries: head, count, latest time, rejected samples, so a compiled kernel bound
    to it once pushes in place (``core/src/multi.c``: ``ct_sample_push``, through
    ``measure.windows.SensorChannel.push``).
    """

    def __init__(self, capacity: int):
        super().__init__(capacity, (("B", 3),), state=4)
        self.t_us = self.t
        self.b = self.d
        self.flags = np.zeros(self.capacity, dtype=np.uint8)
        # memoryviews read and write single elements as Python int/float,
        # without creating numpy scalars or arrays
        self.bv = memoryview(self.b.reshape(-1))
        self.fv = memoryview(self.flags)
        self._hcv[2] = NO_TIME_US

    def _set_latest(self, v: int) -> None:
        self._hcv[2] = v

    def _set_rejected(self, v: int) -> None:
        self._hcv[3] = v

    _latest = property(lambda self: self._hcv[2], _set_latest)      # time of the newest sample
    #: samples refused by push (bad data)
    rejected = property(lambda self: self._hcv[3], _set_rejected)

    def push(self, t_us: int, bx: float, by: float, bz: float,
             saturated: bool, flip: int) -> None:
        """Append one sample, overwriting the oldest when full.

        Samples that are not strictly later than the previous one, have a
        non-integer or out-of-range time, or a non-finite field are dropped
        and counted in ``rejected`` (a dropped sample shows up as a gap).
        """
        hc = self._hcv
        try:
            t = operator.index(t_us)
            x = float(bx)
            y = float(by)
            z = float(bz)
            fl = ((SAMPLE_SATURATED if saturated else 0)
                  | (SAMPLE_FLIP if operator.index(flip) & 1 else 0))
        except (TypeError, ValueError, OverflowError):
            hc[3] += 1
            return
        if (t <= hc[2] or t > _INT64_MAX
                or not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z))):
            hc[3] += 1
            return
        p = hc[0]                                 # Ring.push
        self.tv[p] = t
        n = p + 1
        hc[0] = 0 if n == self.capacity else n
        if hc[1] < self.capacity:
            hc[1] += 1
        j = 3 * p
        bv = self.bv
        bv[j] = x
        bv[j + 1] = y
        bv[j + 2] = z
        self.fv[p] = fl
        hc[2] = t

    def push_kernel(self, ext, counts):
        """The compiled :meth:`push` (``ext.SamplePush``, ``core/src/multi.c`` ``ct_sample_push``) bound to
        this ring's arrays and state and to a channel's counters ``counts`` (int64 (2,): samples, changes,
        both counted per sample, as ``SensorChannel.push`` counts them)."""
        return ext.SamplePush(self.t, self.b, self.flags, self.hc, counts)

    def clear(self) -> None:
        """Empty the ring; the next sample may have any time."""
        super().clear()
        self._latest = NO_TIME_US

    @property
    def latest_t_us(self) -> int:
        """Time of the newest sample, ``NO_TIME_US`` when empty."""
        return self._hcv[2]

    def nearest_slot(self, t_us: int) -> int:
        """The slot of the sample nearest ``t_us``, or -1 when empty. The search goes back from
        the newest sample (at most the ring's count; in a live stream the newest is the nearest)
        to the first at or before ``t_us`` and compares it with the one after."""
        slot = self._head
        tv = self.tv
        best = -1
        for _ in range(self._count):
            slot -= 1
            if slot < 0:
                slot += self.capacity
            if tv[slot] <= t_us:
                if best < 0 or t_us - tv[slot] < tv[best] - t_us:
                    best = slot
                break
            best = slot
        return best

    def time_at(self, slot: int) -> int:
        """The time stamp (us) of the sample in ``slot``."""
        return self.tv[slot]

    def field_at(self, slot: int) -> tuple[float, float, float]:
        """The field (T, sensor axes) of the sample in ``slot``."""
        bv, j = self.bv, 3 * slot
        return bv[j], bv[j + 1], bv[j + 2]

    def flip_at(self, slot: int) -> bool:
        """The set/reset (flip) state of the sample in ``slot``."""
        return bool(self.fv[slot] & SAMPLE_FLIP)

    def saturated_at(self, slot: int) -> bool:
        """Whether the sample in ``slot`` was saturated."""
        return bool(self.fv[slot] & SAMPLE_SATURATED)

    def extract_with(self, kernel, start_us: int, end_us: int) -> int:
        """Run the compiled extraction ``kernel`` (``core/src/window.c``: ``PulseWindow``, bound
        to this ring's arrays) on the window ``[start_us, end_us]`` at the ring's present state
        (head and count); returns the window flags."""
        return kernel.extract(start_us, end_us, self._head, self._count)

    def close_with(self, kernel, start_us: int, end_us: int, coil: int) -> int:
        """Run the compiled window close ``kernel`` (``core/src/multi.c``: ``WindowColumn``, bound to
        this ring's arrays) on the window ``[start_us, end_us]`` at the ring's present state, into
        column ``coil``; returns the window flags."""
        return kernel.close(start_us, end_us, self._head, self._count, coil)

    @property
    def oldest_t_us(self) -> int:
        """Time of the oldest retained sample, ``NO_TIME_US`` when empty."""
        if self._count == 0:
            return NO_TIME_US
        return self.tv[self.slot(0)]


class _WindowColumn:
    """The part of :class:`PulseExtractor` that closes a sensor channel's window into its burst in
    one compiled call (``core/src/multi.c``: ``ct_window_column``), bound by :meth:`bind_column`."""

    def bind_column(self, S, var, flags, done, pulse_mid, amp, amp_var, info) -> bool:
        """On the compiled core, bind :meth:`extract_column` to a sensor channel's burst buffers
        (``measure.windows.SensorChannel``: ``S``, ``var`` (3, n), ``flags``, ``done``,
        ``pulse_mid`` (n,), its last window ``amp``, ``amp_var`` (3,) and ``info`` (4,) int64);
        False (nothing bound) on the Python core or for an extractor with an extraction of its own."""
        if self._ext is None:
            return False
        ring = self._ring
        self._colk = self._ext.WindowColumn(
            ring.t, ring.b, ring.flags, self._used_t, self._emp_var, self._res, self._ires, S, var, flags, done,
            pulse_mid, amp, amp_var, info, self._settle_us, self._fall_us, self._baseline_us, self._guard_us,
            self._min_pulse, self._min_base, self._max_gap_us, self.max_samples, self._drift_limit, self._sigma,
            self._drift_nsigma)
        return True

    def extract_column(self, coil: int, start_us: int, end_us: int):
        """After :meth:`bind_column`: the channel's ``close_window`` in one call of
        ``ct_window_column`` (:meth:`extract` of the window into the bound ``amp``, ``amp_var`` and
        column ``coil``, its flags, middle, and ``info`` = n_used, n_base, first and last used
        sample times, as ``SensorChannel.close_window`` writes them); returns the flags, or None
        for a time the compiled extraction does not take (the caller then runs the reference)."""
        try:
            start = operator.index(start_us)
            end = operator.index(end_us)
        except TypeError:
            return None
        if not (-_T_FAR < start < _T_FAR and -_T_FAR < end < _T_FAR):
            return None
        return self._ring.close_with(self._colk, start, end, coil)

    def column_closed(self) -> None:
        """The bound column kernel closed a window (:meth:`extract_column`, or a run of channels'
        windows in one call: ``measure.windows.WindowCloser.close_run``): nothing left to do, its
        counts of used samples (``_n_used``, ``_n_rec``) are the kernel's results in ``_ires``."""
        return

    column_kernel = property(lambda self: getattr(self, "_colk", None))   # ext.WindowColumn (bind_column) or None

    def _set_n_used(self, v: int) -> None:
        self._iresv[1] = v

    def _set_n_rec(self, v: int) -> None:
        self._iresv[3] = v

    #: used in-pulse samples of the last extract (in ``_ires``, where the compiled kernels leave them)
    _n_used = property(lambda self: self._iresv[1], _set_n_used)
    #: of which timestamps recorded (<= max_samples)
    _n_rec = property(lambda self: self._iresv[3], _set_n_rec)


class PulseExtractor(_WindowColumn):
    """Extract pulse amplitudes from a :class:`SampleRing` (see module docstring).

    All times are integer microseconds; ``settle_us``, ``fall_us``,
    ``baseline_us`` and ``guard_us`` are measured from the commanded pulse
    edges. ``sigma_t`` is the per-sample noise std (tesla, all axes).
    ``max_samples`` sizes the buffer of used in-pulse timestamps kept for
    :meth:`last_used_times`. ``max_gap_us`` (0 = automatic) and
    ``drift_nsigma`` tune the ``PULSE_INCOMPLETE`` gap test and the
    ``PULSE_BASELINE_DRIFT`` noise allowance. ``core`` (``coiltrack.firmware.core``, chosen at
    composition): on the compiled one :meth:`extract` is one call of ``ct_pulse_extract``
    (``core/src/window.c``: the same operations in the same order, so the same result to the
    bit), bound here to the ring's arrays and this extractor's scratch.
    """

    def __init__(self, ring: SampleRing, *, settle_us: int, fall_us: int, baseline_us: int,
                 guard_us: int, min_pulse_samples: int = 3, min_baseline_samples: int = 2,
                 drift_limit_t: float = 2e-6, sigma_t: float = 5e-8, max_samples: int = 256,
                 max_gap_us: int = 0, drift_nsigma: float = 3.0, core=_DEFAULT_CORE):
        self._ring = ring
        self._settle_us = operator.index(settle_us)
        self._fall_us = operator.index(fall_us)
        self._baseline_us = operator.index(baseline_us)
        self._guard_us = operator.index(guard_us)
        self._min_pulse = operator.index(min_pulse_samples)
        self._min_base = operator.index(min_baseline_samples)
        self._max_gap_us = operator.index(max_gap_us)
        max_samples = operator.index(max_samples)
        if min(self._settle_us, self._fall_us, self._baseline_us, self._guard_us,
               self._max_gap_us) < 0:
            raise ValueError("settle/fall/baseline/guard/max_gap times must be >= 0")
        if self._min_pulse < 1 or self._min_base < 1 or max_samples < 1:
            raise ValueError("min_pulse_samples, min_baseline_samples, max_samples must be >= 1")
        self._drift_limit = float(drift_limit_t)
        self._sigma = float(sigma_t)
        self._drift_nsigma = float(drift_nsigma)
        if not (self._sigma > 0.0 and math.isfinite(self._sigma)
                and self._drift_limit >= 0.0 and self._drift_nsigma >= 0.0):
            raise ValueError("sigma_t must be > 0, drift_limit_t and drift_nsigma >= 0")
        self.max_samples = max_samples
        # scratch, allocated once
        self._used_t = np.zeros(max_samples, dtype=np.int64)
        self._used_tv = memoryview(self._used_t)
        self._emp_var = np.full(3, np.inf)
        self._emp_vv = memoryview(self._emp_var)
        # the last extract's flags, used in-pulse samples (``_n_used``), baseline samples and the
        # used samples whose times were recorded (``_n_rec``, <= max_samples): int64, so a compiled
        # kernel that closes the window (core/src/window.c, multi.c) leaves them where they are read
        self._ires = np.zeros(4, dtype=np.int64)
        self._iresv = memoryview(self._ires)
        self._sums = [0.0] * 5  # baseline regression sums of the window being extracted
        self._pm = [0.0] * 11   # in-pulse moments of the window being extracted
        self._pm_sat = False
        self._ext = None        # the compiled core's extension, once bound
        if type(self).extract is PulseExtractor.extract:     # (a subclass with its own extract keeps it)
            #: the numeric core the extraction runs (``"compiled"`` or ``"python"``)
            self.core = "python"
            if core.ext is not None:
                self._bind_compiled(core.ext)

    def _bind_compiled(self, ext) -> None:
        """Run :meth:`extract` on ``ct_pulse_extract``: the kernel bound once to the ring's
        arrays, the used-time and empirical-variance buffers and its result buffers (amplitude
        and variance; flags, counts); the method is replaced on this instance, so no call tests
        the choice."""
        ring = self._ring
        self._res = np.zeros(6)
        self._resv = memoryview(self._res)
        self._ck = ext.PulseWindow(ring.t, ring.b, ring.flags, self._used_t, self._emp_var, self._res, self._ires,
                                   self._settle_us, self._fall_us, self._baseline_us, self._guard_us,
                                   self._min_pulse, self._min_base, self._max_gap_us, self.max_samples,
                                   self._drift_limit, self._sigma, self._drift_nsigma)
        self.extract = self._extract_compiled
        self.core = "compiled"
        self._ext = ext

    def _extract_compiled(self, start_us: int, end_us: int, amp_out, var_out) -> tuple[int, int, int]:
        """:meth:`extract` on the compiled kernel; a time that is no integer, or one so far out
        that the span's ends would leave int64, goes to the reference (which flags it)."""
        try:
            start = operator.index(start_us)
            end = operator.index(end_us)
        except TypeError:
            start = end = _T_FAR
        if not (-_T_FAR < start < _T_FAR and -_T_FAR < end < _T_FAR):
            return PulseExtractor.extract(self, start_us, end_us, amp_out, var_out)
        flags = self._ring.extract_with(self._ck, start, end)
        r, ir = self._resv, self._iresv
        amp_out[0], amp_out[1], amp_out[2] = r[0], r[1], r[2]
        var_out[0], var_out[1], var_out[2] = r[3], r[4], r[5]
        return flags, ir[1], ir[2]

    # ------------------------------------------------------------------ timing
    def span(self, start_us: int, end_us: int) -> tuple[int, int]:
        """First and last time of the samples a window reads."""
        return (start_us - self._baseline_us,
                end_us + self._fall_us + self._baseline_us)

    def ready(self, start_us: int, end_us: int) -> bool:
        """True once a sample later than ``end + fall + baseline`` has arrived."""
        return self._ring.latest_t_us > end_us + self._fall_us + self._baseline_us

    def expect_complete(self, start_us: int, end_us: int) -> bool:
        """Whether every sample the window reads is expected in: the next sample, one interval
        (the newest between two samples) after the newest, falls after ``end + fall + baseline``.
        A prediction for a caller that works ahead (``track.magnetic`` solving ahead): a late
        or skipped sample can prove it wrong, so what was computed from it must be checked
        against the window's amplitude once :meth:`ready`."""
        return self._next_expected_us() > end_us + self._fall_us + self._baseline_us

    def completing_sample_us(self, start_us: int, end_us: int) -> int:
        """The time the sample that will make the window :meth:`ready` is expected at: the next
        sample (:meth:`expect_complete`'s, one interval after the newest) where the window is not
        ready yet and that sample falls after it; :data:`NO_TIME_US` otherwise. A hint for the wall-clock loop,
        which starts a tick just after it (``[timing] align_us``); nothing is computed from it."""
        ready_after = end_us + self._fall_us + self._baseline_us
        if self._ring.latest_t_us > ready_after:
            return NO_TIME_US
        t = self._next_expected_us()
        return t if t > ready_after else NO_TIME_US

    def _next_expected_us(self) -> int:
        """The next sample's expected time: one interval (the newest between two samples) after
        the newest; :data:`NO_TIME_US` with fewer than two samples in."""
        ring = self._ring
        slot = ring.peek(1)
        if slot < 0:
            return NO_TIME_US
        t = ring.latest_t_us
        return 2 * t - ring.tv[slot]

    # --------------------------------------------------------- introspection
    def last_used_times(self, out) -> int:
        """Write the times of the in-pulse samples used by the last extract
        into ``out`` (int64 array); return how many were written
        (``min(n_pulse, max_samples, len(out))``)."""
        n = self._n_rec
        if n > len(out):
            n = len(out)
        uv = self._used_tv
        for k in range(n):
            out[k] = uv[k]
        return n

    def last_used_span(self) -> tuple[int, int]:
        """Times of the first and the last in-pulse sample the last extract recorded (the
        first and the last of :meth:`last_used_times`), ``(0, 0)`` when none."""
        n = self._n_rec
        if n == 0:
            return 0, 0
        uv = self._used_tv
        return uv[0], uv[n - 1]

    def last_empirical_var(self, out) -> int:
        """Write the empirical variance of the last in-pulse mean per axis,
        ``s^2 / n_pulse``, into ``out`` (3,); return ``n_pulse``. ``s^2`` is
        the unbiased sample variance of the used samples after removing the
        fitted baseline slope (+inf when fewer than 2 samples). It is the
        measured counterpart of ``sigma^2 / n_pulse`` (Schepers & Veltink
        sec. 3.1, Fig. 5); it carries no baseline term and grows when the
        coil field seen by the sensor changes during the pulse (motion)."""
        ev = self._emp_vv
        out[0] = ev[0]
        out[1] = ev[1]
        out[2] = ev[2]
        return self._n_used

    # ------------------------------------------------------------ extraction
    def _fail(self, flags: int, amp_out, var_out, n_pulse: int, n_base: int):
        amp_out[0] = 0.0
        amp_out[1] = 0.0
        amp_out[2] = 0.0
        var_out[0] = _INF
        var_out[1] = _INF
        var_out[2] = _INF
        return flags | PULSE_TOO_FEW, n_pulse, n_base

    def extract(self, start_us: int, end_us: int, amp_out, var_out) -> tuple[int, int, int]:
        """Estimate the pulse amplitude for the window ``[start_us, end_us]``.

        Writes ``amp_out`` (3,) tesla and ``var_out`` (3,) tesla^2; returns
        ``(flags, n_pulse, n_base)``. Never raises on bad data. The span's
        samples are read in time order, in its three parts (module docstring):
        the before-baseline, the used in-pulse samples, the after-baseline.
        """
        ev = self._emp_vv
        ev[0] = _INF
        ev[1] = _INF
        ev[2] = _INF
        self._n_used = 0
        self._n_rec = 0
        try:
            start = operator.index(start_us)
            end = operator.index(end_us)
        except TypeError:
            return self._fail(PULSE_INCOMPLETE, amp_out, var_out, 0, 0)
        ring = self._ring
        n = len(ring)
        if n == 0:
            return self._fail(PULSE_INCOMPLETE, amp_out, var_out, 0, 0)
        idx = ring.index_at_or_after
        i_lo = idx(start - self._baseline_us)                       # span start
        i_hi = idx(end + self._fall_us + self._baseline_us + 1)     # first sample after the span
        flags = self._span_flags(i_lo, i_hi, n)
        if i_lo == i_hi:
            return self._fail(flags, amp_out, var_out, 0, 0)
        sums = self._sums                         # regression sums over both sides
        sums[0] = sums[1] = sums[2] = sums[3] = sums[4] = 0.0
        ref = ring.field_at(ring.slot(i_lo))      # values relative to the first span sample
        i_pre = idx(start - self._guard_us + 1)   # before-baseline: [i_lo, i_pre)
        before = self._baseline_side(i_lo, i_pre, start, ref)
        used0 = max(idx(start + self._settle_us), idx(start) + 1, i_pre)   # not the first in [start, end]
        used1 = min(idx(end - self._guard_us + 1), idx(end + 1) - 1)       # nor the last
        n_p = self._pulse_moments(used0, used1, start, ref)
        i_post = max(idx(end + self._fall_us), i_pre, used1 if used1 > used0 else 0)
        after = self._baseline_side(i_post, i_hi, start, ref)
        if before[4] or after[4] or self._pm_sat:
            flags |= PULSE_SATURATED
        n_a = before[0]
        n_c = after[0]
        n_b = n_a + n_c
        self._n_used = n_p
        self._n_rec = n_p if n_p < self.max_samples else self.max_samples
        if n_p < self._min_pulse or n_a < self._min_base or n_c < self._min_base:
            flags |= PULSE_TOO_FEW
        if n_p == 0 or n_b == 0:
            return self._fail(flags, amp_out, var_out, n_p, n_b)
        flags |= self._amplitude(before, after, n_p, amp_out, var_out)
        return flags, n_p, n_b

    def _span_flags(self, i_lo: int, i_hi: int, n: int) -> int:
        """``PULSE_INCOMPLETE`` and ``PULSE_FLIP`` of the span ``[i_lo, i_hi)`` (logical
        indices): not bracketed on both sides, a gap between consecutive samples (the
        bracketing samples included), or a change of the flip state."""
        ring = self._ring
        tv = ring.tv
        fv = ring.fv
        flags = PULSE_OK
        if i_lo == 0 or i_hi >= n:                # span not bracketed on both sides
            flags |= PULSE_INCOMPLETE
        first = i_lo - 1 if i_lo > 0 else i_lo
        last = i_hi if i_hi < n else i_hi - 1
        min_dt = max_dt = n_dt = 0
        flip0 = -1
        if first <= last:
            prev_t = tv[ring.slot(first)]
            for i in range(first + 1, last + 1):
                t = tv[ring.slot(i)]
                dt = t - prev_t
                if n_dt == 0 or dt < min_dt:
                    min_dt = dt
                if dt > max_dt:
                    max_dt = dt
                n_dt += 1
                prev_t = t
        for i in range(i_lo, i_hi):
            fb = fv[ring.slot(i)] & SAMPLE_FLIP
            if flip0 < 0:
                flip0 = fb
            elif fb != flip0:
                flags |= PULSE_FLIP
                break
        if n_dt > 0:
            if self._max_gap_us > 0:
                if max_dt > self._max_gap_us:
                    flags |= PULSE_INCOMPLETE
            elif n_dt > 1 and 2 * max_dt > 3 * min_dt:
                flags |= PULSE_INCOMPLETE
        return flags

    def _baseline_side(self, i0: int, i1: int, start: int, ref: tuple) -> tuple:
        """One baseline side, samples ``[i0, i1)``: ``(n, sum x, sum y, sum z, saturated)``
        of the values relative to the field ``ref``; the regression sums over both sides
        (``self._sums``: t, t^2, t x, t y, t z; t relative to ``start``, us) go on."""
        ring = self._ring
        tv = ring.tv
        bv = ring.bv
        fv = ring.fv
        rx, ry, rz = ref
        sums = self._sums
        st, stt, stx, sty, stz = sums[0], sums[1], sums[2], sums[3], sums[4]
        n = 0
        ax = ay = az = 0.0
        sat = False
        for i in range(i0, i1):
            p = ring.slot(i)
            j = 3 * p
            x = bv[j] - rx
            y = bv[j + 1] - ry
            z = bv[j + 2] - rz
            tr = float(tv[p] - start)
            n += 1
            ax += x
            ay += y
            az += z
            st += tr
            stt += tr * tr
            stx += tr * x
            sty += tr * y
            stz += tr * z
            if fv[p] & SAMPLE_SATURATED:
                sat = True
        sums[0], sums[1], sums[2], sums[3], sums[4] = st, stt, stx, sty, stz
        return n, ax, ay, az, sat

    def _pulse_moments(self, i0: int, i1: int, start: int, ref: tuple) -> int:
        """The used in-pulse samples ``[i0, i1)``: running means, centred sums of squares
        (q) and time co-moments (k) per axis (Welford), for the mean and the empirical
        variance of the residuals about the fitted baseline slope, into ``self._pm``
        (t, q_t, x, y, z, q_x, q_y, q_z, k_x, k_y, k_z); their times into the used-time
        buffer. Returns their count."""
        ring = self._ring
        tv = ring.tv
        bv = ring.bv
        fv = ring.fv
        uv = self._used_tv
        max_rec = self.max_samples
        rx, ry, rz = ref
        n_p = 0
        mt = qt = 0.0
        mx = my = mz = 0.0
        qx = qy = qz = 0.0
        kx = ky = kz = 0.0
        sat = False
        for i in range(i0, i1):
            p = ring.slot(i)
            t = tv[p]
            j = 3 * p
            x = bv[j] - rx
            y = bv[j + 1] - ry
            z = bv[j + 2] - rz
            if n_p < max_rec:
                uv[n_p] = t
            n_p += 1
            tr = float(t - start)
            d_t = tr - mt
            mt += d_t / n_p
            qt += d_t * (tr - mt)
            d = x - mx
            mx += d / n_p
            qx += d * (x - mx)
            kx += d_t * (x - mx)
            d = y - my
            my += d / n_p
            qy += d * (y - my)
            ky += d_t * (y - my)
            d = z - mz
            mz += d / n_p
            qz += d * (z - mz)
            kz += d_t * (z - mz)
            if fv[p] & SAMPLE_SATURATED:
                sat = True
        pm = self._pm
        pm[0], pm[1], pm[2], pm[3], pm[4] = mt, qt, mx, my, mz
        pm[5], pm[6], pm[7], pm[8], pm[9], pm[10] = qx, qy, qz, kx, ky, kz
        self._pm_sat = sat
        return n_p

    def _amplitude(self, before: tuple, after: tuple, n_p: int, amp_out, var_out) -> int:
        """Amplitude and variance from the sums (module docstring); the empirical variance;
        returns ``PULSE_BASELINE_DRIFT`` when the sides disagree beyond noise, else 0."""
        n_a, ax, ay, az, _ = before
        n_c, cx, cy, cz, _ = after
        st, stt, stx, sty, stz = self._sums
        mt, qt, mx, my, mz, qx, qy, qz, kx, ky, kz = self._pm
        flags = PULSE_OK
        s2 = self._sigma * self._sigma
        tm = mt                                   # mean time of the used samples
        inv_nb = 1.0 / (n_a + n_c)
        bx = (ax + cx) * inv_nb
        by = (ay + cy) * inv_nb
        bz = (az + cz) * inv_nb
        fac = inv_nb
        gx = gy = gz = 0.0                        # baseline slopes, T/us
        if n_a > 0 and n_c > 0:
            tbar = st * inv_nb
            sxx = stt - st * tbar
            if sxx > 0.0:
                dtm = tm - tbar
                gx = (stx - tbar * (ax + cx)) / sxx
                gy = (sty - tbar * (ay + cy)) / sxx
                gz = (stz - tbar * (az + cz)) / sxx
                bx += gx * dtm
                by += gy * dtm
                bz += gz * dtm
                fac = inv_nb + dtm * dtm / sxx
            # drift between the sides, beyond the limit plus what noise explains
            lim = (self._drift_limit
                   + self._drift_nsigma * self._sigma * math.sqrt(1.0 / n_a + 1.0 / n_c))
            inv_a = 1.0 / n_a
            inv_c = 1.0 / n_c
            if (abs(ax * inv_a - cx * inv_c) > lim or abs(ay * inv_a - cy * inv_c) > lim
                    or abs(az * inv_a - cz * inv_c) > lim):
                flags |= PULSE_BASELINE_DRIFT
        amp_out[0] = mx - bx
        amp_out[1] = my - by
        amp_out[2] = mz - bz
        v = s2 / n_p + s2 * fac
        var_out[0] = v
        var_out[1] = v
        var_out[2] = v
        if n_p >= 2:
            # sum of squared residuals about the baseline slope:
            # sum((x - mx) - g (t - mt))^2 = qx - 2 g kx + g^2 qt
            k = 1.0 / ((n_p - 1) * n_p)
            ev = self._emp_vv
            ev[0] = max(qx - 2.0 * gx * kx + gx * gx * qt, 0.0) * k
            ev[1] = max(qy - 2.0 * gy * ky + gy * gy * qt, 0.0) * k
            ev[2] = max(qz - 2.0 * gz * kz + gz * gz * qt, 0.0) * k
        return flags
