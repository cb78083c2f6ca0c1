"""The emulator: nodes and world on one link.

``step(now_us)`` (true time) releases delayed frames of a faulty link,
drains what the firmware sent, routes each message to the node(s) it is for
(``TIME_SYNC`` to every node, ``COIL_PULSE_CMD`` to the driver,
``MAG_FLIP_CMD`` to the addressed sensor) and shows every message to the
recorder (which plays the host), then lets every node act up to ``now_us``
(the driver first, so pulses are committed before the sensors sample). A
link is anything with ``read() -> bytes`` and ``write(bytes)``; the emulator
never sees the firmware, only its frames.
"""
from __future__ import annotations

from coiltrack.protocol import FrameDecoder, FrameEncoder

_ROUTE_ALL = ("TIME_SYNC",)
_TO_DRIVER = ("COIL_PULSE_CMD", "AC_DRIVE_CMD")
_TO_SENSOR = ("MAG_FLIP_CMD",)


class Emulator:
    def __init__(self, world, link, driver, sensors, recorder, verifier=None):
        self.world = world
        self.link = link
        self.driver = driver
        self.sensors = list(sensors)
        self.nodes = [driver, *self.sensors]
        self.recorder = recorder
        # verifier: optional callable(header, msg) -> bool, e.g.
        # protocol.signing.SignatureVerifier, to require signed commands
        self.decoder = FrameDecoder(verifier=verifier)
        self.encoders = {n.node_id: FrameEncoder(n.node_id) for n in self.nodes}
        self.frames_tx = 0
        self.frames_rx = 0

    def _send(self, node, msg) -> None:
        self.link.write(self.encoders[node.node_id].encode(msg))
        self.frames_tx += 1

    def step(self, now_us: int) -> None:
        service = getattr(self.link, "service", None)
        if service is not None:
            service(now_us)
        data = self.link.read()
        if data:
            for msg in self.decoder.feed(data):
                self.frames_rx += 1
                name = msg.NAME
                if name in _TO_DRIVER:
                    self.driver.handle(msg, now_us, self._send)
                elif name in _TO_SENSOR:
                    for s in self.sensors:
                        if s.node_id == msg.node:
                            s.handle(msg, now_us, self._send)
                elif name in _ROUTE_ALL:
                    for n in self.nodes:
                        n.handle(msg, now_us, self._send)
                self.recorder.on_message(msg, now_us)
        for n in self.nodes:
            n.tick(now_us, self._send)
