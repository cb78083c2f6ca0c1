"""The receive stage's budget: at most ``rx_frames_per_tick`` frames decoded and routed in one
tick, the rest kept in order for the next ticks and counted, and a queue beyond
``rx_queue_bytes`` dropped and counted. References are the frames the test builds."""
import pytest

from coiltrack.firmware.config import ConfigError, FirmwareConfig
from coiltrack.firmware.receive import Receiver
from coiltrack.protocol import MSG, FrameDecoder, encode_frame
from coiltrack.protocol.schema import pack_stamp

from .test_receive_compact import _Port


class _Sink:
    def __init__(self):
        self.mag = []

    def on_message(self, msg, now):
        pass

    def on_mag(self, msg, lsb):
        self.mag.append((now_tick[0], msg.node, msg.t_us))


now_tick = [0]


def _receiver(k, queue_bytes=16384):
    port, sink = _Port(), _Sink()
    r = Receiver(port, FrameDecoder(), [], None, sink, sink, None, frames_per_tick=k, queue_bytes=queue_bytes)
    return r, port, sink


def _frames(n, t_us=1_000_000):
    return [encode_frame(MSG["MAG_PACKED"](16 + i, i, -i, 2 * i, pack_stamp(t_us)), i & 0xFF, 16 + i) for i in range(n)]


def _run(r, ticks):
    for t in range(ticks):
        now_tick[0] = t
        r.step(1_000_000 + 1000 * t)


def test_sixteen_frames_take_two_ticks_of_eight_in_order():
    """16 sensors' samples of one instant, one read: 8 routed in the first tick and 8 in the second,
    in arrival order, none lost or repeated (a bound that dropped the rest, re-fed the queue twice
    or reordered it fails here); 8 counted as deferred once."""
    r, port, sink = _receiver(8)
    port.data = b"".join(_frames(16))
    _run(r, 3)
    assert [(t, n) for t, n, _ in sink.mag] == [(0, 16 + i) for i in range(8)] + [(1, 16 + i) for i in range(8, 16)]
    assert all(ts == 1_000_000 for _, _, ts in sink.mag)
    assert r.deferred == 8 and r.queue_overflows == 0 and r.decoder.frames_bad == 0


def test_partial_frames_and_new_bytes_keep_their_order():
    """A backlog, then more bytes arriving split in the middle of a frame: every frame once, in the
    order sent (appending the new bytes before the queued ones would reorder them)."""
    r, port, sink = _receiver(3)
    data = b"".join(_frames(10))
    cut = len(data) - 7
    port.data = data[:cut]
    _run(r, 1)
    port.data = data[cut:]
    for t in range(1, 6):
        now_tick[0] = t
        r.step(1_000_000 + 1000 * t)
    assert [n for _, n, _ in sink.mag] == [16 + i for i in range(10)]
    assert [t for t, _, _ in sink.mag] == [0, 0, 0, 1, 1, 1, 2, 2, 2, 3]
    assert r.decoder.frames_bad == 0


def test_no_bound_routes_everything_at_once():
    r, port, sink = _receiver(0)
    port.data = b"".join(_frames(40))
    _run(r, 1)
    assert len(sink.mag) == 40 and r.deferred == 0


def test_a_queue_beyond_its_bytes_is_dropped_and_counted():
    """A backlog beyond rx_queue_bytes is dropped (a board's RX buffer is finite), counted, and the
    stream resumes with the next frames (an unbounded queue would grow without limit)."""
    r, port, sink = _receiver(1, queue_bytes=1024)
    port.data = b"".join(_frames(100))
    _run(r, 1)
    port.data = b"".join(_frames(100))
    _run(r, 1)
    assert r.queue_overflows == 1
    port.data = b"".join(_frames(2, t_us=1_004_000))
    n0 = len(sink.mag)
    _run(r, 3)
    assert [ts for _, _, ts in sink.mag[n0:]] == [1_004_000, 1_004_000]


@pytest.mark.parametrize("key,value", [("rx_frames_per_tick", -1), ("rx_frames_per_tick", 1.5),
                                       ("rx_queue_bytes", 100), ("rx_queue_bytes", True)])
def test_bad_budget_values_are_refused_by_name(key, value):
    with pytest.raises(ConfigError, match=key):
        FirmwareConfig().with_keys(**{key: value}).validate()
