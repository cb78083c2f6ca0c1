"""The firmware's only door to the world.

A :class:`Port` moves bytes; it never blocks. The same firmware runs on an
in-process link (simulated clock), a pseudo-terminal or a real UART, or a CAN
bus adapter, by being handed another Port.

:class:`Port` is the link's contract (a ``typing.Protocol``). A link implements it by
subclassing (the links of ``tools/bench``, :class:`SerialPort`) or structurally, by having
the three methods: the links of :mod:`coiltrack.protocol` (``protocol.can.CanLink``,
``protocol.serial_link.SerialLink`` and ``FdPort``) cannot import the firmware
(``firmware_py -> protocol``, never back) and implement it so.
``tests/firmware/test_seams.py`` checks every link against it.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable


@runtime_checkable
class Port(Protocol):
    """Byte link: ``read()`` returns what has arrived (maybe b''), ``write()`` queues bytes.

    Reads: the link's receive side, never blocking (what has arrived, at most what the link
    buffers). Owns: the link (its descriptor, bus or buffers) and closes it.
    Returns: bytes as they arrived; frame boundaries are the codec's business
    (:mod:`coiltrack.protocol.framing` or the CAN reassembler), not the port's.
    Work bound: O(bytes moved) per call; :meth:`write` queues what the link cannot take now
    or counts it lost, and never waits.
    """

    def read(self) -> bytes:  # pragma: no cover - interface
        raise NotImplementedError

    def write(self, data: bytes) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        """Release the link (a link with nothing to release keeps this default)."""


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
