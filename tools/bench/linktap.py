"""A tap on a link: every chunk of bytes read from or written to a port is
also handed to the sinks that want it, without changing what the port does.

The firmware's Port and the emulator's link both move COBS frames (on a CAN
bus too: ``protocol.can.CanLink`` turns frames into CAN messages and back),
so one tap serves the OpenIGTLink output (``tools.outputs.igtl``, which decodes the
POSE frames) and the raw serial capture (``tools.outputs.buscapture``). A sink is a
callable taking the bytes.
"""
from __future__ import annotations

from coiltrack.firmware.port import Port


class TapPort(Port):
    """Wraps ``link``; ``rx_sinks`` see what ``read()`` returned, ``tx_sinks`` what was
    written. Every other attribute (``service``, ``flush``, ``fd``, counters) is the
    wrapped link's, so loops that look for them find them."""

    def __init__(self, link, rx_sinks=(), tx_sinks=()):
        self.link = link
        self.rx_sinks = list(rx_sinks)
        self.tx_sinks = list(tx_sinks)

    def read(self) -> bytes:
        data = self.link.read()
        if data:
            for sink in self.rx_sinks:
                sink(data)
        return data

    def write(self, data: bytes) -> None:
        for sink in self.tx_sinks:
            sink(data)
        self.link.write(data)

    def close(self) -> None:
        close = getattr(self.link, "close", None)
        if close is not None:
            close()

    def __getattr__(self, name):
        # only called for attributes TapPort itself does not have
        return getattr(self.__dict__["link"], name)
