"""The IMU ring's push on the compiled core (``core/src/fusimu.c`` ``ct_imu_ring_push``, glue
``ext.ImuPush``) against its Python reference (``measure/imu.py`` ``ImuRing.push``): the same
times, the same rows bit for bit (a count times its LSB, for integer counts as received and for
the floats of an IMU_DELTA pair's steps), the same head and count, and the same refusals and
overwrites counted (a sample not newer than the last, a full ring's oldest overwritten), and the
rows against the independent reference ``counts * LSB`` computed by numpy. Seeded; skips where
the extension is not built."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.measure.imu import ImuRing
from coiltrack.firmware.receive import ImuRecord
from coiltrack.protocol.schema import ACC_LSB, GYR_LSB

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")


def _record(t, v):
    r = ImuRecord()
    r.t_us = t
    r.ax, r.ay, r.az, r.gx, r.gy, r.gz = v
    return r


def test_compiled_push_matches_the_reference():
    rng = np.random.default_rng(7)
    ref, got = ImuRing(8, core.PYTHON), ImuRing(8, core.load("compiled"))
    assert ref.push.__func__ is ImuRing.push and not hasattr(got.push, "__func__")
    t = 1_000
    expect = []
    for i in range(200):
        step = int(rng.integers(-3000, 12000))          # some not newer: refused
        t += step
        if i % 2:
            v = tuple(int(x) for x in rng.integers(-32768, 32768, size=6))    # counts as received
        else:
            v = tuple(float(x) for x in rng.normal(0.0, 3000.0, size=6))     # an IMU_DELTA pair's means
        msg = _record(t, v)
        ref.push(msg)
        got.push(msg)
        if t > (expect[-1][0] if expect else -(1 << 62)):
            expect.append((t, v))
        assert (ref.last_t, ref.dropped, ref.received) == (got.last_t, got.dropped, got.received), i
        assert (len(ref), ref.slot(0) if len(ref) else -1) == (len(got), got.slot(0) if len(got) else -1), i
        np.testing.assert_array_equal(ref.t, got.t)
        np.testing.assert_array_equal(ref.d, got.d)      # bit for bit
    # refusals and overwrites both seen; the ring holds the newest 8 samples taken
    assert got.received == len(expect) and got.dropped > len(expect) - 8 + 20 and len(got) == 8
    last = expect[-8:]
    out = [0.0] * 6
    lsb = np.array([ACC_LSB] * 3 + [GYR_LSB] * 3)
    for t_k, v in last:
        assert got.pop_sample(out) == t_k
        np.testing.assert_array_equal(out, np.array(v, dtype=float) * lsb)    # the independent reference
    assert got.pop_sample(out) == -1


def test_compiled_push_refuses_a_bad_record():
    """A record without a field or with a non-number is refused with a Python error, the ring unchanged."""
    got = ImuRing(4, core.load("compiled"))
    got.push(_record(10, (1, 2, 3, 4, 5, 6)))
    bad = _record(20, (1, 2, 3, 4, 5, 6))
    bad.gz = "x"
    with pytest.raises(TypeError):
        got.push(bad)
    with pytest.raises(AttributeError):
        got.push(object())
    assert (got.received, got.dropped, len(got), got.last_t) == (1, 0, 1, 10)
