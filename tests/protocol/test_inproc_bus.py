"""The in-process CAN bus (protocol.interfaces.inproc) behaves as python-can's ``virtual`` bus on
what the bench relies on: every other end hears every frame, in order, with the sender's fields
and a data buffer of its own; an end does not hear itself (unless asked); a shut-down end is off
the wire; filters and blocking receives take BusABC's path. And CanLink over it carries the same
messages as over ``virtual`` (the bench's ``--transport can`` report does not change)."""
import threading

import can
import pytest

from coiltrack.protocol.can import CanLink, inproc_link_pair, virtual_bus_pair
from coiltrack.protocol.examples import EXAMPLES
from coiltrack.protocol.framing import FrameDecoder, build_frame, cobs_encode
from coiltrack.protocol.interfaces.inproc import InprocBus, InprocChannel, inproc_bus_pair


def _frames():
    return [can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"),
            can.Message(arbitration_id=0x1ABCDE0, is_extended_id=True, data=bytes(range(8))),
            can.Message(arbitration_id=0x321, is_extended_id=False, is_remote_frame=True, dlc=4),
            can.Message(arbitration_id=0x456, is_extended_id=False, is_fd=True, bitrate_switch=True,
                        data=bytes(range(64)))]


FIELDS = ("arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "dlc", "data", "is_fd",
          "bitrate_switch", "error_state_indicator", "is_rx")


def _drain(bus):
    out = []
    while (m := bus.recv(timeout=0)) is not None:
        out.append(m)
    return out


def test_frames_arrive_in_order_with_the_fields_virtual_gives():
    a, b = inproc_bus_pair()
    va, vb = virtual_bus_pair()
    try:
        for f in _frames():
            a.send(f)
            va.send(f)
        got, ref = _drain(b), _drain(vb)
        assert len(got) == len(ref) == 4
        for g, r in zip(got, ref):
            assert [getattr(g, k) for k in FIELDS] == [getattr(r, k) for k in FIELDS]
            assert g.is_rx
        assert _drain(a) == []                      # not its own frames
    finally:
        for x in (a, b, va, vb):
            x.shutdown()


def test_a_received_frame_owns_its_data():
    a, b = inproc_bus_pair()
    try:
        f = can.Message(arbitration_id=0x10, is_extended_id=False, data=b"\x05\x06")
        a.send(f)
        f.data[0] = 0xFF                            # the sender reuses its buffer
        m = b.recv(timeout=0)
        assert bytes(m.data) == b"\x05\x06" and m is not f
    finally:
        a.shutdown()
        b.shutdown()


def test_three_ends_own_messages_and_shutdown():
    ch = InprocChannel("t")
    a, b, c = InprocBus(ch), InprocBus(ch), InprocBus(ch, receive_own_messages=True)
    try:
        a.send(can.Message(arbitration_id=1, is_extended_id=False))
        c.send(can.Message(arbitration_id=2, is_extended_id=False))
        assert [m.arbitration_id for m in _drain(b)] == [1, 2]
        own = _drain(c)
        assert [(m.arbitration_id, m.is_rx) for m in own] == [(1, True), (2, False)]
        assert [m.arbitration_id for m in _drain(a)] == [2]
        b.shutdown()
        assert b not in ch.ends
        a.send(can.Message(arbitration_id=3, is_extended_id=False))
        assert b.pending() == 0
        with pytest.raises(can.CanOperationError):
            b.send(can.Message(arbitration_id=4, is_extended_id=False))
    finally:
        for x in (a, b, c):
            x.shutdown()


def test_filters_and_a_full_queue():
    ch = InprocChannel()
    a = InprocBus(ch)
    b = InprocBus(ch, can_filters=[{"can_id": 0x100, "can_mask": 0x7F0, "extended": False}])
    c = InprocBus(ch, rx_queue_size=2)
    try:
        for i in (0x101, 0x205, 0x10F):
            a.send(can.Message(arbitration_id=i, is_extended_id=False))
        assert [m.arbitration_id for m in _drain(b)] == [0x101, 0x10F]
        assert [m.arbitration_id for m in _drain(c)] == [0x101, 0x205] and c.overruns == 1
    finally:
        for x in (a, b, c):
            x.shutdown()


def test_a_blocking_receive_wakes_on_a_frame_from_another_thread():
    a, b = inproc_bus_pair()
    try:
        got = []
        t = threading.Thread(target=lambda: got.append(b.recv(timeout=5.0)))
        t.start()
        a.send(can.Message(arbitration_id=7, is_extended_id=False))
        t.join(10.0)
        assert got and got[0].arbitration_id == 7
        assert b.recv(timeout=0.001) is None        # nothing more: a bounded wait gives None
    finally:
        a.shutdown()
        b.shutdown()


@pytest.mark.parametrize("name", ["POSE", "PULSE_WINDOW", "MAG_PACKED", "TIME_SYNC_REPLY", "HEARTBEAT"])
def test_canlink_carries_the_same_bytes_as_over_virtual(name):
    """The same serial frames written on each bus come out the same at the other end."""
    ex = EXAMPLES[name]
    data = b""
    for seq in range(3):
        data += cobs_encode(build_frame(ex.msg, seq, ex.src)) + b"\x00"
    outs = []
    for pair in (inproc_link_pair(ex.src, 3), None):
        if pair is None:
            va, vb = virtual_bus_pair()
            pair = CanLink(va, ex.src), CanLink(vb, 3)
        tx, rx = pair
        for link in pair:          # what a station has heard before (the bus forms are restored against it)
            link.codec.context.note(EXAMPLES["TIME_SYNC"].msg)
            link.codec.context.note(EXAMPLES["COIL_PULSE_CMD"].msg)
        tx.write(data)
        outs.append((rx.read(), tx.counters(), rx.counters()))
        tx.close()
        rx.close()
    assert outs[0] == outs[1]
    dec = FrameDecoder()
    assert len(dec.feed(outs[0][0])) == 3


SLOTS = ("arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "dlc", "data", "is_fd",
         "bitrate_switch", "error_state_indicator", "is_rx", "channel", "timestamp")


@pytest.mark.parametrize("kw", [
    dict(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"),
    dict(arbitration_id=0x1ABCDE0, is_extended_id=True, data=bytearray(range(8)), timestamp=12.5, channel="c"),
    dict(arbitration_id=0x321, is_extended_id=False, is_remote_frame=True, dlc=4, data=b"\x01"),
    dict(arbitration_id=0x456, is_extended_id=False, is_fd=True, bitrate_switch=True, data=bytes(64), is_rx=False),
    dict(arbitration_id=0x7, is_extended_id=False, data=None, is_error_frame=True, error_state_indicator=True),
])
def test_message_builds_what_can_message_builds(kw):
    """protocol.interfaces.message bypasses Message.__init__: every slot as the constructor sets it,
    and the data a buffer of its own."""
    from coiltrack.protocol.interfaces import FAST, message

    ref = can.Message(**kw)
    m = message(**kw)
    assert FAST                                         # this python-can's Message has the slots it sets
    assert type(m) is can.Message
    assert [getattr(m, k) for k in SLOTS] == [getattr(ref, k) for k in SLOTS]
    if isinstance(kw.get("data"), bytearray):
        assert m.data is not kw["data"]
