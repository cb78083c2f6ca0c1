"""Robustness of the decoders (serial stream and CAN reassembly) against
random bytes, truncations, bit flips, duplicated and reordered frames: no
exception but ProtocolError escapes an explicit decoder, the streaming
decoders never raise, no corrupted frame is accepted, and decoding is back
in sync at the next valid frame. Seeded and deterministic."""
import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from coiltrack.protocol import MSG, FrameDecoder, ProtocolError, decode_frame, encode_frame
from coiltrack.protocol.can import MAX_CAN_NODE, CanCodec, CanReassembler, decode_pdu, BASE_ID, is_direct, parse_id
from coiltrack.protocol.examples import EXAMPLES
from coiltrack.protocol.schema import MESSAGES, TYPES

SETTINGS = settings(derandomize=True, database=None, max_examples=150, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])
NAMES = list(EXAMPLES)


def field_strategy(f):
    code = TYPES[f.type]
    if code == "f":
        return st.floats(width=32, allow_nan=False)
    if code == "d":
        return st.floats(allow_nan=False)
    bits = np.dtype(code).itemsize * 8 if code not in "qQ" else 64
    if code.islower():
        return st.integers(-(1 << (bits - 1)), (1 << (bits - 1)) - 1)
    return st.integers(0, (1 << bits) - 1)


@st.composite
def messages(draw):
    m = draw(st.sampled_from(MESSAGES))
    vals = [draw(field_strategy(f)) for f in m.fields]
    return MSG[m.name](*vals), draw(st.integers(0, 255)), draw(st.integers(0, 31))


# ------------------------------------------------------------------ serial
@SETTINGS
@given(st.lists(st.one_of(messages(), st.binary(max_size=80)), max_size=12),
       st.integers(1, 64), messages())
def test_serial_stream_property(items, chunk, last):
    """Valid frames and arbitrary garbage interleaved: each valid frame that
    follows a delimiter decodes; nothing else is accepted; never raises."""
    stream = bytearray()
    expect = []
    for it in items:
        if isinstance(it, bytes):
            stream += it
        else:
            msg, seq, src = it
            stream += b"\x00" + encode_frame(msg, seq, src)
            expect.append(msg)
    stream += b"\x00" + encode_frame(*last)
    expect.append(last[0])
    d = FrameDecoder()
    got = []
    for k in range(0, len(stream), chunk):
        got += d.feed(bytes(stream[k:k + chunk]))
    assert got == expect


@SETTINGS
@given(st.binary(max_size=300))
def test_explicit_serial_decoder_raises_only_protocol_errors(data):
    try:
        decode_frame(data)
    except ProtocolError:
        pass


@pytest.mark.parametrize("name", NAMES)
def test_every_single_bit_flip_is_rejected(name):
    """Exhaustive: flip each bit of each golden frame (a flip to 0x00 splits
    the frame); the decoder rejects every variant and resyncs."""
    ex = EXAMPLES[name]
    frame = encode_frame(ex.msg, ex.seq, ex.src)
    good = encode_frame(MSG["TIME_SYNC"](1, 2))
    d = FrameDecoder()
    flips = 0
    for i in range(len(frame) - 1):
        for b in range(8):
            bad = bytearray(frame)
            bad[i] ^= 1 << b
            assert d.feed(bytes(bad)) == []
            assert d.feed(b"\x00" + good) == [MSG["TIME_SYNC"](1, 2)]
            flips += 1
    assert d.frames_ok == flips and d.frames_bad >= flips


def mutate_stream(frames, rng, n_mut):
    """Mutation fuzzer over a list of frames: flips, truncations, garbage,
    duplicates, reordering."""
    frames = [bytearray(f) for f in frames]
    for _ in range(n_mut):
        k = int(rng.integers(0, len(frames)))
        op = int(rng.integers(0, 6))
        f = frames[k]
        if op == 0 and len(f) > 1:
            i = int(rng.integers(0, len(f) - 1))
            f[i] ^= 1 << int(rng.integers(0, 8))
        elif op == 1 and len(f) > 2:
            cut = int(rng.integers(1, len(f) - 1))
            frames[k] = f[:cut] + f[-1:]
        elif op == 2:
            frames.insert(k, bytearray(rng.integers(0, 256, int(rng.integers(1, 50)), dtype=np.uint8)))
        elif op == 3:
            frames.insert(k, bytearray(f))
        elif op == 4 and k + 1 < len(frames):
            frames[k], frames[k + 1] = frames[k + 1], frames[k]
        elif op == 5 and len(f) > 3:
            i = int(rng.integers(0, len(f) - 1))
            del f[i]
    return b"".join(bytes(f) for f in frames)


@pytest.mark.parametrize("seed", range(6))
def test_serial_mutation_fuzzer(seed):
    rng = np.random.default_rng(seed)
    sent = []
    frames = []
    for i in range(300):
        ex = EXAMPLES[NAMES[i % len(NAMES)]]
        msg = ex.msg._replace(**{ex.msg._fields[0]: i % 200}) if ex.msg._fields[0] in ("node", "coil") else ex.msg
        sent.append(msg)
        frames.append(encode_frame(msg, i & 0xFF, ex.src))
    stream = mutate_stream(frames, rng, 200)
    final = encode_frame(MSG["TIME_SYNC"](99, 99))
    d = FrameDecoder()
    got = []
    for k in range(0, len(stream), 97):
        got += d.feed(stream[k:k + 97])
    allowed = set(sent)
    assert all(m in allowed for m in got)                    # nothing corrupted accepted
    assert d.frames_bad > 0 and len(got) > 150
    assert d.feed(b"\x00" + final) == [MSG["TIME_SYNC"](99, 99)]   # back in sync


# --------------------------------------------------------------------- CAN
def can_frames(msg, seq, src, fd=False):
    return CanCodec(fd=fd).encode(msg, seq, src)


@st.composite
def can_ops(draw):
    return draw(st.lists(st.tuples(st.integers(0, 5), st.integers(0, 10_000), st.integers(0, 255)), max_size=25))


def _single(f) -> bool:
    """A single-frame message (no PDU CRC of its own: bit errors inside it are the CAN CRC's)."""
    try:
        return not f.is_extended_id and is_direct(parse_id(f.arbitration_id)[0], bool(f.is_fd))
    except ProtocolError:
        return False


def apply_can_ops(frames, ops):
    """Drop, duplicate, swap, flip a bit, insert a random frame, truncate. A bit flip or a
    random frame on a single frame's identifier would pass the CAN CRC only on a broken bus,
    so those two go to segmented traffic (whose PDU CRC must catch them)."""
    frames = list(frames)
    for op, pos, val in ops:
        if not frames:
            break
        k = pos % len(frames)
        f = frames[k]
        if op == 3 and _single(f):
            continue
        if op == 0:                                          # drop
            del frames[k]
        elif op == 1:                                        # duplicate
            frames.insert(k, f)
        elif op == 2 and k + 1 < len(frames):                # swap neighbours
            frames[k], frames[k + 1] = frames[k + 1], frames[k]
        elif op == 3 and len(f.data):                        # bit flip in the data
            data = bytearray(f.data)
            data[val % len(data)] ^= 1 << (val % 8)
            frames[k] = can.Message(arbitration_id=f.arbitration_id, is_extended_id=False, data=bytes(data),
                                    is_fd=f.is_fd)
        elif op == 4:                                        # random frame on a coiltrack id
            ids = sorted(b for m, b in BASE_ID.items() if not is_direct(m, False))
            data = bytes((val * (i + 7)) & 0xFF for i in range(val % 9))
            frames.insert(k, can.Message(arbitration_id=ids[val % len(ids)] | (val % 64),
                                         is_extended_id=False, data=data))
        elif op == 5 and len(f.data) > 1:                    # truncated frame
            frames[k] = can.Message(arbitration_id=f.arbitration_id, is_extended_id=False,
                                    data=bytes(f.data)[:val % len(f.data)], is_fd=f.is_fd)
    return frames


@SETTINGS
@given(st.lists(messages(), min_size=1, max_size=6), can_ops(), st.booleans())
def test_can_reassembly_property(items, ops, fd):
    """Dropped, duplicated, swapped, flipped, truncated and random frames:
    the reassembler never raises, accepts only messages that were sent, and
    the next clean message of every sender decodes."""
    sent = []
    frames = []
    used: dict[tuple, set] = {}
    first: dict[tuple, object] = {}
    for msg, seq, src in items:
        if msg.DEF.sender_field and is_direct(msg.ID, fd):
            if msg.node > MAX_CAN_NODE:
                continue        # a single frame's sender is its node field: it must fit the identifier
            src = msg.node
        key = (msg.ID, src)
        if seq in used.get(key, ()):
            continue            # the same seq twice on one identifier may be a repeat: keep items distinct
        used.setdefault(key, set()).add(seq)
        first.setdefault(key, msg)
        sent.append(msg)
        frames += can_frames(msg, seq, src, fd)
    r = CanReassembler()
    got = []
    for f in apply_can_ops(frames, ops):
        got += r.feed(f)
    assert all(m in sent for m in got)
    # back in sync: a fresh message (a sequence number not used before) on every identifier
    out = []
    fresh = []
    for (mid, src), seqs in used.items():
        seq = min(set(range(256)) - seqs)
        msg = first[(mid, src)]
        fresh.append(msg)
        for f in can_frames(msg, seq, src, fd):
            out += r.feed(f)
    assert out == fresh


@SETTINGS
@given(st.lists(st.tuples(st.integers(0, 0x7FF), st.binary(max_size=8)), max_size=12))
def test_explicit_can_decoder_raises_only_protocol_errors(raw):
    frames = [can.Message(arbitration_id=i, is_extended_id=False, data=d) for i, d in raw]
    try:
        CanCodec.decode_frames(frames)
    except ProtocolError:
        pass
    for i, d in raw:
        try:
            decode_pdu(MESSAGES[i % len(MESSAGES)].id, i & 31, d + d + d)
        except ProtocolError:
            pass


@pytest.mark.parametrize("seed", range(4))
def test_can_mutation_fuzzer(seed):
    rng = np.random.default_rng(100 + seed)
    sent = []
    frames = []
    for i in range(200):
        ex = EXAMPLES[NAMES[int(rng.integers(0, len(NAMES)))]]
        src = int(rng.choice([1, 2, 16, 17, 18]))
        sent.append(ex.msg)
        frames += can_frames(ex.msg, i & 0xFF, src, fd=bool(seed & 1))
    ops = [(int(rng.integers(0, 6)), int(rng.integers(0, 10_000)), int(rng.integers(0, 256))) for _ in range(150)]
    r = CanReassembler()
    got = []
    for f in apply_can_ops(frames, ops):
        got += r.feed(f)
    assert all(m in sent for m in got)
    assert r.frames_bad > 0 and len(got) > 100
    final = EXAMPLES["COIL_STATUS"].msg
    out = []
    for f in can_frames(final, 77, 2):
        out += r.feed(f)
    assert out == [final]
