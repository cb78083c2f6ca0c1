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
"""
from __future__ import annotations

from .framing import FrameDecoder


class SerialLink:
    def __init__(self, url: str, baudrate: int = 1_000_000, max_read: int = 65536,
                 tx_capacity: int = 65536, verifier=None):
        import serial  # pyserial

        self._s = serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=0)
        self.url = url
        self.max_read = max_read
        self.tx_capacity = tx_capacity
        self._tx = bytearray()
        self.decoder = FrameDecoder(verifier=verifier)
        self.bytes_rx = 0
        self.bytes_tx = 0
        self.tx_dropped = 0
        self.tx_errors = 0

    # Port ----------------------------------------------------------------
    def read(self) -> bytes:
        try:
            n = self._s.in_waiting
            data = self._s.read(min(n, self.max_read)) if n else b""
        except (OSError, ValueError):
            return b""
        except Exception:  # serial.SerialException (device gone)
            return b""
        self.bytes_rx += len(data)
        return data

    def write(self, data: bytes) -> None:
        if len(self._tx) + len(data) > self.tx_capacity:
            self.flush()
            if len(self._tx) + len(data) > self.tx_capacity:
                self.tx_dropped += 1
                return
        self._tx += data
        self.flush()

    def flush(self) -> None:
        if not self._tx:
            return
        try:
            n = self._s.write(bytes(self._tx))
        except (OSError, ValueError):
            self.tx_errors += 1
            return
        except Exception:  # serial.SerialTimeoutException / SerialException
            self.tx_errors += 1
            return
        n = len(self._tx) if n is None else n
        self.bytes_tx += n
        del self._tx[:n]

    @property
    def tx_pending(self) -> int:
        return len(self._tx)

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
