"""The receive stage: drain the Port, decode frames (a corrupt frame is
counted by the decoder and skipped) and route each message by its schema id:
magnetometer samples into the sensor channels' rings, IMU samples and the
source module's samples to the tracker, coil status to the pulse schedule and
the tracker, heartbeats to the schema check. The supervisor sees every
message first."""
from __future__ import annotations

from coiltrack.protocol import MSG, PROTOCOL_VERSION, SCHEMA_HASH
from coiltrack.protocol.schema import EVT_SCHEMA_MISMATCH, MAG_LSB_T

_MAG = MSG["MAG_SAMPLE"].ID
_IMU = MSG["IMU_SAMPLE"].ID
_COIL_STATUS = MSG["COIL_STATUS"].ID
_HEARTBEAT = MSG["HEARTBEAT"].ID


class Receiver:
    def __init__(self, port, decoder, channels, schedule, tracker, supervisor, tx, other=None):
        self.port = port
        self.decoder = decoder
        self.channels = {ch.node: ch for ch in channels}
        self.schedule = schedule
        self.tracker = tracker
        self.supervisor = supervisor
        self.tx = tx
        self.schema_mismatches = 0
        self.peer_hashes: dict[int, int] = {}
        self.imu_received = 0
        self.other = other            # the pipeline's handler of the messages routed nowhere else

    def step(self, now_us: int) -> None:
        data = self.port.read()
        if not data:
            return
        sup = self.supervisor
        for msg in self.decoder.feed(data):
            sup.on_message(msg, now_us)
            mid = msg.ID
            if mid == _MAG:
                ch = self.channels.get(msg.node)
                if ch is not None:
                    ch.push(msg, MAG_LSB_T)
                else:
                    self.tracker.on_mag(msg, MAG_LSB_T)
            elif mid == _IMU:
                self.imu_received += 1
                ch = self.channels.get(msg.node)
                if ch is not None:
                    ch.push_imu(msg)
                self.tracker.on_imu(msg, now_us)
            elif mid == _COIL_STATUS:
                self.schedule.on_status(msg)
                self.tracker.on_coil_status(msg)
            elif mid == _HEARTBEAT:
                self._on_heartbeat(msg)
            elif self.other is not None:
                self.other(msg, now_us)

    def _on_heartbeat(self, msg) -> None:
        self.peer_hashes[msg.node] = msg.schema_hash
        if msg.schema_hash != SCHEMA_HASH or msg.proto_version != PROTOCOL_VERSION:
            self.schema_mismatches += 1
            self.tx.event(EVT_SCHEMA_MISMATCH, msg.node)

    def counters(self) -> dict:
        d = {"schema_mismatches": self.schema_mismatches}
        d.update({"rx_" + k: v for k, v in self.decoder.counters().items()})
        return d
