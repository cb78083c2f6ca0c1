"""The receive stage turns protocol v2's compact samples into the full ones:
MAG_PACKED's 14-bit stamp restored against the tick's clock, an IMU_DELTA pair
into the interval's mean rate and specific force at its middle. References are
the integers the test builds (no firmware code computes them)."""
import numpy as np
import pytest

from coiltrack.firmware.receive import Receiver
from coiltrack.protocol import MSG, FrameDecoder, encode_frame
from coiltrack.protocol.schema import (ACC_LSB, DANG_LSB_RAD, DVEL_LSB_MPS, GYR_LSB, STAMP_DVEL, STAMP_FLIP,
                                       STAMP_LEAD_US, STAMP_SATURATED, STAMP_WRAP_US, pack_stamp, unwrap_stamp)


class _Port:
    def __init__(self):
        self.data = b""

    def read(self):
        d, self.data = self.data, b""
        return d


class _Sink:
    """Records what the receive stage hands on (values copied: the records are reused)."""

    def __init__(self):
        self.mag, self.imu, self.sup = [], [], []

    def on_message(self, msg, now):
        self.sup.append((msg.ID, msg.node, msg.t_us))

    def on_imu(self, msg, now):
        self.imu.append((msg.node, msg.t_us, msg.ax, msg.ay, msg.az, msg.gx, msg.gy, msg.gz))

    def on_mag(self, msg, lsb):
        self.mag.append((msg.node, msg.t_us, msg.x, msg.y, msg.z, msg.flip))


def _receiver(interval_us=100_000, step_us=100_000):
    port, sink = _Port(), _Sink()
    r = Receiver(port, FrameDecoder(), [], None, sink, sink, None, imu_interval_us=interval_us,
                 imu_step_us=step_us)
    return r, port, sink


def test_unwrap_restores_the_time_over_the_whole_window():
    """Every time in (now + lead - 131072 us, now + lead] comes back to the 8 us it was rounded
    to, across wraps of the 14 bits (a receiver window off by one wrap is 131 ms wrong)."""
    rng = np.random.default_rng(5)
    for _ in range(2000):
        now = int(rng.integers(200_000, 10 ** 12))
        t = now + STAMP_LEAD_US - int(rng.integers(0, STAMP_WRAP_US - 8))
        t8 = (t + 4) // 8 * 8
        if t8 > now + STAMP_LEAD_US:
            continue
        assert unwrap_stamp(pack_stamp(t), now) == t8


def test_mag_packed_becomes_a_mag_sample_with_its_time_and_bits():
    """The stamp's bit 15 is the set state and bit 14 saturation: a swapped mapping would give
    flip 2 / 1. The time is restored 30 ms after the sample and across a wrap boundary."""
    r, port, sink = _receiver()
    t = 5 * STAMP_WRAP_US - 3000                         # 3 ms before a wrap of the 14 bits
    port.data = encode_frame(MSG["MAG_PACKED"](17, 100, -200, 300, pack_stamp(t) | STAMP_FLIP), 0, 17) + \
        encode_frame(MSG["MAG_PACKED"](17, 1, 2, 3, pack_stamp(t + 8336) | STAMP_SATURATED), 1, 17)
    r.step(t + 8336 + 30_000)
    assert sink.mag == [(17, (t + 4) // 8 * 8, 100, -200, 300, 1), (17, (t + 8336 + 4) // 8 * 8, 1, 2, 3, 2)]
    assert sink.sup[0] == (MSG["MAG_SAMPLE"].ID, 17, (t + 4) // 8 * 8)


def _pair(node, sums_a, sums_v, end, seq):
    return (encode_frame(MSG["IMU_DELTA"](node, *sums_a, pack_stamp(end)), seq, node)
            + encode_frame(MSG["IMU_DELTA"](node, *sums_v, pack_stamp(end) | STAMP_DVEL), seq + 1, node))


def test_imu_delta_pair_becomes_the_interval_mean_at_its_middle():
    """The frames carry running sums: the first pair anchors them, the next gives the differences
    dtheta = (400, -80, 12) x 5e-5 rad and dv = (1000, 0, 9810) x 1e-4 m/s over T = 100 ms (the
    time between the stamps). Rate = dtheta / T and specific force = dv / T in GYR_LSB / ACC_LSB
    counts, stamped T/2 before the interval's end (one step per interval here). The sums wrap:
    32700 + 400 is -32436. A receiver that took the frame's values as the deltas, or did not
    unwrap, is off by the whole sum."""
    r, port, sink = _receiver(interval_us=90_000, step_us=200_000)
    e1, e2 = 2_000_000, 2_100_000
    a0, v0 = (32700, 5, -7), (-100, 30000, 1)
    a1 = tuple((x + d + 32768) % 65536 - 32768 for x, d in zip(a0, (400, -80, 12)))
    v1 = tuple((x + d + 32768) % 65536 - 32768 for x, d in zip(v0, (1000, 0, 9810)))
    port.data = _pair(20, a0, v0, e1, 0) + _pair(20, a1, v1, e2, 2)
    r.step(e2 + 2000)
    assert len(sink.imu) == 1 and r.imu_delta_anchors == 1
    node, t, ax, ay, az, gx, gy, gz = sink.imu[0]
    T = 0.1
    assert node == 20 and t == e2 - round(T * 5e5)
    np.testing.assert_allclose([gx, gy, gz], np.array([400, -80, 12]) * DANG_LSB_RAD / T / GYR_LSB, rtol=1e-12)
    np.testing.assert_allclose([ax, ay, az], np.array([1000, 0, 9810]) * DVEL_LSB_MPS / T / ACC_LSB, rtol=1e-12)


def test_imu_delta_pair_is_given_back_in_the_filters_steps():
    """At imu_rate_hz = 120 a 100 ms pair becomes 12 equal samples at the middles of 12 equal steps
    of (t_end - T, t_end]: their rotation sums to the delta angle (a receiver that stamped them
    at the interval's end, or emitted one sample, shifts the motion by 50 ms or starves the
    strapdown of steps). A lost pair: the next one covers 200 ms in 24 steps, nothing lost."""
    r, port, sink = _receiver(interval_us=100_000, step_us=1e6 / 120)
    e1, e2, e4 = 3_000_000, 3_100_000, 3_300_000
    for data, end in ((_pair(21, (0, 0, 0), (0, 0, 0), e1, 0), e1), (_pair(21, (600, 0, -300), (0, 0, 981), e2, 2), e2),
                      (_pair(21, (1800, 0, -900), (0, 0, 2943), e4, 6), e4)):
        port.data = data
        r.step(end + 1000)                       # each pair 1 ms after its end (stamps restore within 114 ms)
    first, second = sink.imu[:12], sink.imu[12:]
    assert len(first) == 12 and len(second) == 24
    step = 0.1 / 12
    assert [t for _, t, *_ in first] == [e1 + round((i + 0.5) * step * 1e6) for i in range(12)]
    assert [t for _, t, *_ in second] == [e2 + round((i + 0.5) * step * 1e6) for i in range(24)]
    for part, da, dv in ((first, (600, 0, -300), (0, 0, 981)), (second, (1200, 0, -600), (0, 0, 1962))):
        dtheta = sum(np.array([gx, gy, gz]) * GYR_LSB * step for *_, gx, gy, gz in part)
        np.testing.assert_allclose(dtheta, np.array(da) * DANG_LSB_RAD, rtol=1e-12, atol=1e-15)
        dvel = sum(np.array([ax, ay, az]) * ACC_LSB * step for _, _, ax, ay, az, *_ in part)
        np.testing.assert_allclose(dvel, np.array(dv) * DVEL_LSB_MPS, rtol=1e-12, atol=1e-15)


def test_unpaired_deltas_are_counted_and_dropped():
    """A delta velocity whose angle was lost (or carries another stamp) is not used: mixing two
    intervals would turn into a wrong rate."""
    r, port, sink = _receiver()
    port.data = encode_frame(MSG["IMU_DELTA"](20, 1, 2, 3, pack_stamp(1_000_000)), 0, 20) + \
        encode_frame(MSG["IMU_DELTA"](20, 1, 2, 3, pack_stamp(1_100_000) | STAMP_DVEL), 1, 20) + \
        encode_frame(MSG["IMU_DELTA"](20, 1, 2, 3, pack_stamp(1_200_000) | STAMP_DVEL), 2, 20)
    r.step(1_201_000)
    assert sink.imu == [] and r.imu_delta_unpaired == 2


class _Quiet:
    def quiet(self, t):
        return True


def test_compass_sample_is_the_one_nearest_the_imu_time():
    """IMU steps given back from a pair reach the orientation filter up to 100 ms after the
    magnetometer samples of their time: the compass sample is the one nearest the step's time
    (rule stated in the test: argmin |t - t_imu| over the ring), not the newest (which is up to
    100 ms away and was refused, so the source module lost its compass and its heading drifted
    10 deg), and not one far ahead of the step."""
    from coiltrack.firmware.measure.pulse import SampleRing
    from coiltrack.firmware.track.burst_fusion import quiet_sample

    ring = SampleRing(32)
    times = [1_000_000 + round(k * 1e6 / 120) for k in range(20)]
    for t in times:
        ring.push(t, 1e-5, 0.0, 4e-5, False, 0)
    max_age = int(2e6 / 120) * 2
    for t_imu in (1_010_000, 1_051_234, 1_100_000, 1_150_000):
        slot = quiet_sample(ring, 0, t_imu, max_age, _Quiet())
        want = min(times, key=lambda t: abs(t - t_imu))
        assert slot >= 0 and ring.tv[slot] == want, t_imu
    assert quiet_sample(ring, times[-1], 1_150_000, max_age, _Quiet()) == -1     # nothing newer than after_t
    assert quiet_sample(ring, 0, 900_000, max_age, _Quiet()) == -1              # nearest too far away
