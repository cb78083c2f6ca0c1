"""The compiled POSE frame (firmware_py/core/src/frame.c, ``ct_pose_frame``) against its Python
reference (transmit.Transmitter.pose through protocol.framing.encode_frame): the same bytes, the
same refusals, one frame sequence shared with the other messages. Seeded; skips without the
extension."""
import math
import random

import pytest

from coiltrack.firmware.transmit import F32_MAX, PoseReport
from coiltrack.protocol import MSG, FrameDecoder
from coiltrack.protocol.framing import encode_frame
from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")


def _send(t, node, t_us, px, py, pz, qw, qx, qy, qz, v0, v1, v2, v3, v4, v5, status, quality=255):
    """``t.pose`` of a :class:`PoseReport` holding these values."""
    r = PoseReport(node)
    r.t_us, r.status, r.quality = t_us, status, quality
    r.p[:] = [px, py, pz]
    r.q[:] = [qw, qx, qy, qz]
    r.var[:] = [v0, v1, v2, v3, v4, v5]
    t.pose(r)


def _values(rng):
    """13 doubles over the f32 range and beyond it, with NaN, infinities, signed zeros and
    subnormals among them."""
    special = [math.nan, math.inf, -math.inf, 0.0, -0.0, 1e-45, 1e-310, 3.4028234663852886e38, 3.0e38, 1e39,
               -1e39, 3.4028235677973366e38]
    out = []
    for _ in range(13):
        if rng.random() < 0.15:
            out.append(rng.choice(special))
        else:
            out.append(rng.uniform(-1.0, 1.0) * 10.0 ** rng.uniform(-40, 38.5))
    return out


def test_pose_frames_are_the_python_bytes(transmitter_pair):
    """2000 POSEs with random fields (node, 64-bit time, status, quality over their ranges, floats
    over the f32 range and past it, NaN and infinite): the same frames (bytes), the same tx
    errors where struct.pack refuses a value, the same pose counters."""
    rng = random.Random(3)
    ref, got = transmitter_pair()
    for _ in range(2000):
        v = _values(rng)
        node = rng.choice([0, 1, 255, rng.randrange(256)])
        t_us = rng.choice([0, (1 << 64) - 1, rng.randrange(1 << 50)])
        status = rng.choice([0, POSE_VALID, POSE_VALID | POSE_FUSED, 0xFFFF, rng.randrange(1 << 16)])
        quality = rng.randrange(256)
        _send(ref, node, t_us, *v, status, quality)
        _send(got, node, t_us, *v, status, quality)
    assert got.port.frames == ref.port.frames
    assert (got.tx_errors, got.poses, got.fused_poses) == (ref.tx_errors, ref.poses, ref.fused_poses)
    assert 0 < ref.tx_errors < 2000 and ref.poses > 0


def test_variances_are_clamped_as_the_reference(transmitter_pair):
    """A NaN or huge variance leaves as F32_MAX, as ``_f32`` sends it (read back by the decoder)."""
    ref, got = transmitter_pair()
    for t in (ref, got):
        _send(t, 3, 10, 0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0, math.nan, 1e300, math.inf, 2.5e-7, -1.0, 3.0e38,
               POSE_VALID, 200)
    assert got.port.frames == ref.port.frames
    msg = FrameDecoder().feed(got.port.frames[0])[0]
    assert msg.ID == MSG["POSE"].ID
    f32max = float(__import__("numpy").float32(F32_MAX))
    assert (msg.var_px, msg.var_py, msg.var_pz) == (f32max, f32max, f32max) and msg.var_rz == f32max
    assert msg.var_ry == -1.0


def test_out_of_range_integers_are_refused_and_counted(transmitter_pair):
    """A node above 255, a negative time, a status above 16 bits or a quality above 255: no
    frame, one tx error, the sequence number not spent (as FrameEncoder on struct's error)."""
    ref, got = transmitter_pair()
    good = (0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4)
    for args in ((256, 5, *good, 1, 9), (1, -1, *good, 1, 9), (1, 5, *good, 1 << 16, 9), (1, 5, *good, 1, 256),
                 (1, 1 << 70, *good, 1, 9), (1, 5, *good, 1, 9)):
        _send(ref, *args)
        _send(got, *args)
    assert got.tx_errors == ref.tx_errors == 5
    assert got.port.frames == ref.port.frames and len(ref.port.frames) == 1
    assert got.port.frames[0] == encode_frame(MSG["POSE"](1, 5, *good, 1, 9), 0, 7)


def test_one_sequence_with_the_other_messages_and_a_failing_link(transmitter_pair):
    """POSEs, events and heartbeats interleaved over more than 256 frames, every third write
    failing: the same bytes in the same order and the same errors as the Python transmitter (the
    sequence number wraps at 256 and advances over a failed write, as FrameEncoder's)."""
    rng = random.Random(5)
    ref, got = transmitter_pair(fail_every=3)
    for k in range(700):
        r = rng.random()
        for t in (ref, got):
            if r < 0.7:
                _send(t, 2, 1000 * k, 0.1 * k, -0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 1e-6, 2e-6, 3e-6, 1e-4, 2e-4, 3e-4,
                       POSE_VALID, 128)
            elif r < 0.85:
                t.event(5, k)
            else:
                t.step(100_000 * k)
    assert got.port.frames == ref.port.frames
    assert got.tx_errors == ref.tx_errors > 0
