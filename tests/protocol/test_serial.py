"""Serial transport: pyserial on loop:// and on a pseudo-terminal, bounded
buffers."""
import os
import time

from coiltrack.protocol import MSG, FrameDecoder, encode_frame
from coiltrack.protocol.examples import EXAMPLES
from coiltrack.protocol.serial_link import FdPort, SerialLink, open_pty

#: a guard against a hang only: every wait ends as soon as its data is there,
#: so a loaded machine makes the test slower, never fail
IO_TIMEOUT_S = 30.0


def test_loop_url_round_trip():
    link = SerialLink("loop://")
    try:
        frames = [encode_frame(ex.msg, ex.seq, ex.src) for ex in EXAMPLES.values()]
        for f in frames:
            link.write(f)
        got = []
        deadline = time.monotonic() + IO_TIMEOUT_S
        while len(got) < len(frames) and time.monotonic() < deadline:
            got += link.poll()
        assert got == [ex.msg for ex in EXAMPLES.values()]
        assert link.decoder.frames_bad == 0 and link.tx_pending == 0
    finally:
        link.close()


def test_pty_both_directions():
    master, slave, path = open_pty()
    try:
        board = FdPort(master)            # the side a board (or the emulator) sits on
        host = SerialLink(path)
        msg = MSG["MAG_SAMPLE"](16, 123, 1, -2, 3, 1)
        board.write(encode_frame(msg, 4, 16) * 50)
        got = []
        deadline = time.monotonic() + IO_TIMEOUT_S
        while len(got) < 50 and time.monotonic() < deadline:
            got += host.poll()
            board.flush()
            time.sleep(0.001)
        assert got == [msg] * 50
        host.write(encode_frame(MSG["TIME_SYNC"](9, 1), 0, 1))
        d = FrameDecoder()
        out = []
        while not out and time.monotonic() < deadline:
            out = d.feed(board.read())
            time.sleep(0.001)
        assert out == [MSG["TIME_SYNC"](9, 1)]
        host.close()
    finally:
        os.close(master)
        os.close(slave)


def test_transmit_queue_is_bounded_and_drops_whole_frames():
    master, slave, path = open_pty()
    try:
        port = FdPort(master, tx_capacity=4096)
        frame = encode_frame(MSG["POSE"](*([0] * 2 + [0.0] * 13 + [0, 0])))
        for _ in range(5000):             # nobody reads the slave: the pty fills, then the queue
            port.write(frame)
        assert port.tx_pending <= 4096
        assert port.tx_dropped > 0
        # what was queued goes out as whole frames: drain the pty and decode
        os.set_blocking(slave, False)
        d = FrameDecoder()
        while True:
            port.flush()
            try:
                chunk = os.read(slave, 65536)
            except BlockingIOError:
                if port.tx_pending == 0:
                    break
                continue
            d.feed(chunk)
        assert d.frames_bad == 0
        assert d.frames_ok == 5000 - port.tx_dropped
    finally:
        os.close(master)
        os.close(slave)


def test_read_is_bounded():
    link = SerialLink("loop://", max_read=100)
    try:
        link.write(b"\x55" * 1000)
        chunks = []
        deadline = time.monotonic() + IO_TIMEOUT_S
        while sum(map(len, chunks)) < 1000 and time.monotonic() < deadline:
            c = link.read()
            assert len(c) <= 100
            chunks.append(c)
        assert sum(map(len, chunks)) == 1000
    finally:
        link.close()
