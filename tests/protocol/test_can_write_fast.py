"""CanLink.write takes an unsigned message that travels as a segmented PDU (PULSE_WINDOW, POSE,
MAG_FLIP_CMD, ...) straight from the serial frame's bytes (FrameDecoder.take_raw, then the PDU
sliced out of them): every write, of every kind, must put the same CAN frames on the bus (identifier,
data, flags, order) and leave the same counters, local ids and tx decoder state as the reference
(the tx decoder's feed, each message re-encoded by CanCodec.encode). The bus's frames are also
reassembled by the other end (an independent path) into the messages written."""
import random
import struct

from coiltrack.protocol.can import CanLink, virtual_bus_pair
from coiltrack.protocol.codec import MSG
from coiltrack.protocol.examples import EXAMPLES, example_context
from coiltrack.protocol.framing import HEADER_LEN, build_frame, cobs_encode, frame_crc
from coiltrack.protocol.schema import BY_NAME


def _links(fd):
    """Two firmware-side links (the fast one, the reference) and the buses that hear them."""
    out = []
    for _ in range(2):
        a, b = virtual_bus_pair()
        link = CanLink(a, 1, fd=fd)
        link.codec.context.note(EXAMPLES["TIME_SYNC"].msg)
        link.codec.context.note(EXAMPLES["COIL_PULSE_CMD"].msg)
        out.append((link, b))
    return out


def _encoded(raw) -> bytes:
    return cobs_encode(bytes(raw)) + b"\x00"


def _pose_with_nan(rng, signaling: bool) -> bytes:
    """A POSE frame with a NaN in an f32 field (a signalling one: quiet bit clear)."""
    m = MSG["POSE"](16, rng.randrange(1 << 40), *(rng.uniform(-1, 1) for _ in range(13)), 3, 200)
    raw = bytearray(build_frame(m, rng.randrange(256), 1))
    o = HEADER_LEN + 1 + 8 + 4 * rng.randrange(13)
    raw[o:o + 4] = struct.pack("<I", 0x7F800001 if signaling else 0x7FC00000)
    end = len(raw) - 2
    crc = frame_crc(raw[:end], raw[4])
    raw[end], raw[end + 1] = crc & 0xFF, crc >> 8
    return _encoded(raw)


def _writes(rng):
    """What a firmware writes (its messages, one frame a write, src 1) and what it may not: other
    sources (0, beyond the CAN node field), several frames in one write, a frame cut in two, a bad
    CRC, garbage, signed frames, NaNs in a POSE, bytearrays."""
    out = []
    for k in range(600):
        r = rng.random()
        seq = rng.randrange(256)
        src = 1 if rng.random() < 0.85 else rng.choice((0, 2, 63, 64, 200))
        if r < 0.35:
            m = MSG["PULSE_WINDOW"](rng.randrange(16, 32), rng.randrange(3), rng.randrange(4096),
                                    rng.randrange(1 << 40), rng.randrange(1 << 40), rng.randrange(256),
                                    rng.randrange(256), rng.choice((0, 0, 1, 16)))
            out.append(_encoded(build_frame(m, seq, src)))
        elif r < 0.55:
            m = MSG["POSE"](rng.randrange(16, 32), rng.randrange(1 << 40), *(rng.uniform(-1, 1) for _ in range(7)),
                            *(rng.choice((0.0, 1e-6, 3.0e38, float("inf"))) for _ in range(6)), 3, 255)
            out.append(_encoded(build_frame(m, seq, src)))
        elif r < 0.6:
            out.append(_pose_with_nan(rng, rng.random() < 0.5))
        elif r < 0.7:
            m = MSG["MAG_FLIP_CMD"](rng.randrange(16, 32), rng.randrange(1 << 40), rng.randrange(2))
            out.append(_encoded(build_frame(m, seq, src)))
        elif r < 0.82:
            ex = rng.choice(list(EXAMPLES.values()))
            sig = getattr(ex, "signature", b"") or b""
            out.append(_encoded(build_frame(ex.msg, ex.seq, ex.src, 1 if sig else 0, sig)))
        elif r < 0.87:                                  # two frames in one write
            m = MSG["MAG_FLIP_CMD"](20, 5, 1)
            out.append(_encoded(build_frame(m, seq, 1)) + _encoded(build_frame(m, seq + 1, 1)))
        elif r < 0.92:                                  # a frame in two writes
            e = _encoded(build_frame(MSG["MAG_FLIP_CMD"](21, 7, 0), seq, 1))
            cut = rng.randrange(1, len(e))
            out += [e[:cut], e[cut:]]
        elif r < 0.96:                                  # a bad CRC
            raw = bytearray(build_frame(MSG["PULSE_WINDOW"](20, 1, 2, 3, 4, 5, 6, 0), seq, 1))
            raw[-1] ^= 0x10
            out.append(_encoded(raw))
        elif r < 0.98:
            out.append(bytes(rng.randrange(1, 256) for _ in range(rng.randrange(1, 40))) + b"\x00")
        else:
            out.append(bytearray(_encoded(build_frame(MSG["MAG_FLIP_CMD"](22, 9, 1), seq, 1))))
    return out


def _frame(f):
    return (f.arbitration_id, f.is_extended_id, bytes(f.data), f.is_fd, f.bitrate_switch, f.is_error_frame)


def _drain(bus):
    out = []
    while (f := bus.recv(timeout=0)) is not None:
        out.append(_frame(f))
    return out


def _state(link):
    d = link._tx_decoder
    return (link.counters(), sorted(link.local_ids), link.bytes_tx, d.counters(), dict(d._last_seq),
            d.header.seq, d.header.src, d.header.msg_id)


def test_write_puts_the_reference_frames_on_the_bus():
    """Every write of the mixed stream, on a classic and an FD link: the same frames, counters and
    state as the reference after each write; the fast path taken for most of the firmware's own."""
    for fd in (False, True):
        rng = random.Random(30 + fd)
        (fast, bus_f), (ref, bus_r) = _links(fd)
        for k, w in enumerate(_writes(rng)):
            fast.write(w)
            ref.bytes_tx += len(w)
            ref._tx_decoder.feed(w)
            assert _drain(bus_f) == _drain(bus_r), (fd, k, w)
            assert _state(fast) == _state(ref), (fd, k)
        assert fast.messages_tx > 400 and fast.tx_errors > 0 and fast.tx_bad > 0
        for link in (fast, ref, bus_f, bus_r):
            (link.close if isinstance(link, CanLink) else link.shutdown)()


def test_written_frames_reassemble_into_the_messages():
    """Independent of the reference: a PULSE_WINDOW and a POSE written to one link come out of the
    other end's reassembly as the same messages, seq and sender."""
    a, b = virtual_bus_pair()
    tx = CanLink(a, 1)
    rx = CanLink(b, 2)
    win = MSG["PULSE_WINDOW"](17, 2, 300, 1_000_000, 1_040_000, 5, 8, 0)
    pose = MSG["POSE"](17, 123456, 0.125, -0.25, 0.375, 1.0, 0.0, 0.0, 0.0, 2.0 ** -20, 2.0 ** -19, 2.0 ** -18, 2.0 ** -13,
                       2.0 ** -12, 2.0 ** -11, 3, 200)          # f32-exact values
    tx.write(_encoded(build_frame(win, 7, 1)))
    tx.write(_encoded(build_frame(pose, 8, 1)))
    got = []
    rs = rx.reassembler
    while (f := b.recv(timeout=0)) is not None:
        got += rs.feed_with_headers(f)
    assert [(h.seq, h.src, m) for h, m in got] == [(7, 1, win), (8, 1, pose)]
    assert tx.frames_tx == 4 + 10 and tx.messages_tx == 2
    tx.close()
    rx.close()


def test_take_raw_refuses_what_feed_must_judge():
    """take_raw takes only one whole good unsigned frame with nothing buffered: a partial frame
    buffered, a signed one, a bad CRC, two frames: None and no counter moved."""
    from coiltrack.protocol.framing import FrameDecoder
    d = FrameDecoder()
    good = _encoded(build_frame(MSG["MAG_FLIP_CMD"](20, 5, 1), 3, 1))
    assert d.take_raw(good) == build_frame(MSG["MAG_FLIP_CMD"](20, 5, 1), 3, 1)
    assert (d.frames_ok, d.bytes_in, d.header.seq) == (1, len(good), 3)
    ex = EXAMPLES["COIL_PULSE_CMD"]
    signed = getattr(ex, "signature", b"") or b"\x01" * 13
    for bad in (good + good, good[:-1], _encoded(build_frame(ex.msg, 1, 1, 1, signed)), b"\x00", b""):
        assert d.take_raw(bad) is None
    d.feed(good[:4])
    assert d.take_raw(good) is None and (d.frames_ok, d.bytes_in) == (1, len(good) + 4)
    assert example_context() is not None and BY_NAME["POSE"].size == 64


def test_short_cobs_decode_is_cobs_decode():
    """The in-place decode of take_raw against framing.cobs_decode: every encoded string shorter than
    254 bytes (zeros at the ends and in runs) decodes to itself; on random garbage it gives
    cobs_decode's bytes or None where cobs_decode raises or a 0xFF block would need it."""
    from coiltrack.protocol.errors import FramingError
    from coiltrack.protocol.framing import _cobs_decode_short, cobs_decode
    rng = random.Random(7)
    for _ in range(3000):
        n = rng.randrange(0, 253)
        s = bytes(rng.choice((0, 0, rng.randrange(256))) for _ in range(n))
        assert _cobs_decode_short(cobs_encode(s) + b"\x00") == s
    for _ in range(3000):
        g = bytes(rng.randrange(1, 256) if rng.random() < 0.9 else rng.choice((1, 2, 255))
                  for _ in range(rng.randrange(1, 60)))
        got = _cobs_decode_short(g + b"\x00")
        try:
            want = cobs_decode(g)
        except FramingError:
            want = None
        assert got is None or got == want, g
        assert got is not None or want is None or 0xFF in g, g
