"""protocol.interfaces.slcan: the slcan lines it writes (golden bytes, the Lawicel text python-can's
slcan writes), the lines it parses (partial lines kept, replies and bad lines counted, CAN FD
lengths), and the bus on an SlcanBridge: frames reach python-can's slcan and back, a flush writes
a whole batch in one system call, and a read takes what the tty held when it began."""
import time

import can
import pytest

from collections import deque

from coiltrack.protocol.can import CanLink, open_bus
from coiltrack.protocol.examples import EXAMPLES
from coiltrack.protocol.framing import FrameDecoder, build_frame, cobs_encode
from coiltrack.protocol.interfaces.slcan import encode_line, parse_lines
from coiltrack.protocol.slcan import SlcanBridge, frame_line_ok

GOLDEN = [
    (dict(arbitration_id=0x123, is_extended_id=False, data=b"\x01\xab"), b"t123201AB\r"),
    (dict(arbitration_id=0x7FF, is_extended_id=False, data=b""), b"t7FF0\r"),
    (dict(arbitration_id=0x1ABCDE0, is_extended_id=True, data=bytes(range(8))), b"T01ABCDE080001020304050607\r"),
    (dict(arbitration_id=0x321, is_extended_id=False, is_remote_frame=True, dlc=4), b"r3214\r"),
    (dict(arbitration_id=0x1F, is_extended_id=True, is_remote_frame=True, dlc=0), b"R0000001F0\r"),
    (dict(arbitration_id=0x456, is_extended_id=False, is_fd=True, bitrate_switch=True, data=bytes(12)),
     b"b4569" + b"00" * 12 + b"\r"),
    (dict(arbitration_id=0x456, is_extended_id=True, is_fd=True, data=bytes([0xEE]) * 64),
     b"D00000456F" + b"EE" * 64 + b"\r"),
]


@pytest.mark.parametrize("fields,line", GOLDEN)
def test_encode_golden_lines(fields, line):
    assert encode_line(can.Message(**fields)) == line
    assert frame_line_ok(line[:-1])               # the bridge's own check accepts it


@pytest.mark.parametrize("fields,line", GOLDEN)
def test_parse_golden_lines(fields, line):
    out, counts = deque(), [0, 0]
    buf = bytearray(line)
    parse_lines(buf, out, counts)
    m = out.popleft()
    ref = can.Message(**fields)
    assert (m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.is_fd, m.bitrate_switch, m.dlc, bytes(m.data)) \
        == (ref.arbitration_id, ref.is_extended_id, ref.is_remote_frame, ref.is_fd, ref.bitrate_switch, ref.dlc,
            bytes(ref.data))
    assert not buf and counts == [0, 0]


def test_parse_keeps_a_partial_line_and_counts_replies_and_bad_lines():
    out, counts = deque(), [0, 0]
    buf = bytearray(b"\r\at1232AABB\r\nt12\x0d" + b"t0013ABCDEF\rT0000")
    parse_lines(buf, out, counts)
    assert [(m.arbitration_id, bytes(m.data)) for m in out] == [(0x123, b"\xaa\xbb"), (0x001, b"\xab\xcd\xef")]
    assert counts == [2, 1]                        # "" and "\a" are replies; "t12" is a bad frame line
    assert buf == bytearray(b"T0000")              # the partial line waits for its end
    buf += b"0012" + b"1" + b"FF\r"
    parse_lines(buf, out, counts)
    assert out[-1].arbitration_id == 0x12 and out[-1].is_extended_id and bytes(out[-1].data) == b"\xff"
    bad = [b"t1239" + b"00" * 9, b"t1232AB", b"t12G1AA", b"d1239" + b"00" * 11, b"r1239"]
    buf = bytearray(b"\r".join(bad) + b"\r")
    n0 = len(out)
    parse_lines(buf, out, counts)
    assert len(out) == n0 and counts[1] == 1 + len(bad)


def _drain(bus, wait_s=20.0, want=1):
    out, end = [], time.monotonic() + wait_s
    while len(out) < want and time.monotonic() < end:
        m = bus.recv(timeout=0.05)
        if m is not None:
            out.append(m)
    return out


def test_frames_reach_python_cans_slcan_and_back_one_write_per_flush():
    with SlcanBridge(2) as br:
        a = open_bus("slcan-tty", br.paths[0])
        b = open_bus("slcan", br.paths[1])
        try:
            assert br.wait_open()
            frames = [can.Message(**f) for f, _ in GOLDEN[:5]]
            w0 = a.writes
            for f in frames:
                a.send(f)
            assert a.writes == w0                  # coalesced: nothing written before the flush
            a.send_queued()
            assert a.writes == w0 + 1
            got = _drain(b, want=len(frames))
            assert [encode_line(m) for m in got] == [encode_line(f) for f in frames]
            for f in frames:
                b.send(f)
            got = _drain(a, want=len(frames))
            assert [encode_line(m) for m in got] == [encode_line(f) for f in frames]
        finally:
            a.shutdown()
            b.shutdown()


def test_canlink_reads_what_the_tty_held_and_flush_sends_a_batch():
    ex = EXAMPLES["POSE"]
    with SlcanBridge(2) as br:
        tx = CanLink(open_bus("slcan-tty", br.paths[0]), ex.src)
        rx = CanLink(open_bus("slcan-tty", br.paths[1]), 3)
        try:
            assert br.wait_open()
            assert tx.fd is not None and tx.fd == tx.bus.fileno()
            for seq in range(3):
                tx.write(cobs_encode(build_frame(ex.msg, seq, ex.src)) + b"\x00")
            n_frames = tx.frames_tx
            assert n_frames == 3 * 10 and tx.bus.lines_tx == n_frames
            w0 = tx.bus.writes
            tx.flush()
            assert tx.bus.writes == w0 + 1           # a POSE is 10 frames: 30 lines, one write
            data, end = b"", time.monotonic() + 20.0
            while len(FrameDecoder().feed(data)) < 3 and time.monotonic() < end:
                time.sleep(0.01)
                data += rx.read()
            msgs = FrameDecoder().feed(data)
            assert [m for m in msgs] == [ex.msg] * 3
            assert rx.reassembler.frames_bad == 0 and rx.frames_rx == n_frames
        finally:
            tx.close()
            rx.close()
