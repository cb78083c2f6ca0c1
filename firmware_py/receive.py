"""The receive stage: drain the Port, decode frames (a corrupt frame is
counted by the decoder and skipped) and route each message by its schema id:
magnetometer samples into the sensor channels' rings, IMU samples and the
source module's samples to the tracker, coil status to the pulse schedule and
the tracker, heartbeats to the schema check. The supervisor sees every
message first.

Calibration: a node with a :class:`coiltrack.firmware.calibration.SensorCalibration`
has its magnetometer ellipsoid and its IMU model inverted here, the one place
every sample enters (before the rings, the pulse windows and the one
strapdown): the stages downstream receive a preallocated view of the message
whose readings are the corrected ones, in the message's own units (counts).
The supervisor sees the raw message (saturation is a property of the
reading)."""
from __future__ import annotations

from coiltrack.protocol import MSG, PROTOCOL_VERSION, SCHEMA_HASH
from coiltrack.protocol.schema import ACC_LSB, EVT_SCHEMA_MISMATCH, GYR_LSB, MAG_LSB_T

_MAG = MSG["MAG_SAMPLE"].ID
_IMU = MSG["IMU_SAMPLE"].ID
_COIL_STATUS = MSG["COIL_STATUS"].ID
_HEARTBEAT = MSG["HEARTBEAT"].ID
_INV_MAG = 1.0 / MAG_LSB_T
_INV_ACC = 1.0 / ACC_LSB
_INV_GYR = 1.0 / GYR_LSB


class _MagView:
    """A MAG_SAMPLE with corrected readings (counts), reused for every sample."""
    __slots__ = ("ID", "node", "t_us", "x", "y", "z", "flip")

    def __init__(self):
        self.ID, self.node, self.t_us, self.x, self.y, self.z, self.flip = _MAG, 0, 0, 0.0, 0.0, 0.0, 0


class _ImuView:
    """An IMU_SAMPLE with corrected readings (counts), reused for every sample."""
    __slots__ = ("ID", "node", "t_us", "ax", "ay", "az", "gx", "gy", "gz")

    def __init__(self):
        self.ID, self.node, self.t_us = _IMU, 0, 0
        self.ax = self.ay = self.az = self.gx = self.gy = self.gz = 0.0


class Receiver:
    def __init__(self, port, decoder, channels, schedule, tracker, supervisor, tx, other=None, calibration=None):
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
        cal = calibration or {}
        # node -> SensorCalibration, for the nodes whose magnetometer / IMU is calibrated
        self.mag_cal = {n: c for n, c in cal.items() if c.has_mag}
        self.imu_cal = {n: c for n, c in cal.items() if c.has_imu}
        self._magv = _MagView()
        self._imuv = _ImuView()

    def step(self, now_us: int) -> None:
        data = self.port.read()
        if not data:
            return
        sup = self.supervisor
        for msg in self.decoder.feed(data):
            sup.on_message(msg, now_us)
            mid = msg.ID
            if mid == _MAG:
                c = self.mag_cal.get(msg.node) if self.mag_cal else None
                if c is not None:
                    msg = self._correct_mag(msg, c)
                ch = self.channels.get(msg.node)
                if ch is not None:
                    ch.push(msg, MAG_LSB_T)
                else:
                    self.tracker.on_mag(msg, MAG_LSB_T)
            elif mid == _IMU:
                self.imu_received += 1
                c = self.imu_cal.get(msg.node) if self.imu_cal else None
                if c is not None:
                    msg = self._correct_imu(msg, c)
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

    def _correct_mag(self, msg, c):
        """The sample with its ellipsoid inverted (calibration ``mag_soft``, ``mag_hard_t``)."""
        v = self._magv
        x, y, z = c.correct_mag(msg.x * MAG_LSB_T, msg.y * MAG_LSB_T, msg.z * MAG_LSB_T)
        v.node, v.t_us, v.flip = msg.node, msg.t_us, msg.flip
        v.x, v.y, v.z = x * _INV_MAG, y * _INV_MAG, z * _INV_MAG
        return v

    def _correct_imu(self, msg, c):
        """The sample with the IMU model inverted and rotated into the magnetometer's frame."""
        v = self._imuv
        fx, fy, fz, wx, wy, wz = c.correct_imu(msg.ax * ACC_LSB, msg.ay * ACC_LSB, msg.az * ACC_LSB,
                                               msg.gx * GYR_LSB, msg.gy * GYR_LSB, msg.gz * GYR_LSB)
        v.node, v.t_us = msg.node, msg.t_us
        v.ax, v.ay, v.az = fx * _INV_ACC, fy * _INV_ACC, fz * _INV_ACC
        v.gx, v.gy, v.gz = wx * _INV_GYR, wy * _INV_GYR, wz * _INV_GYR
        return v

    def _on_heartbeat(self, msg) -> None:
        self.peer_hashes[msg.node] = msg.schema_hash
        if msg.schema_hash != SCHEMA_HASH or msg.proto_version != PROTOCOL_VERSION:
            self.schema_mismatches += 1
            self.tx.event(EVT_SCHEMA_MISMATCH, msg.node)

    def counters(self) -> dict:
        d = {"schema_mismatches": self.schema_mismatches}
        d.update({"rx_" + k: v for k, v in self.decoder.counters().items()})
        return d
