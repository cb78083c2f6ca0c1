"""A magnetometer sample's way into its sensor channel (``SensorChannel.push`` with
``SampleRing.push``) on the compiled core (``core/src/multi.c`` ``ct_sample_push``, glue
``py_multi.c`` ``SamplePush``) against the Python reference: the same ring (times, fields, flags,
head, count, latest time), the same refusals and counters, and the same windows read from it.

The stream mixes what a live link gives (integer counts, flip and saturation bits, jitter, gaps,
the ring wrapped many times) with what the reference refuses (a repeated or older time, a time
beyond int64, a NaN or infinite field from a calibrated, float, sample) and what the kernel hands
back to the reference (a float or numpy count, a time that is no int). An independent check: the
ring's newest rows against the pushed values scaled by hand. Seeded; skips without the extension."""
import math

import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.measure.pulse import NO_TIME_US, SAMPLE_FLIP, SAMPLE_SATURATED, SampleRing
from coiltrack.firmware.measure.windows import SensorChannel

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
COMPILED = core.load("compiled")
LSB = 5e-9


class _Sample:
    def __init__(self, t, x, y, z, flip):
        self.t_us, self.x, self.y, self.z, self.flip = t, x, y, z, flip


def _pair(capacity=None):
    kw = {"pulse": {"ring_capacity": capacity}} if capacity else {}
    cfg = FirmwareConfig().with_(link={"sensor_ids": (16,)}, **kw).validate()
    ref = SensorChannel(16, cfg, core.PYTHON)
    got = SensorChannel(16, cfg, COMPILED)
    assert ref.push.__func__ is SensorChannel.push
    assert got.push.__func__ is SensorChannel._push_compiled
    return ref, got


def _same(ref, got, case):
    a, b = ref.ring, got.ring
    np.testing.assert_array_equal(b.t, a.t, err_msg=str(case))
    np.testing.assert_array_equal(b.b, a.b, err_msg=str(case))          # NaN-free: only pushed rows
    np.testing.assert_array_equal(b.flags, a.flags, err_msg=str(case))
    np.testing.assert_array_equal(b.hc, a.hc, err_msg=str(case))
    assert (len(b), b.latest_t_us, b.rejected) == (len(a), a.latest_t_us, a.rejected), case
    assert (got.samples, got.changes) == (ref.samples, ref.changes), case


def _stream(rng, n):
    """n samples: mostly a live link's, with refused and handed-back ones among them."""
    t, flip = int(rng.integers(-10_000, 10_000)), 0
    for k in range(n):
        t += int(rng.integers(8_000, 8_700)) if rng.random() > 0.02 else int(rng.integers(15_000, 40_000))
        if rng.random() < 0.01:
            flip ^= 1
        x, y, z = (int(v) for v in rng.integers(-(1 << 20), 1 << 20, size=3))
        fl = flip | (2 if rng.random() < 0.02 else 0) | (4 if rng.random() < 0.01 else 0)
        r = rng.random()
        ts = t
        if r < 0.02:
            ts = t - int(rng.integers(0, 30_000))          # not later than the latest: refused
        elif r < 0.025:
            ts = 1 << 63                                   # beyond int64: refused (by the reference)
        elif r < 0.03:
            x = float(x) + 0.25                            # a calibrated sample: handed back, pushed
        elif r < 0.035:
            y = math.nan if rng.random() < 0.5 else -math.inf    # ... refused as not finite
        elif r < 0.04:
            z = np.int64(z)                                # a numpy count: handed back
        elif r < 0.042:
            x = (1 << 60) + 1                              # a count beyond 2**53: handed back
        yield k, _Sample(ts, x, y, z, fl)


def test_push_equals_the_reference_on_a_mixed_stream():
    """6000 samples through both cores, the ring wrapped ~40 times: after every sample the same
    ring, state and counters; the refusals counted alike. Catches a count not kept (a refused sample
    uncounted), the flip and saturation bits swapped, a wrap off by one, the latest time not kept or
    the product taken in another order."""
    rng = np.random.default_rng(30)
    ref, got = _pair(capacity=150)
    for k, s in _stream(rng, 6000):
        ref.push(s, LSB)
        got.push(s, LSB)
        _same(ref, got, k)
    assert ref.ring.rejected > 100 and ref.samples == 6000


def test_pushed_rows_are_the_scaled_counts():
    """Independent of the reference: the newest row holds count * LSB per axis, the flags bit0
    saturated (flip bit1 of the message) and bit1 the flip state (bit0), the time the sample's."""
    _, got = _pair()
    got.push(_Sample(1000, 3, -7, 1 << 20, 3), LSB)
    got.push(_Sample(2000, -1, 0, 12345, 0), LSB)
    r = got.ring
    s0, s1 = r.peek(1), r.peek(0)
    assert (r.t[s0], r.t[s1], len(r), r.latest_t_us) == (1000, 2000, 2, 2000)
    assert list(r.b[s0]) == [3 * LSB, -7 * LSB, (1 << 20) * LSB]
    assert list(r.b[s1]) == [-LSB, 0.0, 12345 * LSB]
    assert r.flags[s0] == SAMPLE_SATURATED | SAMPLE_FLIP and r.flags[s1] == 0
    got.push(_Sample(2000, 1, 1, 1, 0), LSB)            # the same time again: refused, counted
    assert (len(r), r.rejected, got.samples, got.changes) == (2, 1, 3, 3)


def test_ring_state_array_is_the_ring():
    """SampleRing keeps head, count, latest and rejected in ``hc``: the Ring operations (slot, peek,
    index_at_or_after, drop_newer_than, clear) see what the pushes wrote."""
    r = SampleRing(4)
    assert (len(r), r.latest_t_us, r.oldest_t_us) == (0, NO_TIME_US, NO_TIME_US)
    for k in range(6):
        r.push(100 * (k + 1), k, 0.0, 0.0, False, 0)
    assert list(r.hc) == [2, 4, 600, 0] and r.full
    assert [r.t[r.slot(i)] for i in range(4)] == [300, 400, 500, 600]
    assert r.index_at_or_after(450) == 2 and r.peek(0) == 1
    r.drop_newer_than(450)
    assert (len(r), r._head) == (2, 0)
    r.clear()
    assert (len(r), r.latest_t_us) == (0, NO_TIME_US)
    r.push(-5, 1.0, 2.0, 3.0, True, 1)
    assert (len(r), r.latest_t_us, r.flags[0]) == (1, -5, SAMPLE_SATURATED | SAMPLE_FLIP)
