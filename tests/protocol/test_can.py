"""CAN: identifiers, ISO-TP segmentation, reassembly (per sender, bad and
out-of-order frames counted), CAN FD, python-can virtual back-to-back, and
the CanLink Port adapter."""
import can
import pytest

from coiltrack.protocol import FrameDecoder, ProtocolError, encode_frame
from coiltrack.protocol.can import (BASE_ID, CAN_INDEX, FUNCTION_MASK, MAX_CAN_NODE, CanCodec, CanLink, CanReassembler,
                          build_pdu, can_id, decode_pdu, direct_size, ext_id, frame_data_lengths, is_direct,
                          open_bus, parse_id, segment,
                          virtual_bus_pair, virtual_link_pair)
from coiltrack.protocol.codec import STRUCTS
from coiltrack.protocol.errors import CrcError, EncodeError, LengthError, UnknownMessageError
from coiltrack.protocol.examples import EXAMPLES, example_context
from coiltrack.protocol.schema import BY_NAME, MESSAGES, NODE_COIL_DRIVER, NODE_FIRMWARE, NODE_SENSOR_BASE


def frames_of(name, fd=False, src=None, seq=None):
    ex = EXAMPLES[name]
    return CanCodec(fd=fd, context=example_context()).encode(ex.msg, ex.seq if seq is None else seq,
                                                             ex.src if src is None else src)


def wire_seq(ex, fd, previous=-1):
    """The serial seq a receiver gives a message: the sender's for a segmented PDU, the sender's
    previous seq + 1 for a single frame (which carries no seq; -1: none heard yet)."""
    return (previous + 1) & 0xFF if is_direct(ex.msg.ID, fd) else ex.seq


# ------------------------------------------------------------ identifiers
def test_ids_unique_per_message_and_sender():
    nodes = [NODE_FIRMWARE, NODE_COIL_DRIVER] + list(range(NODE_SENSOR_BASE, MAX_CAN_NODE + 1))
    ids = {}
    for m in MESSAGES:
        for n in nodes:
            i = can_id(m.id, n)
            assert 0 <= i <= 0x7FF
            assert i not in ids, (m.name, n, ids.get(i))
            ids[i] = (m.name, n)
            assert parse_id(i) == (m.id, n)


def test_arbitration_favours_time_sync_then_pulse_commands():
    def worst(name):   # the highest (least urgent) id of that message over all senders
        return can_id(BY_NAME[name].id, MAX_CAN_NODE)

    def best(name):
        return can_id(BY_NAME[name].id, 0)

    others = [m.name for m in MESSAGES if m.name not in ("TIME_SYNC", "COIL_PULSE_CMD")]
    assert worst("TIME_SYNC") < best("COIL_PULSE_CMD")
    for name in others:
        assert worst("COIL_PULSE_CMD") < best(name), name
    # the class is the schema priority
    for m in MESSAGES:
        assert BASE_ID[m.id] >> 8 == m.priority
        assert BASE_ID[m.id] & ~FUNCTION_MASK == 0


def test_id_layout_is_stable():
    """Pinned: changing these breaks every deployed node (the golden CAN
    vectors pin them too)."""
    assert {m.name: BASE_ID[m.id] for m in MESSAGES} == {
        "HEARTBEAT": 0x600, "TIME_SYNC": 0x000, "TIME_SYNC_REPLY": 0x500, "COIL_PULSE_CMD": 0x100,
        "COIL_STATUS": 0x200, "MAG_SAMPLE": 0x300, "IMU_SAMPLE": 0x340, "MAG_FLIP_CMD": 0x240,
        "MAG_PACKED": 0x380, "IMU_DELTA": 0x3C0,
        "POSE": 0x400, "PULSE_WINDOW": 0x640, "CONFIG_GET": 0x540, "CONFIG_SET": 0x580,
        "CONFIG_ACK": 0x5C0, "FAULT_EVENT": 0x280, "AC_DRIVE_CMD": 0x140, "AC_DRIVE_STATUS": 0x2C0}
    assert max(CAN_INDEX.values()) < 4
    assert MAX_CAN_NODE == 63


def test_signed_messages_travel_on_29_bit_ids_with_the_11_bit_priority():
    """A signed command is segmented on ``id11 << 18``: its arbitration rank among the
    11-bit messages is that of its 11-bit id (an id with the base in the low bits would
    outrank TIME_SYNC), and the reassembler takes it back (a dropped IDE case loses it)."""
    ex = EXAMPLES["COIL_PULSE_CMD"]
    sig = bytes(range(13))
    fr = CanCodec().encode(ex.msg, ex.seq, ex.src, signature=sig)
    assert all(f.is_extended_id and f.arbitration_id == ext_id(can_id(ex.msg.ID, ex.src)) for f in fr)
    assert fr[0].arbitration_id >> 18 == can_id(ex.msg.ID, ex.src)
    r = CanReassembler()
    out = [p for f in fr for p in r.feed_with_headers(f)]
    assert len(out) == 1 and out[0][1] == ex.msg and out[0][0].signature == sig and out[0][0].seq == ex.seq


def test_single_frames_continue_the_senders_numbering():
    """Segmented seq 7, then two single frames, then segmented seq 10 from one sender: the single
    frames become 8 and 9 and no gap is counted (a receiver counting single frames on their own
    from 0 reports gaps on every sender that mixes both forms, as conform's sequence rule saw)."""
    r = CanReassembler()
    hb, mag = EXAMPLES["TIME_SYNC_REPLY"].msg._replace(node=16), EXAMPLES["MAG_PACKED"].msg
    c = CanCodec()
    out = []
    for m, q in ((hb, 7), (mag, 8), (mag._replace(stamp=mag.stamp + 1), 9), (hb._replace(sync_seq=43), 10)):
        for f in c.encode(m, q, 16):
            out += r.feed_with_headers(f)
    assert [h.seq for h, _ in out] == [7, 8, 9, 10] and r.seq_gaps == 0


def test_single_frames_carry_the_payload_without_the_sender_byte():
    """MAG_PACKED and IMU_DELTA travel as one classic 8-byte frame whose bytes are the
    payload after ``node`` (a codec that kept the node byte, a PCI or a CRC would make
    9..11 bytes); every message is one CAN FD frame."""
    for name in ("MAG_PACKED", "IMU_DELTA"):
        ex = EXAMPLES[name]
        fr = frames_of(name)
        assert len(fr) == 1 and len(fr[0].data) == 8 == direct_size(ex.msg.ID)
        assert bytes(fr[0].data) == STRUCTS[ex.msg.ID].pack(*ex.msg)[1:]
        assert fr[0].arbitration_id == can_id(ex.msg.ID, ex.msg.node)
    for m in MESSAGES:
        assert len(frame_data_lengths(m.id, fd=True)) == 1, m.name


def test_bad_ids_and_nodes():
    with pytest.raises(EncodeError):
        can_id(0x20, 64)
    with pytest.raises(UnknownMessageError):
        can_id(0xEE, 1)
    for bad in (0x7E0, 0x0E0, 0x800, 0x1FFFFFFF):
        with pytest.raises(UnknownMessageError):
            parse_id(bad)


# ------------------------------------------------------------ segmentation
def test_mag_sample_fits_three_classic_frames():
    """v1's MAG_SAMPLE (full time stamp) still segments into three frames."""
    mid = BY_NAME["MAG_SAMPLE"].id
    assert BY_NAME["MAG_SAMPLE"].size == 16
    assert frame_data_lengths(mid) == [8, 8, 7]
    fr = frames_of("MAG_SAMPLE")
    assert len(fr) == 3 and all(not f.is_fd and f.dlc <= 8 for f in fr)
    assert [f.data[0] for f in fr] == [0x10, 0x21, 0x22]


@pytest.mark.parametrize("name", list(EXAMPLES))
@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_round_trip_every_message(name, fd):
    ex = EXAMPLES[name]
    fr = frames_of(name, fd)
    assert all(f.arbitration_id == can_id(ex.msg.ID, ex.src) for f in fr)
    if fd:
        assert all(f.is_fd and len(f.data) in (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64) for f in fr)
    else:
        assert all(len(f.data) <= 8 for f in fr)
    assert CanCodec.decode_frames(fr, context=example_context()) == ex.msg
    r = CanReassembler(context=example_context())
    out = []
    for f in fr:
        out += r.feed_with_headers(f)
    assert len(out) == 1
    hdr, msg = out[0]
    src = ex.msg.node if is_direct(ex.msg.ID, fd) and ex.msg.DEF.sender_field else ex.src
    assert msg == ex.msg and hdr.src == src and hdr.seq == wire_seq(ex, fd)
    assert r.frames_bad == 0


def test_segment_sequence_nibble_wraps():
    pdu = bytes(range(200))          # longer than any message: 6 + 7*28 bytes, SN wraps twice
    segs = segment(pdu)
    assert [s[0] & 0x0F for s in segs[1:18]] == [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 0, 1]
    assert b"".join(s[1:] for s in segs[1:]) == pdu[6:]


def test_crc_extra_catches_schema_mismatch_on_can():
    """The PDU CRC mixes the CRC extra, so a sender whose table differs fails
    on CAN as on serial: relabel TIME_SYNC's segmented full form (the 29-bit fallback of its bus
    form) as MAG_FLIP_CMD (same size)."""
    ex = EXAMPLES["TIME_SYNC"]
    fr = segment(build_pdu(ex.msg, ex.seq, NODE_FIRMWARE))
    wrong_id = ext_id(can_id(BY_NAME["MAG_FLIP_CMD"].id, NODE_FIRMWARE))
    relabelled = [can.Message(arbitration_id=wrong_id, is_extended_id=True, data=d) for d in fr]
    r = CanReassembler()
    for f in relabelled:
        assert r.feed(f) == []
    assert r.crc_errors == 1
    with pytest.raises(CrcError):
        CanCodec.decode_frames(relabelled)


def test_explicit_decoders_raise_protocol_errors_only():
    ex = EXAMPLES["MAG_SAMPLE"]
    pdu = build_pdu(ex.msg, 1, ex.src)
    assert decode_pdu(ex.msg.ID, ex.src, pdu) == ex.msg
    with pytest.raises(LengthError):
        decode_pdu(ex.msg.ID, ex.src, pdu[:-1])
    with pytest.raises(CrcError):
        decode_pdu(ex.msg.ID, ex.src + 1, pdu)       # src is covered by the CRC
    fr = frames_of("MAG_SAMPLE")
    for frames in (fr[:2], fr[1:], [fr[0], fr[2], fr[1]], fr + fr[:1]):
        with pytest.raises(ProtocolError):
            CanCodec.decode_frames(frames)


# -------------------------------------------------------------- reassembly
def test_interleaved_senders_and_messages():
    """Frames of different senders (and of different messages of one sender)
    interleave on a real bus; each identifier reassembles on its own."""
    a = frames_of("MAG_SAMPLE", src=16, seq=1)
    b = frames_of("MAG_SAMPLE", src=17, seq=1)
    c = CanCodec().encode(EXAMPLES["TIME_SYNC_REPLY"].msg._replace(node=16), 2, 16)
    order = [a[0], b[0], c[0], a[1], c[1], b[1], c[2], a[2], b[2], c[3]]
    r = CanReassembler()
    got = [(h.src, m.NAME) for f in order for h, m in r.feed_with_headers(f)]
    assert sorted(got) == [(16, "MAG_SAMPLE"), (16, "TIME_SYNC_REPLY"), (17, "MAG_SAMPLE")]
    assert r.frames_bad == 0 and r.seq_gaps == 0


def test_reassembler_counts_each_kind_and_recovers():
    mag = frames_of("MAG_SAMPLE")
    r = CanReassembler(timeout_s=0.05)
    feed = lambda f, t=0.0: r.feed(f, now=t)
    assert feed(mag[1]) == [] and r.unexpected_cf == 1                    # CF without FF
    feed(mag[0]); assert feed(mag[2]) == [] and r.out_of_order == 1       # skipped CF
    feed(mag[0]); feed(mag[0]); assert r.duplicates == 1                  # repeated FF
    feed(mag[1]); feed(mag[1]); assert r.duplicates == 2                  # repeated CF
    assert feed(mag[2]) == [EXAMPLES["MAG_SAMPLE"].msg]
    assert feed(mag[0]) == [] and feed(mag[1]) == [] and feed(mag[2]) == [] and r.duplicates == 3  # same PDU again
    r2 = CanReassembler(timeout_s=0.05)
    r2.feed(mag[0], now=0.0)
    assert r2.feed(mag[1], now=0.2) == [] and r2.timeouts == 1            # CF too late
    r2.feed(mag[0], now=1.0)
    assert r2.expire(2.0) == 1 and r2.timeouts == 2
    r3 = CanReassembler()
    r3.feed(mag[0]); r3.feed(frames_of("MAG_SAMPLE", seq=9)[0])
    assert r3.aborted == 1                                                  # new FF interrupts
    assert r3.feed(frames_of("MAG_SAMPLE", seq=9)[1]) == []
    assert r3.feed(frames_of("MAG_SAMPLE", seq=9)[2])[0].t_us == EXAMPLES["MAG_SAMPLE"].msg.t_us


def test_reassembler_ignores_other_traffic():
    r = CanReassembler()
    r.feed(can.Message(arbitration_id=0x18FF0001, is_extended_id=True, data=b"\x01\x02"))
    r.feed(can.Message(arbitration_id=0x301, is_extended_id=False, is_remote_frame=True, dlc=8))
    r.feed(can.Message(is_error_frame=True))
    r.feed(can.Message(arbitration_id=0x310, is_extended_id=False, data=b"\x30\x00\x00"))   # flow control
    assert r.ignored == 4 and r.frames_bad == 0
    r.feed(can.Message(arbitration_id=0x7E8, is_extended_id=False, data=b"\x02\x01\x00"))
    assert r.unknown_ids == 1


# ----------------------------------------------- python-can back to back
def test_virtual_bus_back_to_back():
    """python-can's own back-to-back pattern: two buses on one channel."""
    a, b = virtual_bus_pair()
    try:
        codec = CanCodec()
        r = CanReassembler()
        sent = []
        for name, ex in EXAMPLES.items():
            for f in codec.encode(ex.msg, ex.seq, ex.src):
                a.send(f)
            sent.append(ex.msg)
        got = []
        while (f := b.recv(timeout=0)) is not None:
            assert not f.is_extended_id
            got += r.feed(f)
        assert got == sent
        assert a.recv(timeout=0) is None           # a bus does not hear itself
    finally:
        a.shutdown()
        b.shutdown()


def test_virtual_bus_fd_back_to_back():
    a, b = virtual_bus_pair()
    try:
        codec = CanCodec(fd=True)
        pose = EXAMPLES["POSE"]
        for f in codec.encode(pose.msg, 1, 1):
            a.send(f)
        r = CanReassembler()
        got = []
        while (f := b.recv(timeout=0)) is not None:
            assert f.is_fd
            got += r.feed(f)
        assert got == [pose.msg]
    finally:
        a.shutdown()
        b.shutdown()


# ------------------------------------------------------------------ CanLink
def test_canlink_presents_the_serial_port_interface():
    fw, emu = virtual_link_pair(NODE_FIRMWARE, NODE_COIL_DRIVER)
    try:
        # the firmware's TIME_SYNC and command first: the command's and the status's bus forms are
        # relative to them
        fw.write(encode_frame(EXAMPLES["TIME_SYNC"].msg, 1, NODE_FIRMWARE)
                 + encode_frame(EXAMPLES["COIL_PULSE_CMD"].msg, 3, NODE_FIRMWARE))
        assert FrameDecoder().feed(emu.read()) == [EXAMPLES["TIME_SYNC"].msg, EXAMPLES["COIL_PULSE_CMD"].msg]
        # emulator side writes serial frames from several nodes
        out = b"".join(encode_frame(ex.msg, ex.seq, ex.src) for ex in EXAMPLES.values()
                       if ex.src != NODE_FIRMWARE)
        emu.write(out[:37])
        emu.write(out[37:])                       # split frames are fine
        data = fw.read()
        sent = [ex for ex in EXAMPLES.values() if ex.src != NODE_FIRMWARE]
        counts = {}

        def seq_of(ex):                           # a single frame: the sender's previous seq + 1
            sq = ex.seq if not is_direct(ex.msg.ID, False) else (counts.get(ex.src, -1) + 1) & 0xFF
            counts[ex.src] = sq
            return sq
        want = [(ex.src, seq_of(ex), ex.msg) for ex in sent]
        got = []
        d = FrameDecoder(on_frame=lambda h, m: got.append((h.src, h.seq, m)))
        d.feed(data)
        assert got == want
        # byte for byte the same serial frames, with the receiver's seq for single frames
        assert data == b"".join(encode_frame(m, q, s) for s, q, m in want)
        # the other way
        cmd = EXAMPLES["COIL_PULSE_CMD"]
        fw.write(encode_frame(cmd.msg, 5, NODE_FIRMWARE))
        assert FrameDecoder().feed(emu.read()) == [cmd.msg]
        assert fw.read() == b"" and emu.read() == b""
        # garbage handed to write is dropped (never reaches the bus)
        emu.write(b"\x01\x02\x03\x00" + encode_frame(cmd.msg)[:-3] + b"\x00")
        assert emu.tx_bad == 2 and fw.read() == b""
    finally:
        fw.close()
        emu.close()


def test_canlink_ignores_echo_of_its_own_frames():
    bus = open_bus("virtual", "echo-test", receive_own_messages=True)
    try:
        link = CanLink(bus, NODE_FIRMWARE)
        link.write(encode_frame(EXAMPLES["TIME_SYNC"].msg, 0, NODE_FIRMWARE))
        assert link.read() == b"" and link.echoes == 1          # the bus form: one frame
    finally:
        bus.shutdown()


def test_open_bus_refuses_network_interfaces():
    with pytest.raises(ValueError):
        open_bus("udp_multicast", "239.0.0.1")


def test_canlink_rejects_node_ids_that_do_not_fit():
    a, b = virtual_bus_pair()
    try:
        with pytest.raises(ValueError):
            CanLink(a, 64)
        link = CanLink(a, 1)
        link.write(encode_frame(EXAMPLES["TIME_SYNC"].msg, 0, 200))      # src 200 has no CAN id
        assert link.tx_errors == 1 and b.recv(timeout=0) is None
    finally:
        a.shutdown()
        b.shutdown()
