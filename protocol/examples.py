"""Fixed example values for every message: the source of the golden byte
vectors (``protocol/golden/``), the DBC decoding test and the docs.

Every value is exactly representable on the wire (floats are dyadic), so
``decode(encode(example)) == example`` holds exactly. Each example names the
node that naturally sends it and a sequence number.

The signing example (``SIGNING_KEY``, ``SIGNING_LINK_ID``,
``SIGNING_TIMESTAMP``) gives a signed vector for each signable command; an
implementer checks their HMAC against ``golden/serial/NAME.signed.bin``.
"""
from __future__ import annotations

from dataclasses import dataclass

from .codec import MSG
from .schema import (COIL_FAULT_CURRENT_SAG, EVT_SEQ_GAP, MESSAGES, NODE_COIL_DRIVER, NODE_FIRMWARE,
                     NODE_SENSOR_BASE, POSE_FUSED, POSE_VALID, PROTOCOL_VERSION, ROLE_SENSOR,
                     SCHEMA_HASH, STAMP_FLIP, STATE_RUNNING, pack_stamp)


@dataclass(frozen=True)
class Example:
    name: str
    src: int
    seq: int
    msg: object


S = NODE_SENSOR_BASE
_VALUES = {
    "HEARTBEAT": (S, 7, dict(node=S, role=ROLE_SENSOR, state=STATE_RUNNING, proto_version=PROTOCOL_VERSION,
                             schema_hash=SCHEMA_HASH, errors=3)),
    # the TIME_SYNC heard before the command and the status below: their bus forms restore against it
    "TIME_SYNC": (NODE_FIRMWARE, 1, dict(master_time_us=2_000_150_250, sync_seq=42)),
    # the driver heard that TIME_SYNC 377 us late against its delay envelope (bus form: node_time_late_us)
    "TIME_SYNC_REPLY": (NODE_COIL_DRIVER, 2, dict(node=NODE_COIL_DRIVER, sync_seq=42,
                                                  node_time_us=2_000_150_500, offset_us=-127, drift_ppb=-2500)),
    "COIL_PULSE_CMD": (NODE_FIRMWARE, 3, dict(coil=1, pulse_id=513, current_ma=1500,
                                             start_us=2_000_200_000, duration_us=60_000)),
    # edges 13 us late and 12 us early against the command: the bus form's start_late_us, end_late_us
    "COIL_STATUS": (NODE_COIL_DRIVER, 4, dict(coil=1, pulse_id=513, current_ma=1497, start_us=2_000_200_013,
                                             end_us=2_000_259_988, faults=COIL_FAULT_CURRENT_SAG)),
    "MAG_SAMPLE": (S, 5, dict(node=S, t_us=2_000_208_333, x=1234, y=-2345, z=3456, flip=1)),
    "IMU_SAMPLE": (S + 1, 6, dict(node=S + 1, t_us=2_000_210_000, ax=120, ay=-340, az=9810,
                                   gx=-12, gy=34, gz=-56)),
    # 2_000_208_333 us -> stamp bits (2_000_208_333 + 4) // 8 mod 2**14 = 0x1EA2, set state (bit 15)
    "MAG_PACKED": (S, 17, dict(node=S, x=1234, y=-2345, z=3456, stamp=pack_stamp(2_000_208_333) | STAMP_FLIP)),
    # node 40: a sensor id beyond v1's 5-bit node field; delta angle (bit 15 clear)
    "IMU_DELTA": (S + 24, 18, dict(node=S + 24, x=-420, y=1337, z=12, stamp=pack_stamp(2_000_250_000))),
    "MAG_FLIP_CMD": (NODE_FIRMWARE, 8, dict(node=S, at_us=2_000_700_000, state=1)),
    "POSE": (NODE_FIRMWARE, 9, dict(node=S, t_us=2_000_330_000, px=0.25, py=-0.125, pz=0.0625,
                                    qw=0.5, qx=0.5, qy=-0.5, qz=0.5,
                                    var_px=2.0 ** -20, var_py=2.0 ** -19, var_pz=2.0 ** -18,
                                    var_rx=2.0 ** -12, var_ry=2.0 ** -11, var_rz=2.0 ** -10,
                                    status=POSE_VALID | POSE_FUSED, quality=201)),
    "PULSE_WINDOW": (NODE_FIRMWARE, 10, dict(node=S, coil=1, pulse_id=513, first_us=2_000_208_333,
                                            last_us=2_000_250_000, n_used=6, n_base=14, flags=0)),
    "CONFIG_GET": (NODE_FIRMWARE, 11, dict(node=NODE_COIL_DRIVER, key=0x0102)),
    "CONFIG_SET": (NODE_FIRMWARE, 12, dict(node=NODE_COIL_DRIVER, key=0x0102, value=1.75)),
    "CONFIG_ACK": (NODE_COIL_DRIVER, 13, dict(node=NODE_COIL_DRIVER, key=0x0102, value=1.75, result=0)),
    "FAULT_EVENT": (NODE_FIRMWARE, 14, dict(node=NODE_FIRMWARE, t_us=2_000_400_000, code=EVT_SEQ_GAP,
                                           detail=0x00100203)),
    "AC_DRIVE_CMD": (NODE_FIRMWARE, 15, dict(coil=2, plan_id=7, freq_mhz=430_000, amplitude_ua=1_500_000,
                                            ref_us=2_000_000_000, start_us=2_000_100_000, duration_us=0)),
    "AC_DRIVE_STATUS": (NODE_COIL_DRIVER, 16, dict(coil=2, plan_id=7, freq_mhz=430_000, amplitude_ua=1_499_871,
                                                  phase_urad=-2_345, ref_us=2_000_000_000, faults=0)),
}
del S

#: one example per schema message, in schema order
EXAMPLES: dict[str, Example] = {}
for _m in MESSAGES:
    _src, _seq, _vals = _VALUES[_m.name]
    EXAMPLES[_m.name] = Example(_m.name, _src, _seq, MSG[_m.name](**_vals))
del _m, _src, _seq, _vals

#: test key for the signed golden vectors (never use it on a real system)
SIGNING_KEY = bytes(range(32))
SIGNING_LINK_ID = 1
SIGNING_TIMESTAMP = 0x00_01_23_45_67_89


def example(name: str) -> Example:
    return EXAMPLES[name]


def example_context():
    """A :class:`protocol.busform.BusContext` that has heard the TIME_SYNC and COIL_PULSE_CMD
    examples: what a station on the examples' bus knows when the command and the status arrive
    (their bus forms are relative to it)."""
    from .busform import BusContext

    ctx = BusContext()
    ctx.note(EXAMPLES["TIME_SYNC"].msg)
    ctx.note(EXAMPLES["COIL_PULSE_CMD"].msg)
    return ctx
