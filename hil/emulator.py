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
from coiltrack.protocol.framing import encode_frame

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
        self._ready: dict = {}      # node id -> (prepared message, sequence number, its frame's bytes)
        self.ready_sent = 0         # prepared frames sent as they were encoded ahead

    def counters(self) -> dict:
        """What the emulator's link carried: frames received (decoded), frames it could not
        decode (bad CRC, framing, refused signature), frames sent by its nodes."""
        return {"frames_rx": self.frames_rx, "frames_bad": self.decoder.frames_bad, "frames_tx": self.frames_tx}

    def _send(self, node, msg) -> None:
        enc = self.encoders[node.node_id]
        r = self._ready.get(node.node_id) if self._ready else None
        if r is not None and r[0] is msg:
            del self._ready[node.node_id]
            self.ready_sent += r[1] == enc.seq
            self.link.write(enc.encode_prepared(msg, r[1], r[2]))
        else:
            self.link.write(enc.encode(msg))
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

    # --- wall-clock loops: physics ahead of the sampling path
    def next_due_us(self) -> int | None:
        """True time (us) of the next sample any node takes (None: no node says)."""
        due = [f() for f in (getattr(n, "next_due_us", None) for n in self.nodes) if f is not None]
        return min(due) if due else None

    def prefetch(self, until_us: int, max_n: int, min_n: int = 1) -> int:
        """Let each node that can (``SensorNode.prefetch``) compute the physics of its samples up
        to true time ``until_us`` ahead, at most ``max_n`` sample instants in all (a node with
        fewer than ``min_n`` missing waits); returns how many were computed (0: every node is
        ahead). A wall-clock loop calls it between steps, so a due sample reads its physics from
        a cache instead of computing a chunk of it while it is late."""
        n = 0
        for node in self.nodes:
            f = getattr(node, "prefetch", None)
            if f is not None and node.online and n < max_n:
                n += f(until_us, max_n - n, min(min_n, max_n - n))
        return n

    def prepare(self, until_us: int) -> int:
        """Let each sensor node that can (``SensorNode.prepare_sample``) compute its next sample
        ahead if it is due by true time ``until_us``, and encode its frame now, at its node's
        sequence number; at the sample's instant :meth:`_send` writes those bytes (encoded again
        only if the node sent another frame meanwhile). A prepared sample that no longer holds
        (a pulse committed or a flip commanded since) is computed again here. Returns how many
        samples were computed or frames encoded (0: nothing to do). A wall-clock loop calls it
        between steps, so that the step at a sample's instant only writes prepared bytes."""
        n = 0
        for s in self.sensors:
            f = getattr(s, "prepare_sample", None)
            if f is None or not s.online:
                continue
            n += f(until_us)
            msg = s.prepared_msg
            if msg is None:
                continue
            enc = self.encoders[s.node_id]
            if not hasattr(enc, "encode_prepared"):
                continue
            r = self._ready.get(s.node_id)
            if r is None or r[0] is not msg or r[1] != enc.seq:
                self._ready[s.node_id] = (msg, enc.seq, encode_frame(msg, enc.seq, enc.src))
                n += 1
        return n

