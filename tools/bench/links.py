"""Byte links that join a firmware Port and an emulator link.

``inproc_pair()`` gives two ends of an in-memory full-duplex pipe (simulated
clock, deterministic). ``FdLink`` wraps a non-blocking file descriptor (the
master side of a pseudo-terminal).
"""
from __future__ import annotations

import fcntl
import os
import struct
import termios

from coiltrack.firmware.port import Port
from ..args import bitrate


class InprocEnd(Port):
    def __init__(self, rx: bytearray, tx: bytearray):
        self._rx = rx
        self._tx = tx
        self.bytes_tx = 0

    def read(self) -> bytes:
        if not self._rx:
            return b""
        data = bytes(self._rx)
        self._rx.clear()
        return data

    def write(self, data: bytes) -> None:
        self._tx += data
        self.bytes_tx += len(data)


def inproc_pair() -> tuple[InprocEnd, InprocEnd]:
    a_to_b, b_to_a = bytearray(), bytearray()
    return InprocEnd(b_to_a, a_to_b), InprocEnd(a_to_b, b_to_a)


class FdLink(Port):
    """Non-blocking read/write on a file descriptor (a pty's master or slave side).

    ``read()`` drains what has arrived (one system call, up to 64 KiB). With
    ``coalesce`` a ``write()`` only queues, and :meth:`flush` sends what a
    step or a tick queued in one write (one wake-up of the reader instead of
    one a frame); the loop that owns the link calls it (``emulator_loop``
    after each step, ``firmware_loop`` after each tick). Without it every
    write is sent at once. ``urgent``: message ids whose frame, written alone, leaves at once
    with what was queued before it (the firmware's ``POSE``: the tick's work after the report
    does not delay it; the id is the COBS-encoded frame's sixth byte, the header's message id
    moved by the code byte). ``owns_fd``: :meth:`close` closes the descriptor."""

    def __init__(self, fd: int, coalesce: bool = False, owns_fd: bool = False, urgent=()):
        os.set_blocking(fd, False)
        self.fd = fd
        self.coalesce = coalesce
        self.urgent = frozenset(int(i) for i in urgent)
        self.owns_fd = owns_fd
        self._pending = bytearray()
        self.bytes_tx = 0
        self.bytes_rx = 0
        self.bytes_dropped = 0
        self.writes = 0

    def read(self) -> bytes:
        # Only what the line discipline already holds: a read() of an empty tty waits for the
        # kernel's pending buffer-flush work (tty_buffer_flush_work), a kworker of ordinary
        # priority, even on a non-blocking descriptor; FIONREAD does not wait (as pyserial's
        # in_waiting). Bytes still in the flip buffer come with a later read.
        try:
            n = struct.unpack("i", fcntl.ioctl(self.fd, termios.FIONREAD, b"\0\0\0\0"))[0]
        except OSError:   # not a tty (a pipe, a socket): read what is there
            n = 65536
        if n <= 0:
            return b""
        try:
            data = os.read(self.fd, max(n, 1))
            self.bytes_rx += len(data)
            return data
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:   # peer closed
            return b""

    #: bytes queued at most while the peer does not read; beyond, new writes are dropped (counted)
    MAX_PENDING = 1 << 20

    def write(self, data: bytes) -> None:
        if len(self._pending) + len(data) > self.MAX_PENDING:
            self.bytes_dropped += len(data)
            return
        self._pending += data
        if not self.coalesce or (self.urgent and len(data) > 5 and data[5] in self.urgent):
            self.flush()

    def flush(self) -> None:
        while self._pending:
            try:
                n = os.write(self.fd, self._pending)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self._pending.clear()
                return
            self.bytes_tx += n
            self.writes += 1
            del self._pending[:n]

    def close(self) -> None:
        if self.owns_fd and self.fd >= 0:
            fd, self.fd = self.fd, -1
            os.close(fd)


def is_pty_path(path) -> bool:
    """Whether ``path`` names a Unix98 pseudo-terminal's slave side (``/dev/pts/N``)."""
    return isinstance(path, str) and path.startswith("/dev/pts/") and path[9:].isdigit()


def open_pty_slave(path: str) -> FdLink:
    """The slave side of a pseudo-terminal opened raw and non-blocking, as a coalescing
    :class:`FdLink` (a pty has no baud rate: pyserial's per-read ``in_waiting`` and
    ``select`` calls buy nothing there); a ``POSE`` leaves as it is written (``urgent``)."""
    from coiltrack.protocol import MSG
    from coiltrack.protocol.interfaces.slcan import open_raw_tty

    return FdLink(open_raw_tty(path), coalesce=True, owns_fd=True, urgent=(MSG["POSE"].ID,))


def make_raw_pty() -> tuple[int, int, str]:
    """Open a pseudo-terminal pair in raw mode (binary-safe, no echo)."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    return master, slave, os.ttyname(slave)


class GuardedPort(Port):
    """Wraps a port so that a link that goes away (a pty whose other side closed, a USB
    adapter unplugged: EIO) costs frames, not the loop; errors are counted. With
    ``silence_s`` > 0 a read raises :class:`tools.stopping.PeerSilent` once nothing has
    arrived for that long on ``clock`` (microseconds)."""

    def __init__(self, port, clock=None, silence_s: float = 0.0):
        self.port = port
        self.errors = 0
        self.clock = clock
        self.silence_us = int(silence_s * 1e6) if clock is not None else 0
        self.last_rx_us = None

    def read(self) -> bytes:
        try:
            data = self.port.read()
        except (OSError, ValueError):      # pyserial's SerialException is an OSError
            self.errors += 1
            data = b""
        if self.silence_us:
            self._watch(bool(data))
        return data

    def _watch(self, received: bool) -> None:
        now = self.clock.now()
        if received or self.last_rx_us is None:
            self.last_rx_us = now
        elif now - self.last_rx_us > self.silence_us:
            from ..stopping import PeerSilent

            raise PeerSilent(self.silence_us * 1e-6)

    def write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except (OSError, ValueError):
            self.errors += 1

    def flush(self) -> None:
        """Send what a coalescing port queued (nothing to do for one that is not)."""
        flush = getattr(self.port, "flush", None)
        if flush is not None:
            try:
                flush()
            except (OSError, ValueError):
                self.errors += 1

    def close(self) -> None:
        try:
            self.port.close()
        except OSError:
            pass


def add_link_arguments(p, serial_port_type=str) -> None:
    """The link options of ``firmware`` and ``emulator``: a serial port or a python-can bus."""
    p.add_argument("--transport", choices=("serial", "can"), default="serial",
                   help="serial: COBS frames on --port; can: the same messages on a python-can bus")
    p.add_argument("--port", type=serial_port_type, help="serial device, pty path or pyserial URL (--transport serial)")
    p.add_argument("--baudrate", type=bitrate, default=1_000_000, help="serial baud rate (default 1000000)")
    p.add_argument("--interface", default="slcan",
                   help="python-can interface (--transport can): slcan, socketcan, virtual (default slcan)")
    p.add_argument("--channel", help="python-can channel (--transport can): slcan device or pty, can0, ...")
    p.add_argument("--bitrate", type=bitrate, default=500_000, help="CAN bit rate (--transport can, default 500000)")


def open_link(args, node_id: int):
    """The port that ``add_link_arguments`` describes, as node ``node_id`` on a CAN bus, and
    a description of it; ValueError with a one-line reason when it cannot be opened."""
    if args.transport == "serial" and is_pty_path(args.port):
        what, need, make = args.port, "--port", lambda: open_pty_slave(args.port)
    elif args.transport == "serial":
        from coiltrack.firmware.port import SerialPort

        what, need, make = args.port, "--port", lambda: SerialPort(args.port, args.baudrate)
    else:
        from coiltrack.protocol.can import CanLink, open_bus

        what, need = f"{args.interface}:{args.channel}", "--channel"
        make = lambda: CanLink(open_bus(args.interface, args.channel, args.bitrate), node_id)  # noqa: E731
    if (args.port if args.transport == "serial" else args.channel) is None:
        raise ValueError(f"--transport {args.transport} needs {need}")
    try:
        return make(), what
    except Exception as exc:  # pyserial: SerialException (an OSError) or ValueError; python-can: CanError
        raise ValueError(f"cannot open {what}: {exc}") from None


def warn_virtual_bus(args, command: str, stream=None) -> bool:
    """python-can's ``virtual`` interface joins only the buses of one process: a command that
    meets its peer in another process (``firmware``, ``emulator``, ``conform``) would wait for
    it forever. Say so on stderr (one line); True if it was said. (In one process, e.g. the
    tests or ``bench --transport can``, virtual buses on one channel do meet.)"""
    import sys

    if getattr(args, "transport", None) != "can" or getattr(args, "interface", None) != "virtual":
        return False
    print(f"coiltrack {command}: warning: --interface virtual reaches only buses in this same process; a "
          f"firmware, emulator or tester started as another process never hears it (between processes use "
          f"socketcan, e.g. a vcan0, or slcan on a serial device or pty)", file=stream or sys.stderr, flush=True)
    return True
