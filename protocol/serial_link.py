"""Serial transport: pyserial on a device, a pseudo-terminal or ``loop://``,
with bounded buffers.

:class:`SerialLink` is a byte Port (``read() -> bytes``, ``write(bytes)``)
that never blocks and never holds more than it was sized for:

- ``read()`` returns at most ``max_read`` bytes per call (the rest stays in
  the operating system's buffer for the next call);
- ``write()`` queues at most ``tx_capacity`` bytes that the device could not
  take yet; a frame that would overflow the queue is dropped whole and
  counted (``tx_dropped``), so a stalled peer costs frames, not memory, and
  never a partial frame;
- :meth:`poll` decodes what arrived with a :class:`protocol.FrameDecoder`,
  whose own buffer is bounded by the longest legal frame.

:class:`FdPort` is the same Port on a raw file descriptor, for the master
side of a pseudo-terminal from :func:`open_pty` (the slave side is a path
that pyserial, or a board's tool, opens).
"""
from __future__ import annotations

import os

from .framing import FrameDecoder


def open_pty() -> tuple[int, int, str]:
    """A raw (binary-safe, no echo) pseudo-terminal: ``(master_fd, slave_fd, slave_path)``.
    Keep ``slave_fd`` open while the pty is in use, so the master never sees
    a hang-up when the other program closes and reopens the path."""
    import tty

    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


class _Bounded:
    """Bounded transmit queue shared by the Port classes."""

    def _init_tx(self, tx_capacity: int) -> None:
        self.tx_capacity = tx_capacity
        self._tx = bytearray()
        self.bytes_tx = 0
        self.tx_dropped = 0
        self.tx_errors = 0

    def write(self, data: bytes) -> None:
        if len(self._tx) + len(data) > self.tx_capacity:
            self.flush()
            if len(self._tx) + len(data) > self.tx_capacity:
                self.tx_dropped += 1
                return
        self._tx += data
        self.flush()

    @property
    def tx_pending(self) -> int:
        return len(self._tx)


class SerialLink(_Bounded):
    def __init__(self, url: str, baudrate: int = 1_000_000, max_read: int = 65536,
                 tx_capacity: int = 65536, verifier=None):
        import serial  # pyserial

        # non-blocking writes; pyserial's loop:// emulates a line that never
        # accepts a zero-timeout write, and never blocks anyway
        wt = None if url.startswith("loop://") else 0
        self._s = serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=wt)
        self.url = url
        self.max_read = max_read
        self._init_tx(tx_capacity)
        self.decoder = FrameDecoder(verifier=verifier)
        self.bytes_rx = 0

    def read(self) -> bytes:
        try:
            n = self._s.in_waiting
            data = self._s.read(min(n, self.max_read)) if n else b""
        except Exception:  # OSError, serial.SerialException: device gone
            return b""
        self.bytes_rx += len(data)
        return data

    def flush(self) -> None:
        if not self._tx:
            return
        try:
            n = self._s.write(bytes(self._tx))
        except Exception:  # serial.SerialTimeoutException, SerialException, OSError
            self.tx_errors += 1
            return
        n = len(self._tx) if n is None else n
        self.bytes_tx += n
        del self._tx[:n]

    def poll(self) -> list:
        """Read and decode: the messages that arrived (bad frames counted in
        ``self.decoder``)."""
        self.flush()
        return self.decoder.feed(self.read())

    def close(self) -> None:
        try:
            self._s.close()
        except Exception:
            pass


class FdPort(_Bounded):
    """Non-blocking byte Port on a file descriptor (a pty master)."""

    def __init__(self, fd: int, max_read: int = 65536, tx_capacity: int = 65536):
        os.set_blocking(fd, False)
        self.fd = fd
        self.max_read = max_read
        self._init_tx(tx_capacity)
        self.bytes_rx = 0

    def read(self) -> bytes:
        try:
            data = os.read(self.fd, self.max_read)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:          # the other side is closed
            return b""
        self.bytes_rx += len(data)
        return data

    def flush(self) -> None:
        while self._tx:
            try:
                n = os.write(self.fd, self._tx)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.tx_errors += 1
                self._tx.clear()
                return
            self.bytes_tx += n
            del self._tx[:n]

    def close(self) -> None:
        pass
