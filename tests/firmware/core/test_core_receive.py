"""The compiled IMU decode (firmware_py/core/src/imu.c: ``ct_imu_clipped``, ``ct_imu_delta``)
against its Python reference (receive._clipped, Receiver._delta): a random stream of IMU_DELTA
frames of several nodes through both receivers gives the same IMU steps (times and values bit
for bit), the same counters and the same drops; clipped samples are found alike. Seeded; skips
without the extension."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.receive import Receiver, _clipped
from coiltrack.protocol import MSG, FrameDecoder, encode_frame
from coiltrack.protocol.schema import IMU_CLIP_COUNTS, STAMP_DVEL, STAMP_SATURATED, STAMP_WRAP_US, pack_stamp

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

_DELTA = MSG["IMU_DELTA"]
_SAMPLE = MSG["IMU_SAMPLE"]


class _Port:
    def __init__(self):
        self.data = b""

    def read(self):
        d, self.data = self.data, b""
        return d


class _Sink:
    def __init__(self):
        self.imu, self.sup = [], []

    def on_message(self, msg, now):
        self.sup.append((msg.ID, msg.node, msg.t_us))

    def on_imu(self, msg, now):
        self.imu.append((msg.node, msg.t_us, msg.ax, msg.ay, msg.az, msg.gx, msg.gy, msg.gz))

    def on_imu_saturated(self, node, now):
        self.sup.append(("saturated", node, now))


def _receiver(c):
    port, sink = _Port(), _Sink()
    r = Receiver(port, FrameDecoder(), [], None, sink, sink, None, imu_interval_us=100_000,
                 imu_step_us=1e6 / 120.0, core=c)
    return r, port, sink


def _stream(rng, nodes=(3, 9, 200)):
    """(frames, now) per tick: IMU_DELTA pairs at 10 Hz with jitter, 16-bit sum wraps, a lost
    frame now and then (unpaired), saturated bits, a long gap (anchor only), stamps across the
    14-bit wrap, and clipped / ordinary IMU_SAMPLEs between them."""
    sums = {n: np.zeros(6, dtype=np.int64) for n in nodes}
    t = {n: int(rng.integers(0, STAMP_WRAP_US)) + 1_000_000 for n in nodes}
    seq = 0
    out = []
    for k in range(400):
        frames = b""
        now = 0
        for n in nodes:
            gap = int(rng.choice([100_000, 100_008, 99_992, 200_000, 450_000], p=[0.6, 0.15, 0.15, 0.05, 0.05]))
            t[n] += gap
            sums[n] += rng.integers(-40_000, 40_000, 6)
            s = ((sums[n] + 32768) % 65536) - 32768
            stamp = pack_stamp(t[n])
            sat = STAMP_SATURATED if rng.random() < 0.05 else 0
            a = _DELTA(n, int(s[0]), int(s[1]), int(s[2]), stamp | sat)
            v = _DELTA(n, int(s[3]), int(s[4]), int(s[5]), stamp | STAMP_DVEL | (STAMP_SATURATED if rng.random() < 0.03 else 0))
            r = rng.random()
            if r < 0.05:
                frames += encode_frame(v, seq, n)           # the angle lost
            elif r < 0.1:
                frames += encode_frame(a, seq, n)           # the velocity lost
            else:
                frames += encode_frame(a, seq, n) + encode_frame(v, seq + 1, n)
            seq = (seq + 2) & 0xFF
            vals = [int(x) for x in rng.integers(-40000, 40000, 6)]
            if rng.random() < 0.3:
                vals[int(rng.integers(6))] = int(rng.choice([IMU_CLIP_COUNTS, -IMU_CLIP_COUNTS, -32768]))
            vals = [max(-32768, min(32767, x)) for x in vals]
            frames += encode_frame(_SAMPLE(n, t[n], *vals), seq, n)
            now = max(now, t[n] + int(rng.integers(1000, 20_000)))
        out.append((frames, now))
    return out


def test_imu_stream_gives_the_same_steps_and_counters():
    """400 ticks of three nodes' IMU_DELTA pairs and IMU_SAMPLEs through a Python-core and a
    compiled-core receiver: the same IMU records handed on (times and values to the bit), the same
    supervisor calls and the same counters (pairs, unpaired, anchors, saturated)."""
    rng = np.random.default_rng(12)
    ref, rp, rs = _receiver(core.PYTHON)
    got, gp, gs = _receiver(core.load("compiled"))
    assert (ref.core, got.core) == ("python", "compiled")
    for frames, now in _stream(rng):
        rp.data = gp.data = frames
        ref.step(now)
        got.step(now)
    assert gs.imu == rs.imu and gs.sup == rs.sup
    assert got.counters() == ref.counters()
    c = ref.counters()
    assert c["rx_imu_deltas"] > 100 and c["rx_imu_delta_unpaired"] > 0 and c["rx_imu_delta_anchors"] > 0
    assert c["imu_saturated"] > 0 and c["imu_saturated_pairs"] > 0


def test_clipped_matches_the_reference():
    """ct_imu_clipped against _clipped on every axis at and around the clip code."""
    rng = np.random.default_rng(1)
    for _ in range(3000):
        vals = [int(x) for x in rng.integers(-32768, 32768, 6)]
        k = int(rng.integers(6))
        vals[k] = int(rng.choice([32766, 32767, -32767, -32766, -32768, 0]))
        msg = _SAMPLE(1, 5, *vals)
        assert _core.imu_clipped(msg) == _clipped(msg), vals
