"""CanReassembler.feed_serial (what CanLink.read returns for each CAN frame): the plain single
frames (MAG_PACKED, IMU_DELTA) take a short path from the frame's bytes; every frame, of every
kind, must give the same serial bytes, counters, seqs and header as the reference
(feed_with_headers, then build_frame and cobs_encode of each message), and the bytes must decode
back to the message (the protocol's FrameDecoder, an independent path)."""
import random

import can

from coiltrack.protocol import FrameDecoder
from coiltrack.protocol.can import _PLAIN_SINGLE, BASE_ID, CanCodec, CanReassembler
from coiltrack.protocol.codec import MSG
from coiltrack.protocol.examples import EXAMPLES, example_context
from coiltrack.protocol.framing import build_frame, cobs_encode
from coiltrack.protocol.schema import BY_NAME


def _reference(rs, frame) -> bytearray:
    out = bytearray()
    for hdr, msg in rs.feed_with_headers(frame):
        out += cobs_encode(build_frame(msg, hdr.seq, hdr.src, hdr.flags, hdr.signature))
        out.append(0)
    return out


def _header(rs):
    h = rs.header
    return h.seq, h.src, h.flags, h.msg_id, h.signature, h.signed_part


def _frames(rng, fd):
    """A mixed stream: samples of several senders (zeros in their bytes too), every example
    message (bus forms, segmented, signed), wrong lengths, foreign and error frames."""
    codec = CanCodec(fd=fd, context=example_context())
    out = []
    for k in range(400):
        r = rng.random()
        src = rng.choice((16, 17, 40, 63))
        if r < 0.5:
            x, y, z = (rng.choice((0, rng.randrange(-32768, 32768))) for _ in range(3))
            out += codec.encode(MSG["MAG_PACKED"](src, x, y, z, rng.randrange(65536)), 0, src)
        elif r < 0.6:
            out += codec.encode(MSG["IMU_DELTA"](src, rng.randrange(-32768, 32768), 0, rng.randrange(-32768, 32768),
                                                 rng.randrange(65536)), 0, src)
        elif r < 0.8:
            ex = rng.choice(list(EXAMPLES.values()))
            out += codec.encode(ex.msg, ex.seq, ex.src, getattr(ex, "signature", b"") or b"")
        elif r < 0.9:       # a sample frame one byte short or long
            data = bytes(rng.randrange(256) for _ in range(rng.choice((7, 9 if fd else 6))))
            out.append(can.Message(arbitration_id=BASE_ID[BY_NAME["MAG_PACKED"].id] | src, is_extended_id=False,
                                   data=data, is_fd=fd))
        elif r < 0.95:
            out.append(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"\x01\x02"))
        else:
            out.append(can.Message(arbitration_id=0x391, is_error_frame=True))
    return out


def test_feed_serial_matches_the_reference_on_every_frame():
    for fd in (False, True):
        rng = random.Random(7 + fd)
        frames = _frames(rng, fd)
        fast, ref = CanReassembler(context=example_context()), CanReassembler(context=example_context())
        for f in frames:
            a = bytearray()
            fast.feed_serial(f, a)
            assert a == _reference(ref, f), f
            assert _header(fast) == _header(ref)
        assert fast.counters() == ref.counters()
        assert fast._last_seq == ref._last_seq and fast._synth_seq == ref._synth_seq
        assert fast.single_frames > 200


def test_feed_serial_bytes_decode_to_the_message():
    rs = CanReassembler()
    codec = CanCodec()
    msgs = [MSG["MAG_PACKED"](17, 0, -1, 256, 0x8000), MSG["MAG_PACKED"](63, -32768, 32767, 0, 0),
            MSG["IMU_DELTA"](40, 0, 0, 0, 0)]
    out = bytearray()
    for m in msgs:
        for f in codec.encode(m, 0, m.node):
            rs.feed_serial(f, out)
    dec = FrameDecoder()
    got = dec.feed(bytes(out))
    assert got == msgs and dec.frames_bad == 0
    # single frames carry no seq: the receiver numbers each sender's messages from 0
    assert rs._last_seq == {17: 0, 63: 0, 40: 0}


def test_plain_singles_are_the_integer_single_frames():
    names = {BY_NAME[n].id for n in ("MAG_PACKED", "IMU_DELTA")}
    assert names <= {v[1] for v in _PLAIN_SINGLE.values()}
    for n, mid, size, sender in _PLAIN_SINGLE.values():
        assert n <= 8 and size == n + sender
