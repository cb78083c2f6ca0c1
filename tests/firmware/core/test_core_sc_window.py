"""The compiled shared baselines of the single-coil window close (firmware_py/core/src/sc_window.c,
glue py_sc_window.c) against their Python reference, ``estimate.shared_baseline.SharedBaselines``
(``close`` with ``before_after`` and ``span_overlap``; ``variance`` with ``shared_variance``).

The variance an amplitude is taken with decides, through the NIS gate, whether a pulse is used, so
the twin must give the reference's bits: every close's shared fractions, the remembered edges and
every variance are compared with ``==`` on seeded random chains of pulses: back to back (a
baseline shared between two pulses), kept apart, at random gaps, overlapping; the next pulse
commanded or not, a pulse not yet commanded that may or may not follow; the bound on and off;
and windows whose samples are on the sampling grid, cut short (fewer used samples, the last
before the first, none), or off the grid (a dropped or clipped sample: the count differs from the
extraction's and the fraction rule applies). The windows' ``info`` comes from the firmware's own
extraction (``measure.pulse.PulseExtractor``) of rings with a saturated (clipped) sample and
gaps. Independent reference: the chain's closed form ``sigma^2 (1/n_u + 2/n_b)`` of a window whose
both sides are shared, sides even (Schepers & Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt``
sec. 3.1, ``sigma/sqrt(n)``; the module docstring's bound). Seeded; skips where the extension is
not built."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.estimate.shared_baseline import CompiledSharedBaselines, SharedBaselines, shared_baselines
from coiltrack.firmware.measure.pulse import PulseExtractor, SampleRing
from coiltrack.tools.bench.alloc import NumpyAllocationCounter

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
SETTLE, FALL, GUARD, BASE = 3_000, 3_000, 2_000, 35_000
SIGMA = 3e-8
PER = 10_000
GAP = FALL + BASE + GUARD


def _pair(enabled=True, apart=False, per=PER, base=BASE):
    ref = SharedBaselines(FALL, base, GUARD, SIGMA, per, enabled, apart)
    got = shared_baselines(COMPILED, FALL, base, GUARD, SIGMA, per, enabled, apart)
    assert isinstance(got, CompiledSharedBaselines)
    return ref, got


def _state(sh):
    return (sh.prev_end, sh.shared, sh.fb, sh.fa, sh._start, sh._end, sh._b0, sh._b1, sh._a0, sh._a1)


def _same_state(ref, got, what):
    a, b = _state(ref), _state(got)
    assert a == b, f"{what}: {a} != {b}"
    assert all(type(x) is type(y) for x, y in zip(a, b)), what


def _infos(rng, start, end, per):
    """Windows' ``info`` rows for the pulse ``[start, end]``: on the grid (the used samples of a
    sampled pulse), cut short, with the last before the first, with none, off the grid."""
    phase = int(rng.integers(0, per))
    first = start + SETTLE + (phase - (start + SETTLE)) % per
    last = first + per * int((end - GUARD - first) // per)
    n_used = (last - first) // per + 1
    n_b = 0
    for side in (0, 1):
        k = 1
        while True:
            t = first - k * per if side == 0 else last + k * per
            if (side == 0 and t < start - BASE) or (side == 1 and t > end + FALL + BASE):
                break
            if (side == 0 and t <= start - GUARD) or (side == 1 and t >= end + FALL):
                n_b += 1
            k += 1
    yield (n_used, n_b, first, last)                                   # on the grid
    yield (max(n_used - 2, 1), n_b, first, last - 2 * per)              # cut short at the end
    yield (n_used, n_b - 1, first, last)                                # a baseline sample dropped
    yield (n_used, n_b, first + 1234, last)                             # off the grid
    yield (n_used, n_b, last, first - 1)                                # the last before the first
    yield (0, n_b, 0, 0)                                                # no used sample
    yield (n_used, 0, first, last)                                      # no baseline
    yield (1, n_b, first, first)                                        # one used sample


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("mode", ["bound", "ignore", "apart"])
def test_random_chains_give_the_reference_bits(seed, mode):
    rng = np.random.default_rng(seed)
    per = float(PER) if seed != 3 else 1e6 / 98.0          # a period that is no whole microsecond
    ref, got = _pair(mode != "ignore", mode == "apart", per)
    _same_state(ref, got, "start")
    s = 150_000 + int(rng.integers(0, 20_000))
    for i in range(120):
        length = int(rng.choice([20_000, 40_000, 60_000, 80_000]))
        start, end = s, s + length
        gap = int(rng.choice([GAP, GAP + BASE + GUARD, GAP - 10_000, int(rng.integers(0, 3 * GAP)), 0]))
        nxt = end + gap
        r = rng.random()
        if r < 0.4:
            args = (start, end, nxt, -1)                              # the next pulse commanded
        elif r < 0.7:
            args = (start, end, -1, end + int(rng.integers(-BASE, 2 * GAP)))    # may still follow
        elif r < 0.8:
            args = (start, end, -1, -1)                               # none may follow
        else:
            args = (start, end, nxt, int(rng.integers(0, 10 ** 7)))
        a = ref.close(*args)
        b = got.close(*args)
        assert a == b and type(b) is float, (i, args)
        _same_state(ref, got, f"close {i} {args}")
        for info in _infos(rng, start, end, per):
            amp_var = rng.random(3) * 1e-15
            iv = np.array(info, dtype=np.int64)
            va = ref.variance(amp_var, iv).copy()
            vb = got.variance(amp_var, iv).copy()
            assert va.tobytes() == vb.tobytes(), (i, info, va, vb)
            assert ref.shared_variance(*info) == got.shared_variance(*info)
        s = nxt


def _extract(times, start, end, clip=None):
    """The firmware's extraction of a pulse ``[start, end]`` from a ring sampled at ``times``
    (``clip``: the index of a saturated sample): its variances and ``info``."""
    ring = SampleRing(256)
    ext = PulseExtractor(ring, settle_us=SETTLE, fall_us=FALL, baseline_us=BASE, guard_us=GUARD,
                         min_pulse_samples=3, min_baseline_samples=2, sigma_t=SIGMA)
    for i, t in enumerate(times):
        ring.push(t, 0.0, 0.0, 0.0, i == clip, 0)
    amp, v = np.zeros(3), np.zeros(3)
    _, n_u, n_b = ext.extract(start, end, amp, v)
    first, last = ext.last_used_span() if n_u else (0, 0)
    return v, np.array([n_u, n_b, first, last], dtype=np.int64)


@pytest.mark.parametrize("phase", [0, 3_000, 7_500])
def test_a_shared_baseline_between_two_pulses_gives_the_chain_variance(phase):
    """Three pulses back to back (the middle one's both sides shared, the sides even): the middle
    amplitude is taken with ``sigma^2 (1/n_u + 2/n_b)`` on both cores, bit for bit the reference's;
    a clipped sample or a dropped one (off the grid: the fraction rule) gives the reference's bits too."""
    L = 60_000
    edges = [(200_000 + k * (L + GAP), 200_000 + k * (L + GAP) + L) for k in range(3)]
    times = list(range(100_000 + phase, edges[-1][1] + 120_000, PER))
    for clip, drop in ((None, None), (None, 18), (12, None), (25, None)):
        ts = [t for i, t in enumerate(times) if i != drop]
        ref, got = _pair()
        for k, (a, b) in enumerate(edges):
            nxt = edges[k + 1][0] if k + 1 < len(edges) else -1
            ref.close(a, b, nxt, -1)
            got.close(a, b, nxt, -1)
            _same_state(ref, got, f"pulse {k}")
            v, info = _extract(ts, a, b, clip)
            va, vb = ref.variance(v, info).copy(), got.variance(v, info).copy()
            assert va.tobytes() == vb.tobytes(), (clip, drop, k)
            if k == 1 and drop is not None:      # a sample missing: the fraction rule
                assert vb[0] - v[0] == pytest.approx(got.shared * SIGMA ** 2 / int(info[1]), rel=1e-9)
            if k == 1 and clip is None and drop is None:
                # independent: the least-squares line's weights (numpy's lstsq) at the used samples'
                # mid time, summed squared over the baseline samples the neighbours share
                tb = np.array([t for t in ts if a - BASE <= t <= a - GUARD or b + FALL <= t <= b + FALL + BASE], float)
                A = np.stack([np.ones_like(tb), tb], axis=1)
                tm = 0.5 * (info[2] + info[3])
                w = np.array([1.0, tm]) @ np.linalg.pinv(A)
                pa, nb = edges[0][1], edges[2][0]
                sh = [(pa + FALL <= t <= pa + FALL + BASE) or (nb - BASE <= t <= nb - GUARD) for t in tb]
                assert vb[0] - v[0] == pytest.approx(SIGMA ** 2 * float(np.sum(w[sh] ** 2)), rel=1e-9)
                if all(sh):
                    # every baseline sample shared, the sides even: the chain's closed form
                    n_u, n_b = int(info[0]), int(info[1])
                    assert phase != 3_000 and got.fb == 1.0
                    assert vb[0] == pytest.approx(SIGMA ** 2 * (1 / n_u + 2 / n_b), rel=1e-9)


def test_bound_channels_and_no_allocation():
    """``channel_variance`` on the channels bound once reads each channel's own window, the same
    bits as ``variance`` on its arrays, and neither it nor ``close`` allocates a numpy array."""

    class Channel:
        def __init__(self, av, info):
            self.amp_var, self.info = av, info

    rng = np.random.default_rng(5)
    chs = [Channel(rng.random(3) * 1e-15, np.array([5, 7, 203_000 + 10_000 * k, 243_000 + 10_000 * k],
                                                  dtype=np.int64)) for k in range(3)]
    ref, got = _pair()
    got.bind_channels(chs)
    with pytest.raises(RuntimeError):
        got.bind_channels(chs)
    for sh in (ref, got):
        sh.close(100_000, 160_000, 200_000, -1)
        sh.close(200_000, 260_000, 300_000, -1)
    counter = NumpyAllocationCounter()
    for k, ch in enumerate(chs):
        ref.close(200_000, 260_000, 300_000, -1)
        want = ref.channel_variance(k, ch.amp_var, ch.info).copy()
        with counter:
            got.close(200_000, 260_000, 300_000, -1)
            v = got.channel_variance(k, ch.amp_var, ch.info)
        assert v is got.var and v.tobytes() == want.tobytes()
    assert counter.count == 0
    with pytest.raises(TypeError):
        COMPILED.ext.SharedBaselinesCore(np.zeros(3), np.zeros(COMPILED.ext.SB_NF), np.zeros(3))


@pytest.mark.parametrize("mode", ["bound", "ignore", "apart"])
def test_a_decisions_predicted_and_chained_variances_give_the_reference_bits(mode):
    """``predicted`` (a decision's variance of the next pulse) and ``chained`` (a pulse in flight's),
    one compiled call each, give the reference's bits: the previous pulse back to back, at random
    gaps, overlapping, far, none (``prev_end`` 0 or less); the bound on, off and kept apart; on a
    period whose nominal ``n_b`` is odd. Catches a dropped ``apart`` term, a before span taken from
    the wrong edge, the ``prev_end`` test inverted, ``n_base`` not carried to the kernel."""
    rng = np.random.default_rng(11)
    for per in (float(PER), 1e6 / 98.0):
        ref, got = _pair(mode != "ignore", mode == "apart", per)
        assert (got.n_base, got.apart) == (ref.n_base, ref.apart)
        for i in range(300):
            start = 200_000 + int(rng.integers(0, 10 ** 6))
            prev = int(rng.choice([start - GAP, start - GAP - BASE - GUARD, start - int(rng.integers(0, 3 * GAP)),
                                   start + 5_000, 0, -7, start - 10 ** 6]))
            v = float(rng.random() * 1e-15)
            a, b = ref.predicted(v, start, prev), got.predicted(v, start, prev)
            assert a == b and type(b) is float, (i, start, prev)
            assert ref.chained(v) == got.chained(v)
        # independent: back to back, the sides even: sigma^2 / n_b more than the amplitude's (both
        # sides shared), half that kept apart (the before side only), nothing with the bound off
        want = {"bound": SIGMA ** 2 / ref.n_base, "apart": SIGMA ** 2 / (2 * ref.n_base), "ignore": 0.0}[mode]
        assert got.predicted(1e-16, 300_000, 300_000 - GAP) - 1e-16 == pytest.approx(want, rel=1e-9, abs=1e-30)
