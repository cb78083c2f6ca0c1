"""The firmware's only door to the world.

A :class:`Port` moves bytes; it never blocks. The same firmware runs on an
in-process link (simulated clock), a pseudo-terminal or a real UART, or a CAN
bus adapter, by being handed another Port.
"""
from __future__ import annotations


class Port:
    """Byte link: ``read()`` returns what has arrived (maybe b''), ``write()`` queues bytes."""

    def read(self) -> bytes:  # pragma: no cover - interface
        raise NotImplementedError

    def write(self, data: bytes) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass


class SerialPort(Port):
    """A pyserial port (``serial_for_url``: a device path, a pty, ``loop://``)."""

    def __init__(self, url: str, baudrate: int = 1_000_000):
        import serial  # pyserial; imported here so the firmware core needs it only when used

        self._s = serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=0)

    def read(self) -> bytes:
        n = self._s.in_waiting
        return self._s.read(n) if n else b""

    def write(self, data: bytes) -> None:
        self._s.write(data)

    def close(self) -> None:
        self._s.close()
