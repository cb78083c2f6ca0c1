"""CAN between processes without a kernel CAN module: python-can's own
``slcan`` interface on pseudo-terminals joined by the slcan adapter
emulator (protocol.slcan)."""
import subprocess
import sys
import textwrap
import time

from coiltrack.protocol import MSG, FrameDecoder, encode_frame
from coiltrack.protocol.can import CanCodec, CanLink, CanReassembler, open_bus
from coiltrack.protocol.examples import EXAMPLES
from coiltrack.protocol.schema import NODE_FIRMWARE
from coiltrack.protocol.slcan import SlcanBridge, frame_line_ok

#: a guard against a hang only: every wait ends as soon as its data is there,
#: so a loaded machine makes the test slower, never fail
IO_TIMEOUT_S = 30.0


def drain(link, decoder, want, timeout=IO_TIMEOUT_S):
    got = []
    deadline = time.monotonic() + timeout
    while len(got) < want and time.monotonic() < deadline:
        got += decoder.feed(link.read())
        time.sleep(0.001)
    return got


def test_frame_line_validation():
    assert frame_line_ok(b"t1238DEADBEEF00112233")
    assert frame_line_ok(b"t1230")
    assert frame_line_ok(b"T1234567820AB0")
    assert frame_line_ok(b"r1238")
    assert frame_line_ok(b"d123A" + b"00" * 16)
    assert not frame_line_ok(b"t1239" + b"00" * 9)
    assert not frame_line_ok(b"t12380011")
    assert not frame_line_ok(b"t12G100")
    assert not frame_line_ok(b"O")


def test_slcan_back_to_back_in_process():
    with SlcanBridge(2) as br:
        a = open_bus("slcan", br.paths[0], 500_000)
        b = open_bus("slcan", br.paths[1], 500_000)
        try:
            assert br.wait_open()
            la, lb = CanLink(a, NODE_FIRMWARE), CanLink(b, 30)
            frames = [(ex.msg, ex.seq, ex.src) for ex in EXAMPLES.values() if ex.src != 30]
            for msg, seq, src in frames:
                la.write(encode_frame(msg, seq, src))
            got = drain(lb, FrameDecoder(), len(frames))
            assert got == [m for m, _, _ in frames]
            assert lb.reassembler.frames_bad == 0
            # and back
            lb.write(encode_frame(MSG["TIME_SYNC"](5, 6), 0, 30))
            assert drain(la, FrameDecoder(), 1) == [MSG["TIME_SYNC"](5, 6)]
        finally:
            a.shutdown()
            b.shutdown()
        assert br.bad_lines == 0


def test_slcan_fd_frames_and_bitrate_mismatch():
    with SlcanBridge(3) as br:
        a = open_bus("slcan", br.paths[0], 500_000, fd=True)
        b = open_bus("slcan", br.paths[1], 500_000)
        c = open_bus("slcan", br.paths[2], 250_000)        # wrong bit rate: hears nothing
        try:
            assert br.wait_open()
            pose = EXAMPLES["POSE"]
            sent = CanCodec(fd=True).encode(pose.msg, 1, NODE_FIRMWARE)     # one FD frame (v2 single frame)
            for f in sent:
                a.send(f)
            r = CanReassembler()
            got = []
            deadline = time.monotonic() + IO_TIMEOUT_S
            while not got and time.monotonic() < deadline:
                f = b.recv(timeout=0)
                if f is None:
                    time.sleep(0.001)
                    continue
                assert f.is_fd
                got += r.feed(f)
            assert got == [pose.msg]
            assert c.recv(timeout=0) is None
            # the bridge writes the frame to b before it counts c's drop: wait for the count
            while br.frames_dropped < len(sent) and time.monotonic() < deadline:
                time.sleep(0.001)
            assert len(sent) == 1 and br.frames_dropped >= len(sent)
        finally:
            for bus in (a, b, c):
                bus.shutdown()


CHILD = textwrap.dedent("""
    import sys, time
    from coiltrack.protocol import MSG, FrameDecoder, encode_frame
    from coiltrack.protocol.can import CanLink, open_bus
    bus = open_bus("slcan", sys.argv[1], 500000)
    link = CanLink(bus, 2)
    dec = FrameDecoder()
    seq = 0
    replies = 0
    deadline = time.monotonic() + 30
    next_hb = 0.0
    while replies < 3 and time.monotonic() < deadline:
        now = time.monotonic()
        if now >= next_hb:                      # until the parent answers, say hello
            link.write(encode_frame(MSG["HEARTBEAT"](2, 1, 2, 1, 0, 0), seq, 2)); seq += 1
            next_hb = now + 0.05
        for m in dec.feed(link.read()):
            if m.NAME == "TIME_SYNC":
                link.write(encode_frame(MSG["TIME_SYNC_REPLY"](2, m.sync_seq, 7, -1, 0), seq, 2)); seq += 1
                link.write(encode_frame(MSG["MAG_SAMPLE"](16, m.master_time_us, 1, 2, 3, 1), seq, 2)); seq += 1
                replies += 1
        time.sleep(0.001)
    bus.shutdown()
    print("child done", replies, dec.frames_bad, flush=True)
    sys.exit(0 if replies == 3 and dec.frames_bad == 0 else 1)
""")


def test_slcan_between_processes():
    """Bridge in one process, a bus end in another, this test in a third."""
    bridge = subprocess.Popen([sys.executable, "-m", "coiltrack.protocol.slcan", "--ends", "2"],
                              stdout=subprocess.PIPE, text=True)
    child = None
    try:
        paths = [bridge.stdout.readline().strip(), bridge.stdout.readline().strip()]
        assert all(p.startswith("/dev/") for p in paths), paths
        bus = open_bus("slcan", paths[0], 500_000)
        try:
            link = CanLink(bus, NODE_FIRMWARE)
            child = subprocess.Popen([sys.executable, "-c", CHILD, paths[1]], stdout=subprocess.PIPE, text=True)
            dec = FrameDecoder()
            got = []
            deadline = time.monotonic() + IO_TIMEOUT_S
            while not any(m.NAME == "HEARTBEAT" for m in got) and time.monotonic() < deadline:
                got += dec.feed(link.read())
                time.sleep(0.001)
            assert any(m.NAME == "HEARTBEAT" for m in got), "child never heard"
            for k in range(3):
                link.write(encode_frame(MSG["TIME_SYNC"](1000 + k, 40 + k), k, NODE_FIRMWARE))
            replies, mags = [], []
            while len(mags) < 3 and time.monotonic() < deadline:
                for m in dec.feed(link.read()):
                    (replies if m.NAME == "TIME_SYNC_REPLY" else mags if m.NAME == "MAG_SAMPLE" else []).append(m)
                time.sleep(0.001)
            assert [m.sync_seq for m in replies] == [40, 41, 42]
            assert [m.t_us for m in mags] == [1000, 1001, 1002]
            assert child.wait(timeout=IO_TIMEOUT_S) == 0, child.stdout.read()
            assert dec.frames_bad == 0 and link.reassembler.frames_bad == 0
        finally:
            bus.shutdown()
    finally:
        if child is not None and child.poll() is None:
            child.kill()
            child.wait()
        bridge.terminate()
        assert bridge.wait(timeout=IO_TIMEOUT_S) == 0       # a hang guard, not a speed bound


def test_slcan_read_returns_the_frames_that_had_arrived_when_it_began():
    """python-can's slcan reads its adapter a byte at a time (each read of a pty may wait for the
    tty's flush work: one firmware read took 6.8 ms), and frames keep arriving meanwhile. The
    firmware judges every frame of a read against the tick's clock, taken before the read: a
    sample taken during a long read was seen 3.2 ms in the future (more than the 3 ms
    ``stamp_future_tol_us``) and reported as a clock step. So a read returns what the adapter
    held when it began, as a CAN controller's receive FIFO read at the tick would; what arrives
    during it is the next read's. The arrivals during the read are injected into python-can's
    own loopback port (no wall clock, no bridge thread)."""
    bus = open_bus("slcan", "loop://")
    try:
        bus.flush()                     # the adapter commands looped back at open
        port = bus.serialPortOrig
        codec = CanCodec()
        sensor = 16
        early = [MSG["MAG_PACKED"](sensor, 10 * k, 0, 0, k) for k in range(3)]
        late = [MSG["MAG_PACKED"](sensor, 10 * k, 0, 0, 100 + k) for k in range(3)]
        for m in early:
            for f in codec.encode(m, 0, sensor):
                bus.send(f)
        read = port.read
        arrivals = list(late)

        def slow_read(n=1):
            if arrivals:                # the adapter hears frames while the reader is still busy
                for f in codec.encode(arrivals.pop(0), 0, sensor):
                    bus.send(f)
            return read(n)

        port.read = slow_read
        link = CanLink(bus, NODE_FIRMWARE)
        dec = FrameDecoder()
        first = dec.feed(link.read())
        assert [m.stamp for m in first] == [0, 1, 2]
        assert arrivals == []           # the late frames did arrive during that read
        port.read = read
        second = dec.feed(link.read())
        assert [m.stamp for m in second] == [100, 101, 102]
        assert dec.feed(link.read()) == []
    finally:
        bus.shutdown()
