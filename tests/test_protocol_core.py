"""Protocol core: schema-generated round trips, COBS, CRC extra, streaming
decoder resynchronisation and bad-frame counting."""
import struct

import numpy as np
import pytest

from coiltrack import protocol
from coiltrack.protocol import MSG, FrameDecoder, ProtocolError, decode_frame, encode_frame
from coiltrack.protocol.framing import HEADER_LEN, build_frame, cobs_decode, cobs_encode, crc16, parse_frame
from coiltrack.protocol.schema import MESSAGES, TYPES


def sample_values(mdef, rng):
    """Extreme and random values for every field type, exactly representable."""
    vals = []
    for f in mdef.fields:
        code = TYPES[f.type]
        if code in "fd":
            vals.append(float(np.float32(rng.uniform(-1e3, 1e3))))
        else:
            bits = struct.calcsize(code) * 8
            lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if code.islower() else (0, (1 << bits) - 1)
            mid = int(rng.integers(lo, hi, endpoint=True, dtype=np.int64)) if bits < 64 else hi // 3
            vals.append((lo, hi, mid)[int(rng.integers(0, 3))])
    return vals


@pytest.mark.parametrize("mdef", MESSAGES, ids=lambda m: m.name)
def test_round_trip_every_message(mdef):
    rng = np.random.default_rng(mdef.id)
    cls = MSG[mdef.name]
    for _ in range(50):
        msg = cls(*sample_values(mdef, rng))
        seq, src = int(rng.integers(0, 256)), int(rng.integers(0, 256))
        frame = encode_frame(msg, seq, src)
        assert frame.endswith(b"\x00") and b"\x00" not in frame[:-1]
        assert decode_frame(frame) == msg
        d = FrameDecoder()
        assert d.feed(frame) == [msg]
        assert d.header.seq == seq and d.header.src == src


@pytest.mark.parametrize("n", [0, 1, 2, 253, 254, 255, 256, 600])
def test_cobs_round_trip_lengths(n):
    rng = np.random.default_rng(n)
    for zeros in (0.0, 0.3, 1.0):
        data = bytes(int(b) if rng.random() > zeros else 0 for b in rng.integers(1, 256, n))
        enc = cobs_encode(data)
        assert b"\x00" not in enc
        assert cobs_decode(enc) == data


def test_cobs_known_vectors():
    # vectors from the COBS paper / Wikipedia
    assert cobs_encode(b"\x00") == b"\x01\x01"
    assert cobs_encode(b"\x00\x00") == b"\x01\x01\x01"
    assert cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert cobs_encode(b"\x11\x22\x33\x44") == b"\x05\x11\x22\x33\x44"
    assert cobs_encode(bytes(range(1, 255))) == b"\xff" + bytes(range(1, 255)) + b"\x01"


def test_crc16_is_ccitt_false():
    assert crc16(b"123456789") == 0x29B1   # CRC-16/CCITT-FALSE check value


def test_crc_extra_catches_schema_mismatch():
    """A frame whose payload matches another message's size but was built
    with another definition fails the CRC (MAVLink CRC_EXTRA)."""
    msg = MSG["TIME_SYNC"](123, 4)
    raw = bytearray(build_frame(msg))
    raw[4] = MSG["MAG_FLIP_CMD"].ID      # same payload size (10 bytes), other definition
    with pytest.raises(protocol.CrcError):
        parse_frame(bytes(raw))


def test_decoder_resyncs_after_garbage_and_counts():
    rng = np.random.default_rng(7)
    msgs = [MSG["MAG_SAMPLE"](16, i * 8333, i, -i, 2 * i, i & 1) for i in range(200)]
    frames = [encode_frame(m, i & 0xFF, 16) for i, m in enumerate(msgs)]
    stream = bytearray()
    expect = []
    corrupted = 0
    for i, f in enumerate(frames):
        kind = i % 5
        if kind == 1:            # garbage before the frame, ended by a delimiter
            stream += bytes(rng.integers(1, 256, 17, dtype=np.uint8)) + b"\x00"
            corrupted += 1
        if kind == 2:            # flipped bit
            b = bytearray(f)
            b[int(rng.integers(0, len(b) - 1))] ^= 1 << int(rng.integers(0, 8))
            if b"\x00" in b[:-1]:
                b = bytearray(f[:3]) + b"\x00"   # a flip to 0x00 is a truncation
            stream += b
            corrupted += 1
            continue
        if kind == 3:            # truncated frame (delimiter kept)
            stream += f[: len(f) // 2] + b"\x00"
            corrupted += 1
            continue
        stream += f
        expect.append(msgs[i])
    d = FrameDecoder()
    out = []
    for k in range(0, len(stream), 13):     # arbitrary chunking
        out += d.feed(bytes(stream[k:k + 13]))
    assert out == expect
    assert d.frames_ok == len(expect)
    assert d.frames_bad == corrupted


def test_decoder_bounded_buffer_overflow():
    d = FrameDecoder()
    good = encode_frame(MSG["TIME_SYNC"](1, 2))
    assert d.feed(b"\x55" * 10_000) == []
    assert d.overflows == 1
    assert d.feed(b"\x00" + good) == [MSG["TIME_SYNC"](1, 2)]


def test_decode_errors_are_protocol_errors():
    rng = np.random.default_rng(3)
    for _ in range(2000):
        data = bytes(rng.integers(0, 256, int(rng.integers(0, 100)), dtype=np.uint8))
        try:
            decode_frame(data)
        except ProtocolError:
            pass


def test_schema_hash_stable_and_in_heartbeat():
    assert protocol.SCHEMA_HASH == protocol.schema_hash()
    assert 0 <= protocol.SCHEMA_HASH < 2**32
    hb = MSG["HEARTBEAT"](1, 0, 2, protocol.PROTOCOL_VERSION, protocol.SCHEMA_HASH, 0)
    assert decode_frame(encode_frame(hb)).schema_hash == protocol.SCHEMA_HASH


def test_encode_rejects_out_of_range():
    with pytest.raises(protocol.EncodeError):
        encode_frame(MSG["MAG_SAMPLE"](16, 0, 40000, 0, 0, 0))
