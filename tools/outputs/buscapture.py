"""``--capture PATH``: record what crosses a link, for ``coiltrack decode``.

* On a serial link (and the in-process byte pipe): a raw byte capture, the
  COBS frames of both directions in the order they crossed, each frame
  whole (a frame read in pieces is written when its 0x00 delimiter has
  arrived, so the two directions never interleave inside a frame). This is
  what a logic analyser or ``cat /dev/ttyUSB0`` would give, and what
  ``protocol.capture.decode_serial_bytes`` reads.
* On a CAN bus: every CAN frame sent or received, through python-can's
  writers, chosen by the file's suffix (``can.Logger``: ``.blf`` BLFWriter,
  ``.asc`` ASCWriter, ``.log`` CanutilsLogWriter), time-stamped with the
  loop's clock (simulated or wall), read back by ``can.LogReader``.
"""
from __future__ import annotations

import copy
from pathlib import Path

#: suffixes written through python-can (and read back by ``coiltrack decode``)
CAN_SUFFIXES = (".blf", ".asc", ".log")


def check_path(path: str, on_can: bool) -> str | None:
    """The reason ``path`` cannot be a capture of this kind of link, or None."""
    from coiltrack.protocol.capture import CAN_SUFFIXES as CAN_READ

    suffix = Path(path).suffix.lower()
    if on_can and suffix not in CAN_SUFFIXES:
        return f"a CAN capture is written by suffix: {', '.join(CAN_SUFFIXES)} (got '{suffix or path}')"
    if not on_can and suffix in CAN_READ:
        return f"a serial capture is raw bytes (e.g. .bin); '{suffix}' is read back as a CAN log"
    return None


class _Direction:
    """Cuts one direction's bytes into whole frames (up to and with each 0x00)."""

    def __init__(self, out):
        self.out = out
        self.pending = bytearray()

    def feed(self, data: bytes) -> None:
        self.pending += data
        end = self.pending.rfind(0)
        if end >= 0:
            self.out.write(self.pending[:end + 1])
            del self.pending[:end + 1]


class RawCapture:
    """A sink for :class:`tools.bench.linktap.TapPort`: both directions' frames into one file."""

    def __init__(self, path: str):
        self.fh = open(path, "wb")
        self._rx = _Direction(self.fh)
        self._tx = _Direction(self.fh)

    def rx(self, data: bytes) -> None:
        self._rx.feed(data)

    def tx(self, data: bytes) -> None:
        self._tx.feed(data)

    def close(self) -> None:
        for d in (self._rx, self._tx):     # a frame cut by the end of the run: kept, decode counts it
            self.fh.write(d.pending)
            d.pending.clear()
        self.fh.close()


class CapturingBus:
    """Wraps a python-can bus; every frame sent or received also goes to ``writer``
    (a ``can.Listener``), stamped ``clock_us() * 1e-6`` seconds."""

    def __init__(self, bus, writer, clock_us):
        self.bus = bus
        self.writer = writer
        self.clock_us = clock_us
        self.frames = 0

    def _log(self, msg, is_rx: bool) -> None:
        m = copy.copy(msg)
        m.timestamp = self.clock_us() * 1e-6
        m.is_rx = is_rx
        m.channel = None
        self.writer.on_message_received(m)
        self.frames += 1

    def send(self, msg, timeout=None):
        out = self.bus.send(msg, timeout=timeout)
        self._log(msg, False)
        return out

    def recv(self, timeout=None):
        msg = self.bus.recv(timeout=timeout)
        if msg is not None:
            self._log(msg, True)
        return msg

    def shutdown(self) -> None:
        self.bus.shutdown()

    def __getattr__(self, name):
        return getattr(self.__dict__["bus"], name)


class CanCapture:
    """Puts a :class:`CapturingBus` under a ``CanLink`` (``link.bus``); ``close()`` finishes the file."""

    def __init__(self, path: str, link, clock_us):
        import can

        self.writer = can.Logger(path)
        link.bus = CapturingBus(link.bus, self.writer, clock_us)

    def close(self) -> None:
        self.writer.stop()
