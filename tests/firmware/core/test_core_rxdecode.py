"""The receive stage's compiled frame decode (firmware_py/core/src/rxdecode.c through
``firmware.rxdecode.CompiledFrameDecoder``) against its reference, the protocol's Python
``FrameDecoder``: the golden vectors decode to their examples; a seeded stream of every message
with corrupt frames of every kind (flipped bits, lost bytes, stray zeros, unknown ids, bad flags,
wrong lengths, overlong runs), cut at random, gives the same messages and the same counters;
the receiver routes the same records to the same stages with either decoder. Seeded; skips
without the extension."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.receive import Receiver
from coiltrack.firmware.rxdecode import ROWS, CompiledFrameDecoder, frame_decoder
from coiltrack.protocol import MSG, FrameDecoder, encode_frame
from coiltrack.protocol.examples import EXAMPLES, SIGNING_KEY, SIGNING_LINK_ID
from coiltrack.protocol.framing import MAX_ENCODED, build_frame, cobs_encode, crc16
from coiltrack.protocol.golden import GOLDEN_DIR
from coiltrack.protocol.schema import (BY_ID, IMU_CLIP_COUNTS, STAMP_FLIP, STAMP_SATURATED, STAMP_WRAP_US,
                                       pack_stamp, unwrap_stamp)
from coiltrack.protocol.signing import Signer

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

_PACKED, _MAG, _IMU = MSG["MAG_PACKED"], MSG["MAG_SAMPLE"], MSG["IMU_SAMPLE"]


def _both(chunks, now=0):
    """Both decoders over the same chunks: (reference messages, compiled messages, both counters)."""
    ref, got = FrameDecoder(), CompiledFrameDecoder(_core)
    a, b = [], []
    for c in chunks:
        a += ref.feed(c)
        b += got.feed(c, now)
    return a, b, ref.counters(), got.counters()


def test_golden_vectors_decode_to_their_examples():
    """Every serial golden vector (protocol/golden/serial, the signed ones included), whole and
    one byte at a time: the example it was made from, on both decoders, no bad frame."""
    files = sorted(GOLDEN_DIR.joinpath("serial").glob("*.bin"))
    assert len(files) >= 18
    for f in files:
        data = f.read_bytes()
        want = EXAMPLES[f.name.split(".")[0]].msg
        for chunks in ([data], [data[i:i + 1] for i in range(len(data))]):
            a, b, ca, cb = _both(chunks)
            assert a == b == [want], f.name
            assert ca == cb and cb["frames_ok"] == 1 and cb["frames_bad"] == 0, f.name


def _random_message(rng):
    k = rng.integers(5)
    node = int(rng.integers(0, 256))
    if k == 0:
        return _PACKED(node, *(int(x) for x in rng.integers(-32768, 32768, 3)), int(rng.integers(0, 65536)))
    if k == 1:
        return _MAG(node, int(rng.integers(0, 2**63)), *(int(x) for x in rng.integers(-32768, 32768, 3)),
                    int(rng.integers(0, 256)))
    if k == 2:
        vals = [int(x) for x in rng.integers(-32768, 32768, 6)]
        if rng.random() < 0.3:
            vals[int(rng.integers(6))] = int(rng.choice([IMU_CLIP_COUNTS, -IMU_CLIP_COUNTS, -32768, 32766]))
        t = int(rng.integers(0, 2**63)) if rng.random() < 0.9 else 2**63 + int(rng.integers(0, 2**63))
        return _IMU(node, t, *vals)
    return list(EXAMPLES.values())[int(rng.integers(len(EXAMPLES)))].msg


def _corrupt(rng, frame: bytes, src: int, seq: int) -> bytes:
    """One frame, most as sent, the others damaged in one of the ways a link damages them."""
    r = rng.random()
    if r < 0.6:
        return frame
    body = bytearray(frame[:-1])
    kind = int(rng.integers(9))
    if kind == 0:                                   # a flipped bit: CRC (or COBS, or length)
        i = int(rng.integers(len(body)))
        body[i] ^= 1 << int(rng.integers(8))
        if body[i] == 0:
            body[i] = 0x55
    elif kind == 1:                                 # a lost byte
        del body[int(rng.integers(len(body)))]
    elif kind == 2:                                 # a stray delimiter cuts the frame in two
        body.insert(int(rng.integers(len(body))), 0)
    elif kind == 3:                                 # garbage longer than any frame: an overflow
        body = bytearray(int(x) for x in rng.integers(1, 256, MAX_ENCODED + int(rng.integers(1, 200))))
    elif kind in (4, 5, 6):                         # a valid CRC over an unknown id, bad flags, a wrong length
        raw = bytearray(build_frame(_PACKED(1, 2, 3, 4, 5), seq, src))
        if kind == 4:
            raw[4] = int(rng.choice([i for i in range(256) if i not in BY_ID]))
        elif kind == 5:
            raw[1] = int(rng.choice([2, 4, 0x80, 3]))
        else:
            raw[0] += 1
            raw[5:5] = b"\x07"
        end = len(raw) - 2
        crc = crc16(bytes([BY_ID.get(raw[4], BY_ID[0x23]).crc_extra]), crc16(bytes(raw[:end])))
        raw[end], raw[end + 1] = crc & 0xFF, crc >> 8
        body = bytearray(cobs_encode(raw))
    elif kind == 7:                                 # a short frame
        body = bytearray(cobs_encode(bytes(int(x) for x in rng.integers(0, 256, int(rng.integers(0, 7))))))
    else:                                           # a COBS block running past the end
        body[-1:] = bytes([0xFE])
        body[0] = min(0xFF, len(body) + 5)
    return bytes(body) + b"\x00"


def _stream(rng, n=3000):
    signer = Signer(SIGNING_KEY, SIGNING_LINK_ID)
    out = bytearray()
    seqs = {}
    for k in range(n):
        msg = _random_message(rng)
        src = int(rng.choice([0, 1, 2, 16, 17, 200]))
        seq = seqs.get(src, 0)
        seqs[src] = (seq + (1 if rng.random() < 0.97 else 2)) & 0xFF       # a lost frame: a gap
        if rng.random() < 0.05:
            frame = cobs_encode(signer.signed_frame(msg, seq, src, timestamp=1000 + k)) + b"\x00"
        else:
            frame = encode_frame(msg, seq, src)
        out += _corrupt(rng, frame, src, seq)
    return bytes(out)


def _cut(rng, data: bytes, most: int = 600):
    i, chunks = 0, []
    while i < len(data):
        n = int(rng.integers(0, most))
        chunks.append(data[i:i + n])
        i += n
    return chunks


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_damaged_stream_gives_the_same_messages_and_counters(seed):
    """3000 frames of every message (5 % signed), 40 % damaged, cut into random reads (empty ones
    and reads longer than the row table included): the same messages in the same order and the
    same counters, every kind of bad frame among them. Catches a check out of parse_frame's order
    (the wrong counter), a resynchronisation that loses the frame after a bad one, an overflow
    counted twice or never, a buffer kept across the delimiter, a wrong sign or byte order in the
    unpacking, and a read cut at the row table's end that drops or repeats a frame."""
    rng = np.random.default_rng(seed)
    data = _stream(rng)
    a, b, ca, cb = _both(_cut(rng, data))
    assert a == b
    assert ca == cb
    for k in ("crc_errors", "framing_errors", "length_errors", "unknown_ids", "overflows", "seq_gaps"):
        assert cb[k] > 0, k
    assert cb["frames_ok"] > 1500


def test_a_read_of_more_frames_than_the_row_table():
    """Five row tables' worth of MAG_PACKED in one read: every frame once, in order."""
    frames = [_PACKED(16 + i % 16, i, -i, 3 * i, i & 0xFFFF) for i in range(5 * ROWS + 3)]
    data = b"".join(encode_frame(m, i & 0xFF, m.node) for i, m in enumerate(frames))
    a, b, ca, cb = _both([data])
    assert a == b == frames and ca == cb


def test_rows_restore_the_packed_stamp():
    """The MAG_PACKED row's time and flip (Receiver._unpack_mag, restored in C) against
    ``unwrap_stamp`` and the stamp's bits, across the 14-bit wrap."""
    rng = np.random.default_rng(5)
    dec = CompiledFrameDecoder(_core)
    for _ in range(500):
        t = int(rng.integers(0, 50 * STAMP_WRAP_US)) * 8
        now = t + int(rng.integers(-16_000, 100_000))
        bits = int(rng.choice([0, STAMP_FLIP, STAMP_SATURATED, STAMP_FLIP | STAMP_SATURATED]))
        stamp = pack_stamp(t) | bits
        assert dec.decode(encode_frame(_PACKED(17, 1, -2, 3, stamp)), 0, now) == 1
        q = dec.rows
        assert (q[1], q[2], q[3], q[4], q[5]) == (17, unwrap_stamp(stamp & 0x3FFF, now), 1, -2, 3)
        assert q[6] == (1 if bits & STAMP_FLIP else 0) | (2 if bits & STAMP_SATURATED else 0)


class _Port:
    def __init__(self):
        self.data = b""

    def read(self):
        d, self.data = self.data, b""
        return d


class _Sink:
    """Supervisor, tracker and schedule in one: what each is handed, as values."""

    def __init__(self):
        self.log = []

    def on_message(self, msg, now):
        self.log.append(("sup", msg.ID, tuple(getattr(msg, f) for f in _fields(msg)), now))

    def on_mag(self, msg, lsb):
        self.log.append(("mag", tuple(getattr(msg, f) for f in _fields(msg))))

    def on_imu(self, msg, now):
        self.log.append(("imu", tuple(getattr(msg, f) for f in _fields(msg)), now))

    def on_imu_saturated(self, node, now):
        self.log.append(("saturated", node, now))

    def on_coil_status(self, msg):
        self.log.append(("coil", tuple(msg)))

    on_status = on_coil_status

    def other(self, msg, now):
        self.log.append(("other", msg, now))


def _fields(msg):
    return getattr(msg, "_fields", None) or msg.__slots__


def _receiver(dec):
    port, sink = _Port(), _Sink()
    r = Receiver(port, dec, [], sink, sink, sink, None, other=sink.other, imu_interval_us=100_000,
                 imu_step_us=1e6 / 120.0, core=core.load("compiled"))
    return r, port, sink


def test_the_receiver_routes_the_same_records_with_either_decoder():
    """A damaged stream of every message through a receiver on the Python decoder and one on the
    compiled decoder (its rows): the supervisor, the tracker and the other handler see the same
    values at the same times, and the counters are equal. Catches a row column read as another
    field, a MAG_PACKED not restored at the tick's time, a clipped IMU sample used."""
    rng = np.random.default_rng(7)
    data = _stream(rng, 1500)
    chunks = _cut(rng, data, 300)
    ref, rp, rs = _receiver(FrameDecoder())
    got, gp, gs = _receiver(frame_decoder(core.load("compiled")))
    assert isinstance(got.decoder, CompiledFrameDecoder)
    now = 5_000_000
    for c in chunks:
        now += int(rng.integers(0, 3000))
        rp.data = gp.data = c
        ref.step(now)
        got.step(now)
    assert gs.log == rs.log
    assert got.counters() == ref.counters()
    kinds = {e[0] for e in rs.log}
    assert {"sup", "mag", "imu", "saturated", "coil", "other"} <= kinds


def test_python_core_keeps_the_protocol_decoder():
    assert type(frame_decoder(core.PYTHON)) is FrameDecoder


try:
    from hypothesis import given, settings, strategies as st
except ImportError:                                 # pragma: no cover
    given = None

if given is not None:
    @settings(max_examples=200, deadline=None)
    @given(st.lists(st.binary(max_size=120), max_size=8))
    def test_any_bytes_give_the_same_messages_and_counters(chunks):
        """Arbitrary reads (hypothesis): never an exception, the same result as the reference."""
        a, b, ca, cb = _both(chunks)
        assert a == b and ca == cb
