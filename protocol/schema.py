"""The one schema table of the coiltrack protocol.

Every message on every link (serial, CAN) is listed here once: id, name,
fields (name, wire type, unit, scale) and a one-line description. Codecs,
the per-message CRC extra byte, the schema hash reported in heartbeats,
golden byte vectors, round-trip tests and the DBC export are all derived
from this table; nothing else defines the wire format.

Field values on the wire are the *raw* values (integers or IEEE floats, little
endian). ``physical = raw * scale`` in ``unit`` (cantools convention). Times are
integer microseconds.
"""
from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass, field as dc_field
from functools import cached_property

PROTOCOL_VERSION = 4

#: wire types: struct format character and size in bytes
TYPES = {
    "u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i",
    "u64": "Q", "i64": "q", "f32": "f", "f64": "d",
}

# --- node roles and well-known node ids ------------------------------------
ROLE_FIRMWARE = 0
ROLE_COIL_DRIVER = 1
ROLE_SENSOR = 2      # magnetometer (+ optional IMU beside it)
ROLE_MONITOR = 3     # a passive tool (conformance tester, logger)

NODE_FIRMWARE = 1
NODE_COIL_DRIVER = 2
NODE_SENSOR_BASE = 16   # sensor node k has id NODE_SENSOR_BASE + k
#: the highest node id the CAN identifier carries (6 node bits); sensors 16..63
MAX_NODE_ID = 63
NODE_BROADCAST = 0

# --- node states (heartbeat) -------------------------------------------------
STATE_BOOT, STATE_READY, STATE_RUNNING, STATE_FAULT = 0, 1, 2, 3

# --- magnetometer sample scaling --------------------------------------------
#: tesla per LSB of MAG_SAMPLE counts: 16-bit signed, +/-163.84 uT full scale
MAG_LSB_T = 5e-9
#: m/s^2 per LSB of IMU accelerometer counts (+/-32.8 m/s^2)
ACC_LSB = 1e-3
#: rad/s per LSB of IMU gyroscope counts (+/-16.4 rad/s)
GYR_LSB = 5e-4
#: an IMU_SAMPLE axis at +-32767 counts (or -32768) is clipped: the sensor saturated (at its own
#: range or the field's), and the value is not a measurement (a MEMS part's output sticks at its
#: full-scale code when it saturates; PX4's drivers count a sample at that code as clipping)
IMU_CLIP_COUNTS = 32767
#: compact sample time stamps (MAG_PACKED, IMU_DELTA ``stamp``): bits 0..13 are the sample
#: time on the master clock in STAMP_LSB_US units modulo 2**STAMP_BITS (131.072 ms); the
#: receiver restores the full time from its own clock (:func:`unwrap_stamp`)
STAMP_LSB_US = 8
STAMP_BITS = 14
STAMP_MASK = (1 << STAMP_BITS) - 1
STAMP_WRAP_US = STAMP_LSB_US << STAMP_BITS
#: a stamp may lie up to this far ahead of the receiver's clock (node clock ahead, receiver's
#: tick late); it may be up to STAMP_WRAP_US - STAMP_LEAD_US behind
STAMP_LEAD_US = 16_384
#: MAG_PACKED.stamp bit 14: the sample saturated; bit 15: set/reset state (1 set)
STAMP_SATURATED = 1 << 14
STAMP_FLIP = 1 << 15
#: IMU_DELTA.stamp bit 15: 0 delta angle, 1 delta velocity; bit 14 (STAMP_SATURATED): a sample of the
#: interval clipped (the gyroscope in the delta-angle frame, the accelerometer in the delta-velocity
#: frame) or the interval's delta was beyond a frame's range: the pair is not a measurement
STAMP_DVEL = 1 << 15
#: rad per LSB of IMU_DELTA delta angle (+/-1.638 rad per frame: 16.4 rad/s at 10 Hz)
DANG_LSB_RAD = 5e-5
#: m/s per LSB of IMU_DELTA delta velocity (+/-3.277 m/s per frame: 32.8 m/s^2 at 10 Hz)
DVEL_LSB_MPS = 1e-4
#: amperes per LSB of coil currents (signed milliamperes)
CURRENT_LSB_A = 1e-3
#: AC drive plan scaling: frequency in mHz, current amplitude in uA, phase in urad
AC_FREQ_LSB_HZ = 1e-3
AC_CURRENT_LSB_A = 1e-6
AC_PHASE_LSB_RAD = 1e-6

# --- bus forms (protocol v3): the frequent messages in one 8-byte CAN frame ------------------
#: COIL_PULSE_CMD / COIL_STATUS ``pulse_id`` travels on the bus as 12 bits: ids wrap at 4096
PULSE_ID_BITS = 12
PULSE_ID_MASK = (1 << PULSE_ID_BITS) - 1
#: COIL_PULSE_CMD ``start_us`` on the bus: bits ``start_us / 8 mod 2**18`` (2.097 s); the receiver
#: restores the one time in ``[ref - BUS_START_BEHIND_US, ref - BUS_START_BEHIND_US + BUS_START_WRAP_US)``
#: where ``ref`` is the master time of the latest TIME_SYNC on the bus
BUS_START_LSB_US = 8
BUS_START_BITS = 18
BUS_START_WRAP_US = BUS_START_LSB_US << BUS_START_BITS
BUS_START_BEHIND_US = BUS_START_WRAP_US // 4
#: COIL_PULSE_CMD ``duration_us`` on the bus: 14 bits of 16 us (at most 262.128 ms)
BUS_DURATION_LSB_US = 16
BUS_DURATION_BITS = 14
#: COIL_STATUS edges on the bus: actual minus commanded (same pulse_id), signed 12-bit microseconds
BUS_EDGE_BITS = 12
BUS_EDGE_MAX_US = (1 << (BUS_EDGE_BITS - 1)) - 1
#: TIME_SYNC_REPLY on the bus (protocol v4): ``sync_seq`` as its low 6 bits, restored as the one
#: sequence number at or below the latest TIME_SYNC heard (64 broadcasts: 6 s at the firmware's
#: 10 Hz; the firmware matches replies to its last 16 broadcasts)
BUS_REPLY_SEQ_BITS = 6
#: ``node_time_us - (master_time_us of the echoed TIME_SYNC + offset_us)``: the broadcast's
#: lateness above the node's delay envelope, signed 14-bit microseconds (+-8.191 ms)
BUS_REPLY_LATE_BITS = 14
#: ``offset_us`` signed 26 bits (+-33.554431 s: node and master counters started within half a minute)
BUS_REPLY_OFFSET_BITS = 26
#: ``drift_ppb`` signed 18 bits (+-131.071 ppm: a crystal's +-100 ppm over temperature and age)
BUS_REPLY_DRIFT_BITS = 18

# --- coil fault bits (COIL_STATUS.faults) -----------------------------------
COIL_FAULT_OVER_CURRENT = 1
COIL_FAULT_OPEN_CIRCUIT = 2
COIL_FAULT_OVER_TEMPERATURE = 4
COIL_FAULT_DUTY_LIMIT = 8
COIL_FAULT_REFUSED = 16       # command refused (limits, late, bad signature)
COIL_FAULT_LATE = 32          # command arrived after its start time
COIL_FAULT_CURRENT_SAG = 64   # measured current below target (supply sag)
COIL_FAULT_SUPPLY_LOW = 128   # supply voltage below the driver's warning level (current still regulated)

# --- AC drive fault bits (AC_DRIVE_STATUS.faults) ---------------------------
AC_FAULT_FREQUENCY = 1        # frequency clipped into the driver's band
AC_FAULT_VOLTAGE = 2          # amplitude limited by the supply voltage
AC_FAULT_CURRENT = 4          # amplitude limited by the current limit
AC_FAULT_POWER = 8            # amplitude limited by the mean power limit
AC_FAULT_REFUSED = 16         # plan refused (coil, late, not synchronised)

# --- pose status bits (POSE.status) -----------------------------------------
POSE_VALID = 1          # a solution exists
POSE_FUSED = 2          # from the inertial fusion filter (else magnetic only)
POSE_DEGRADED = 4       # pulse quality flags were set on an input window
POSE_INCONSISTENT = 8   # chi-square gate or NIS monitor rejected/flagged it
POSE_STALE = 16         # no magnetic update for longer than the configured age
POSE_SATURATED = 32     # magnetometer saturation in a used window
POSE_DISTORTED = 64     # field distortion (metal) suspected
POSE_COIL_FAULT = 128   # the coil driver reported a fault in this cycle
POSE_DEAD_RECKONING = 256  # fused: no magnetic update for dead_reckon_after_us, inertial only
POSE_RECOVERED = 512    # fused: restarted from a magnetic solution, no update accepted since

# --- fault / event codes (FAULT_EVENT.code) ---------------------------------
EVT_FRAME_BAD = 1
EVT_SEQ_GAP = 2
EVT_NODE_LOST = 3
EVT_NODE_BACK = 4
EVT_COIL_FAULT = 5
EVT_SATURATION = 6
EVT_CLOCK_STEP = 7
EVT_DISTORTION = 8
EVT_SCHEMA_MISMATCH = 9
EVT_AUTH_FAIL = 10
EVT_DEADLINE_MISS = 11
EVT_PULSE_WINDOW = 12
EVT_DEAD_RECKONING = 13  # detail: node | 1 << 8 poses no longer valid | 1 << 9 magnetic updates again
# the fused track restarted; detail: node | reason << 8 (1 disagreement, 2 gap, 3 IMU break) | 1 << 12 offsets kept
EVT_TRACK_REINIT = 14


@dataclass(frozen=True)
class Field:
    name: str
    type: str
    unit: str = ""
    scale: float = 1.0
    doc: str = ""
    #: bit fields of an integer field for the DBC: ``(name, first bit, bits, scale, unit)``
    bits: tuple = ()

    @property
    def fmt(self) -> str:
        return TYPES[self.type]

    @property
    def size(self) -> int:
        return struct.calcsize("<" + self.fmt)


@dataclass(frozen=True)
class MessageDef:
    id: int
    name: str
    fields: tuple[Field, ...]
    doc: str = ""
    #: message class, used for CAN priority (lower = more urgent)
    priority: int = 4
    #: commands that move current or change configuration may be signed
    signable: bool = False
    #: the first field ``node`` is the sender's node id: a CAN single frame leaves it out
    #: (the identifier carries it)
    sender_field: bool = False
    extra: dict = dc_field(default_factory=dict, compare=False)

    @cached_property
    def fmt(self) -> str:
        return "<" + "".join(f.fmt for f in self.fields)

    @cached_property
    def size(self) -> int:
        return struct.calcsize(self.fmt)

    @cached_property
    def field_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    def canonical(self) -> str:
        """Text the CRC extra byte and schema hash are computed from."""
        return self.name + " " + " ".join(f"{f.type} {f.name}" for f in self.fields) + " "

    @cached_property
    def crc_extra(self) -> int:
        """One byte folded from the definition, mixed into every frame's CRC
        (MAVLink's CRC_EXTRA): a peer with a different definition of this
        message fails the CRC instead of misreading the payload."""
        d = hashlib.sha256(self.canonical().encode()).digest()
        return d[0] ^ d[1]


F = Field
MESSAGES: tuple[MessageDef, ...] = (
    MessageDef(0x01, "HEARTBEAT", (
        F("node", "u8", doc="sender node id"),
        F("role", "u8", doc="ROLE_*"),
        F("state", "u8", doc="STATE_*"),
        F("proto_version", "u8"),
        F("schema_hash", "u32", doc="schema_hash() of the sender's table"),
        F("errors", "u16", doc="bad frames counted since boot (saturating)"),
    ), "Every node, once a second: identity, state and the schema it speaks.", priority=6,
        sender_field=True),
    MessageDef(0x02, "TIME_SYNC", (
        F("master_time_us", "u64", "us", doc="master (firmware) clock at transmission"),
        F("sync_seq", "u16"),
    ), "Master clock broadcast; nodes estimate offset and drift from it.", priority=0),
    MessageDef(0x03, "TIME_SYNC_REPLY", (
        F("node", "u8"),
        F("sync_seq", "u16"),
        F("node_time_us", "u64", "us", doc="node clock when the TIME_SYNC arrived"),
        F("offset_us", "i32", "us", doc="node estimate of node - master"),
        F("drift_ppb", "i32", "ppb", doc="node estimate of its drift"),
    ), "A node's answer to TIME_SYNC: its clock and its correction.", priority=5, sender_field=True),
    MessageDef(0x10, "COIL_PULSE_CMD", (
        F("coil", "u8", doc="coil index on the driver"),
        F("pulse_id", "u16", doc="wraps at 4096 (PULSE_ID_MASK); echoed in COIL_STATUS"),
        F("current_ma", "i16", "A", CURRENT_LSB_A, "target current, sign gives polarity"),
        F("start_us", "u64", "us", doc="start time on the master clock"),
        F("duration_us", "u32", "us"),
    ), "Schedule one DC pulse ahead of time.", priority=1, signable=True),
    MessageDef(0x11, "COIL_STATUS", (
        F("coil", "u8"),
        F("pulse_id", "u16"),
        F("current_ma", "i16", "A", CURRENT_LSB_A, "measured steady-state current"),
        F("start_us", "u64", "us", doc="actual start on the master clock"),
        F("end_us", "u64", "us", doc="actual end on the master clock"),
        F("faults", "u8", doc="COIL_FAULT_* bits"),
    ), "What the driver did with a pulse command.", priority=2),
    MessageDef(0x20, "MAG_SAMPLE", (
        F("node", "u8"),
        F("t_us", "u64", "us", doc="sample time (node clock, sync-corrected)"),
        F("x", "i16", "T", MAG_LSB_T),
        F("y", "i16", "T", MAG_LSB_T),
        F("z", "i16", "T", MAG_LSB_T),
        F("flip", "u8", doc="bit0 set/reset state, bit1 saturated"),
    ), "One magnetometer sample in the sensor frame (full time stamp; links without a bus budget).",
        priority=3, sender_field=True),
    MessageDef(0x21, "IMU_SAMPLE", (
        F("node", "u8"),
        F("t_us", "u64", "us"),
        F("ax", "i16", "m/s^2", ACC_LSB),
        F("ay", "i16", "m/s^2", ACC_LSB),
        F("az", "i16", "m/s^2", ACC_LSB),
        F("gx", "i16", "rad/s", GYR_LSB),
        F("gy", "i16", "rad/s", GYR_LSB),
        F("gz", "i16", "rad/s", GYR_LSB),
    ), "Accelerometer (specific force) and gyroscope in the sensor frame (full time stamp); an axis "
       "at +-32767 counts is clipped (IMU_CLIP_COUNTS: the sensor saturated).", priority=3,
        sender_field=True),
    MessageDef(0x22, "MAG_FLIP_CMD", (
        F("node", "u8"),
        F("at_us", "u64", "us", doc="when to flip (master clock)"),
        F("state", "u8", doc="0 reset, 1 set"),
    ), "Schedule a magnetometer set/reset so it falls outside pulses.", priority=2),
    MessageDef(0x23, "MAG_PACKED", (
        F("node", "u8", doc="sender node id (on CAN: the identifier's node bits)"),
        F("x", "i16", "T", MAG_LSB_T),
        F("y", "i16", "T", MAG_LSB_T),
        F("z", "i16", "T", MAG_LSB_T),
        F("stamp", "u16", doc="bits 0..13 sample time / 8 us mod 2^14 (master clock), bit 14 saturated, "
                              "bit 15 set/reset state",
          bits=(("t_8us", 0, 14, STAMP_LSB_US, "us"), ("saturated", 14, 1, 1, ""), ("flip", 15, 1, 1, ""))),
    ), "One magnetometer sample in one classic CAN frame: the time as 14 bits of the master clock "
       "(8 us units, wraps every 131 ms, restored by the receiver).", priority=3, sender_field=True),
    MessageDef(0x24, "IMU_DELTA", (
        F("node", "u8", doc="sender node id (on CAN: the identifier's node bits)"),
        F("x", "i16", doc="running sum of delta angle (DANG_LSB_RAD rad) or delta velocity (DVEL_LSB_MPS m/s), "
                          "wrapped to 16 bits"),
        F("y", "i16"),
        F("z", "i16"),
        F("stamp", "u16", doc="bits 0..13 end of the interval / 8 us mod 2^14 (master clock), bit 14 "
                              "saturated (a sample of the interval clipped), bit 15 0 delta angle, 1 delta velocity",
          bits=(("t_8us", 0, 14, STAMP_LSB_US, "us"), ("saturated", 14, 1, 1, ""), ("dvel", 15, 1, 1, ""))),
    ), "Running sums of the per-interval delta angle (coning-free) or delta velocity (body frame at the "
       "interval's middle) integrated on the node; the receiver differences consecutive pairs (one stamp: "
       "one interval), so the quantisation remainder is carried and a lost pair loses no motion.", priority=3,
        sender_field=True),
    MessageDef(0x30, "POSE", (
        F("node", "u8", doc="sensor node the pose belongs to"),
        F("t_us", "u64", "us"),
        F("px", "f32", "m"), F("py", "f32", "m"), F("pz", "f32", "m"),
        F("qw", "f32"), F("qx", "f32"), F("qy", "f32"), F("qz", "f32"),
        F("var_px", "f32", "m^2"), F("var_py", "f32", "m^2"), F("var_pz", "f32", "m^2"),
        F("var_rx", "f32", "rad^2"), F("var_ry", "f32", "rad^2"), F("var_rz", "f32", "rad^2"),
        F("status", "u16", doc="POSE_* bits"),
        F("quality", "u8", doc="0-255, 255 best: the fit residual, NIS and quiet field (docs/protocol.md)"),
    ), "Sensor pose in the source frame; quaternion maps sensor to source.", priority=4),
    MessageDef(0x31, "PULSE_WINDOW", (
        F("node", "u8", doc="sensor node"),
        F("coil", "u8"),
        F("pulse_id", "u16"),
        F("first_us", "u64", "us", doc="time of the first in-pulse sample used"),
        F("last_us", "u64", "us", doc="time of the last in-pulse sample used"),
        F("n_used", "u8"),
        F("n_base", "u8", doc="baseline samples used"),
        F("flags", "u8", doc="pulse quality flags (coiltrack.firmware.measure.pulse)"),
    ), "Which samples the firmware used for one pulse amplitude (for HIL checks).", priority=6),
    MessageDef(0x40, "CONFIG_GET", (
        F("node", "u8", doc="target node"),
        F("key", "u16"),
    ), "Read one configuration value.", priority=5),
    MessageDef(0x41, "CONFIG_SET", (
        F("node", "u8", doc="target node"),
        F("key", "u16"),
        F("value", "f64"),
    ), "Write one configuration value.", priority=5, signable=True),
    MessageDef(0x42, "CONFIG_ACK", (
        F("node", "u8", doc="answering node"),
        F("key", "u16"),
        F("value", "f64"),
        F("result", "u8", doc="0 ok, 1 unknown key, 2 out of range, 3 read-only, 4 auth"),
    ), "Answer to CONFIG_GET / CONFIG_SET.", priority=5, sender_field=True),
    MessageDef(0x50, "FAULT_EVENT", (
        F("node", "u8"),
        F("t_us", "u64", "us"),
        F("code", "u16", doc="EVT_*"),
        F("detail", "u32"),
    ), "Something went wrong or changed; counted and reported, never fatal.", priority=2),
    MessageDef(0x60, "AC_DRIVE_CMD", (
        F("coil", "u8", doc="coil index on the driver"),
        F("plan_id", "u16", doc="wraps; echoed in AC_DRIVE_STATUS"),
        F("freq_mhz", "u32", "Hz", AC_FREQ_LSB_HZ, "drive frequency"),
        F("amplitude_ua", "u32", "A", AC_CURRENT_LSB_A, "target current amplitude (peak)"),
        F("ref_us", "u64", "us", doc="phase reference on the master clock: the current is "
                                     "amplitude cos(2 pi f (t - ref_us))"),
        F("start_us", "u64", "us", doc="switch-on time on the master clock"),
        F("duration_us", "u32", "us", doc="on for this long; 0: until the next plan"),
    ), "Drive one coil with a sinusoidal current (AC excitation plan, one message per coil).",
        priority=1, signable=True),
    MessageDef(0x61, "AC_DRIVE_STATUS", (
        F("coil", "u8"),
        F("plan_id", "u16"),
        F("freq_mhz", "u32", "Hz", AC_FREQ_LSB_HZ, "executed frequency"),
        F("amplitude_ua", "u32", "A", AC_CURRENT_LSB_A, "measured current amplitude (peak)"),
        F("phase_urad", "i32", "rad", AC_PHASE_LSB_RAD, "measured current phase against "
                                                         "cos(2 pi f (t - ref_us)), (-pi, pi]"),
        F("ref_us", "u64", "us", doc="the plan's phase reference (master clock)"),
        F("faults", "u8", doc="AC_FAULT_* bits"),
    ), "What the driver does with an AC plan: executed frequency, measured current phasor.", priority=2),
)
del F



@dataclass(frozen=True)
class BusField:
    """One field of a bus form: bits ``first_bit .. first_bit + bits - 1`` of the 8 data bytes read
    as one little-endian 64-bit integer (DBC ``@1``); ``physical = raw * scale`` in ``unit``."""
    name: str
    first_bit: int
    bits: int
    signed: bool = False
    scale: float = 1.0
    unit: str = ""
    doc: str = ""


@dataclass(frozen=True)
class BusForm:
    """The CAN form of a frequent message whose schema payload exceeds 8 bytes (protocol v3): one
    classic 8-byte frame on the message's identifier (``protocol.busform`` maps it to and from the
    schema message; ``docs/protocol.md``, "Bus forms")."""
    name: str
    fields: tuple[BusField, ...]
    doc: str = ""

    def canonical(self) -> str:
        return "bus " + self.name + " " + " ".join(
            f"{f.name} {f.first_bit} {'i' if f.signed else 'u'}{f.bits}" for f in self.fields) + " "


B = BusField
BUS_FORMS: tuple[BusForm, ...] = (
    BusForm("HEARTBEAT", (
        B("role", 0, 4, doc="ROLE_*"),
        B("state", 4, 4, doc="STATE_*"),
        B("proto_version", 8, 8),
        B("errors", 16, 16, doc="bad frames counted since boot (saturating)"),
        B("schema_hash", 32, 32),
    ), "role and state as 4-bit fields; the sender is the identifier's node"),
    BusForm("TIME_SYNC", (
        B("master_time_us", 0, 48, unit="us", doc="master clock at transmission (48 bits: 8.9 years)"),
        B("sync_seq", 48, 16),
    ), "the master time in 48 bits"),
    BusForm("COIL_PULSE_CMD", (
        B("coil", 0, 4),
        B("pulse_id", 4, 12, doc="pulse_id (below 4096)"),
        B("current_ma", 16, 16, True, CURRENT_LSB_A, "A", "target current, sign gives polarity"),
        B("start_8us", 32, BUS_START_BITS, False, BUS_START_LSB_US, "us",
          "start_us / 8 mod 2^18 (master clock, wraps every 2.097 s; restored against the latest TIME_SYNC)"),
        B("duration_us", 50, BUS_DURATION_BITS, False, BUS_DURATION_LSB_US, "us", "duration in 16 us units"),
    ), "the start as 18 bits of 8 us restored against the latest TIME_SYNC, the duration in 16 us units"),
    BusForm("COIL_STATUS", (
        B("coil", 0, 4),
        B("pulse_id", 4, 12),
        B("current_ma", 16, 16, True, CURRENT_LSB_A, "A", "measured steady-state current"),
        B("faults", 32, 8, doc="COIL_FAULT_* bits"),
        B("start_late_us", 40, BUS_EDGE_BITS, True, 1.0, "us", "actual start minus commanded start"),
        B("end_late_us", 52, BUS_EDGE_BITS, True, 1.0, "us", "actual end minus commanded start + duration"),
    ), "the edges as signed offsets from the command of the same pulse_id"),
    BusForm("TIME_SYNC_REPLY", (
        B("sync_seq_lo", 0, BUS_REPLY_SEQ_BITS, doc="sync_seq mod 64 (restored: the latest TIME_SYNC heard "
                                                   "with these bits, at or below the latest)"),
        B("node_time_late_us", BUS_REPLY_SEQ_BITS, BUS_REPLY_LATE_BITS, True, 1.0, "us",
          "node_time_us minus (master_time_us of the echoed TIME_SYNC + offset_us)"),
        B("offset_us", BUS_REPLY_SEQ_BITS + BUS_REPLY_LATE_BITS, BUS_REPLY_OFFSET_BITS, True, 1.0, "us",
          "node estimate of node - master"),
        B("drift_ppb", 64 - BUS_REPLY_DRIFT_BITS, BUS_REPLY_DRIFT_BITS, True, 1.0, "ppb",
          "node estimate of its drift"),
    ), "sync_seq as 6 bits restored against the latest TIME_SYNC, node_time_us as its lateness against "
       "the echoed TIME_SYNC's master time plus offset_us (protocol v4)"),
)
del B
BUS_FORM_BY_NAME: dict[str, BusForm] = {b.name: b for b in BUS_FORMS}

BY_ID: dict[int, MessageDef] = {m.id: m for m in MESSAGES}
BY_NAME: dict[str, MessageDef] = {m.name: m for m in MESSAGES}
assert len(BY_ID) == len(MESSAGES) and len(BY_NAME) == len(MESSAGES)
MAX_PAYLOAD = max(m.size for m in MESSAGES)


def schema_text() -> str:
    """The text the schema hash is computed from: the version line, one line per message
    (id and canonical text) and, from protocol v3, one line per bus form."""
    return f"coiltrack v{PROTOCOL_VERSION}\n" + "\n".join(
        [f"{m.id:#04x} {m.canonical()}" for m in MESSAGES] + [b.canonical() for b in BUS_FORMS])


def schema_hash() -> int:
    """32-bit hash of the whole table (version and bus forms included), reported in every
    HEARTBEAT; a peer reporting another hash is refused."""
    return int.from_bytes(hashlib.sha256(schema_text().encode()).digest()[:4], "little")


SCHEMA_HASH = schema_hash()


def restore_low_bits(bits: int, lo: int, nbits: int) -> int:
    """The one integer in ``[lo, lo + 2**nbits)`` whose low ``nbits`` bits are ``bits``: how every
    narrowed counter on the bus (a start, a sequence number, a sample stamp) is restored against
    a reference window."""
    return lo + ((bits - lo) & ((1 << nbits) - 1))


def pack_stamp(t_us: int) -> int:
    """The 14 time bits of a compact stamp for master time ``t_us`` (rounded to 8 us)."""
    return ((int(t_us) + STAMP_LSB_US // 2) // STAMP_LSB_US) & STAMP_MASK


def unwrap_stamp(stamp: int, now_us: int, lead_us: int = STAMP_LEAD_US) -> int:
    """The master time (us, a multiple of 8) of a compact stamp (its low 14 bits) received
    at ``now_us``: the one time in ``(now + lead - 131072 us, now + lead]`` with those bits."""
    r = (int(now_us) + lead_us) // STAMP_LSB_US
    return restore_low_bits(stamp, r - STAMP_MASK, STAMP_BITS) * STAMP_LSB_US
