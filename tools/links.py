"""Byte links that join a firmware Port and an emulator link.

``inproc_pair()`` gives two ends of an in-memory full-duplex pipe (simulated
clock, deterministic). ``FdLink`` wraps a non-blocking file descriptor (the
master side of a pseudo-terminal).
"""
from __future__ import annotations

import os

from coiltrack.firmware.port import Port


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
    """Non-blocking read/write on a file descriptor (pty master)."""

    def __init__(self, fd: int):
        os.set_blocking(fd, False)
        self.fd = fd
        self._pending = bytearray()
        self.bytes_tx = 0

    def read(self) -> bytes:
        try:
            return os.read(self.fd, 65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:   # peer closed
            return b""

    def write(self, data: bytes) -> None:
        self._pending += data
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
            del self._pending[:n]


def make_raw_pty() -> tuple[int, int, str]:
    """Open a pseudo-terminal pair in raw mode (binary-safe, no echo)."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    return master, slave, os.ttyname(slave)
