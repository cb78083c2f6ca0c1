"""slcan (Lawicel ASCII) on a tty the project opens itself: a python-can ``BusABC`` for the
pseudo-terminals of :class:`protocol.slcan.SlcanBridge` (or a serial adapter's tty).

python-can's ``slcan`` interface reads its serial port a byte at a time (pyserial's
``read(1)``: a ``select`` and a ``read`` system call a byte, ~20 bytes a classic frame's line)
and writes each frame's line with a write of its own. Here:

* ``recv(timeout=0)`` returns the frames parsed from what has arrived; when none is left it
  reads *everything* the tty holds in one system call (``FIONREAD``, then one ``read``) and parses
  all its lines at once; :meth:`held_frames` does that read and says how many frames are waiting,
  so a reader takes the frames the adapter held when its read began and no more (as a CAN
  controller's receive FIFO read at the tick; ``protocol.can.CanLink.read``);
* ``send`` encodes the line (``t``/``T``/``r``/``R``/``d``/``D``/``b``/``B``, upper-case hex, as
  python-can's ``slcan`` writes it); with ``coalesce`` the lines only queue and
  :meth:`send_queued` writes them in one system call (``CanLink.flush``, which the firmware's
  loop calls after each tick and the emulator's after each step), otherwise each goes at once.

Lines that are no frame (an adapter's ``\\r`` reply to a command, ``\\a``, a transmit
acknowledgement ``z``/``Z``) are skipped and counted (``other_lines``); a malformed frame line is
counted (``bad_lines``) and skipped. Opening sends ``C``, the bit rate (``S0``..``S8``) and
``O`` (or ``L`` listen-only) without waiting for the replies (skipped as they arrive).
"""
from __future__ import annotations

import fcntl
import os
import struct
import termios
from collections import deque

import can

from . import message

__all__ = ["SlcanTtyBus", "encode_line", "parse_lines"]

#: bit/s -> slcan bit-rate command (python-can's table)
BITRATE_CODES = {10_000: b"S0", 20_000: b"S1", 50_000: b"S2", 100_000: b"S3", 125_000: b"S4",
                 250_000: b"S5", 500_000: b"S6", 750_000: b"S7", 1_000_000: b"S8", 83_300: b"S9"}
_FD_DLC = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
_FD_CODE = {n: i for i, n in enumerate(_FD_DLC)}
#: first byte of a frame line -> (identifier digits, remote, FD, bit-rate switch)
_KIND = {0x74: (3, False, False, False), 0x54: (8, False, False, False),      # t T
         0x72: (3, True, False, False), 0x52: (8, True, False, False),        # r R
         0x64: (3, False, True, False), 0x44: (8, False, True, False),        # d D
         0x62: (3, False, True, True), 0x42: (8, False, True, True)}          # b B
#: lines longer than this (bytes) are no slcan line: the buffer is dropped (a peer's garbage)
MAX_LINE = 160


def encode_line(msg: can.Message) -> bytes:
    """The slcan line of one frame, ``\\r`` included (the text python-can's ``slcan`` sends)."""
    ext = msg.is_extended_id
    if msg.is_remote_frame:
        return b"%s%0*X%d\r" % (b"R" if ext else b"r", 8 if ext else 3, msg.arbitration_id, msg.dlc)
    data = msg.data
    if msg.is_fd:
        kind = (b"B" if ext else b"b") if msg.bitrate_switch else (b"D" if ext else b"d")
        code = _FD_CODE[len(data)] if len(data) in _FD_CODE else _FD_CODE[min(n for n in _FD_DLC if n >= len(data))]
        return b"%s%0*X%X%s\r" % (kind, 8 if ext else 3, msg.arbitration_id, code, data.hex().upper().encode())
    return b"%s%0*X%d%s\r" % (b"T" if ext else b"t", 8 if ext else 3, msg.arbitration_id, len(data),
                              data.hex().upper().encode())


def parse_lines(buf: bytearray, out: deque, counts: list, timestamp: float = 0.0) -> None:
    """Parse every complete line of ``buf`` (up to its last ``\\r``, or ``\\a``: an adapter's error
    reply, which has no ``\\r``) into ``can.Message`` frames
    appended to ``out``; the incomplete rest stays in ``buf``. ``counts``: [other lines, bad lines]
    added to."""
    end = max(buf.rfind(b"\r"), buf.rfind(b"\a"))       # an error reply is a bare \a (no \r)
    if end < 0:
        if len(buf) > MAX_LINE:
            buf.clear()
            counts[1] += 1
        return
    for line in bytes(buf[:end + 1]).replace(b"\a", b"\a\r").split(b"\r")[:-1]:
        if line[:1] == b"\n":             # some adapters end lines with \r\n
            line = line[1:]
        kind = _KIND.get(line[0]) if line else None
        if kind is None:
            counts[0] += 1
            continue
        nid, remote, fd, brs = kind
        try:
            arb = int(line[1:1 + nid], 16)
            dlc = int(line[1 + nid:2 + nid], 16)
            if remote:
                if len(line) != 2 + nid or dlc > 8:
                    raise ValueError
                data, n = None, dlc
            else:
                n = _FD_DLC[dlc] if fd else dlc
                if (not fd and dlc > 8) or len(line) != 2 + nid + 2 * n:
                    raise ValueError
                data = bytes.fromhex(line[2 + nid:].decode("ascii"))
        except (ValueError, IndexError, UnicodeDecodeError):
            counts[1] += 1
            continue
        out.append(message(arb, nid == 8, data, fd, brs, timestamp, remote, n))
    del buf[:end + 1]



def open_raw_tty(path: str) -> int:
    """A tty (a pseudo-terminal's slave side) opened read-write, non-blocking, not as the
    controlling terminal, in raw mode: its descriptor (closed again if raw mode is refused)."""
    import tty

    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        tty.setraw(fd)
    except OSError:
        os.close(fd)
        raise
    return fd

class SlcanTtyBus(can.BusABC):
    """slcan on the tty ``channel`` (a pty path, ``/dev/ttyACM0``); see the module docstring."""

    def __init__(self, channel: str, bitrate: int = 500_000, coalesce: bool = False, listen_only: bool = False,
                 **kwargs):
        import time

        if bitrate not in BITRATE_CODES:
            raise ValueError(f"slcan: bit rate {bitrate} not one of {sorted(BITRATE_CODES)}")
        super().__init__(channel=channel, **kwargs)
        self.channel_info = f"slcan on {channel}"
        self._clock = time.time
        self.fd = open_raw_tty(channel)
        self.coalesce = coalesce
        self._in = bytearray()
        self._out = bytearray()
        self._rx: deque = deque()
        self._counts = [0, 0]
        self._nbuf = bytearray(4)
        #: system calls that wrote lines (one a flush with ``coalesce``), lines written
        self.writes = 0
        self.lines_tx = 0
        #: bytes queued at most while the tty does not take them; beyond, new lines are dropped
        self.max_pending = 1 << 20
        self.dropped = 0
        for cmd in (b"C", BITRATE_CODES[bitrate], b"L" if listen_only else b"O"):
            self._out += cmd + b"\r"
        self.send_queued()

    # receive ----------------------------------------------------------------
    def _fill(self) -> int:
        """One read of everything the tty holds, parsed; returns the frames waiting."""
        try:
            fcntl.ioctl(self.fd, termios.FIONREAD, self._nbuf)
            n = struct.unpack("i", self._nbuf)[0]
        except OSError:
            n = 65536
        if n > 0:
            try:
                self._in += os.read(self.fd, n)
            except (BlockingIOError, InterruptedError):
                pass
            parse_lines(self._in, self._rx, self._counts, self._clock())
        return len(self._rx)

    def held_frames(self) -> int:
        """The frames waiting now, after one read of what the tty holds (see the module docstring)."""
        return self._fill()

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """A waiting frame (filters applied), else one read of the tty; ``timeout`` 0: None when
        nothing passes; otherwise ``BusABC.recv``'s wait."""
        rx = self._rx
        for _ in range(2):
            while rx:
                m = rx.popleft()
                if self._filters is None or self._matches_filters(m):
                    return m
            if timeout != 0 or not self._fill():
                break
        if timeout == 0:
            return None
        return super().recv(timeout)

    def _recv_internal(self, timeout: float | None):
        import select
        import time

        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._rx:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None, False
            select.select([self.fd], [], [], left)
            self._fill()
        return self._rx.popleft(), False

    # send -------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        line = encode_line(msg)
        if len(self._out) + len(line) > self.max_pending:
            self.dropped += 1
            raise can.CanOperationError("slcan: the tty takes no more lines")
        self._out += line
        self.lines_tx += 1
        if not self.coalesce:
            self.send_queued()

    def send_queued(self) -> None:
        """Write the queued lines (one system call; what the tty does not take now stays queued)."""
        if not self._out:
            return
        try:
            n = os.write(self.fd, self._out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._out.clear()
            raise can.CanOperationError(f"slcan: write failed: {exc}") from None
        self.writes += 1
        del self._out[:n]

    def fileno(self) -> int:
        return self.fd

    @property
    def other_lines(self) -> int:
        return self._counts[0]

    @property
    def bad_lines(self) -> int:
        return self._counts[1]

    def shutdown(self) -> None:
        if self.fd >= 0:
            try:
                self._out += b"C\r"
                self.send_queued()
            except can.CanError:
                pass
            os.close(self.fd)
            self.fd = -1
        super().shutdown()
