"""Markdown generated from the schema table (``coiltrack schema --markdown``);
``docs/protocol.md`` embeds it between the markers below, and a test checks
that it is current."""
from __future__ import annotations

from . import schema
from .can import BASE_ID, PDU_OVERHEAD, frame_data_lengths
from .framing import CRC_LEN, HEADER_LEN, SIG_LEN
from .schema import BUS_FORMS, MESSAGES, PROTOCOL_VERSION, SCHEMA_HASH

BEGIN = "<!-- BEGIN GENERATED: coiltrack schema --markdown -->"
END = "<!-- END GENERATED -->"

_CONSTANT_GROUPS = (
    ("Node roles (HEARTBEAT.role)", "ROLE_"),
    ("Node states (HEARTBEAT.state)", "STATE_"),
    ("Well-known node ids", "NODE_"),
    ("Coil fault bits (COIL_STATUS.faults)", "COIL_FAULT_"),
    ("Pose status bits (POSE.status)", "POSE_"),
    ("Compact stamps (MAG_PACKED.stamp, IMU_DELTA.stamp)", "STAMP_"),
    ("Bus forms (COIL_PULSE_CMD, COIL_STATUS, TIME_SYNC_REPLY on CAN)", "BUS_"),
    ("Pulse ids", "PULSE_ID_"),
    ("Fault / event codes (FAULT_EVENT.code)", "EVT_"),
)


def _scale(f) -> str:
    return "" if f.scale == 1.0 else f"{f.scale:g}"


def markdown_table() -> str:
    """The message summary, the field tables and the constants, as Markdown."""
    out = [BEGIN, "",
           f"Protocol version {PROTOCOL_VERSION}, schema hash `{SCHEMA_HASH:#010x}`.", "",
           "| id | message | class | CAN id | signable | payload | serial frame | CAN PDU | classic frames | FD frames | description |",
           "|---:|---|---:|---|:---:|---:|---:|---:|---:|---:|---|"]
    for m in MESSAGES:
        serial = HEADER_LEN + m.size + CRC_LEN
        pdu = PDU_OVERHEAD + m.size
        sign = "yes" if m.signable else ""
        classic = len(frame_data_lengths(m.id))
        fd = len(frame_data_lengths(m.id, fd=True))
        if m.signable:
            serial_s = f"{serial} (+{SIG_LEN})"
            pdu_s = f"{pdu} (+{SIG_LEN})"
            classic_s = f"{classic} ({len(frame_data_lengths(m.id, signed=True))})"
        else:
            serial_s, pdu_s, classic_s = str(serial), str(pdu), str(classic)
        out.append(f"| `{m.id:#04x}` | {m.name} | {m.priority} | `{BASE_ID[m.id]:#05x}+node` | {sign} | "
                   f"{m.size} | {serial_s} | {pdu_s} | {classic_s} | {fd} | {m.doc} |")
    out.append("")
    out.append("Sizes in bytes; the serial frame is before COBS and without the 0x00 delimiter; "
               "figures in parentheses are for a signed command.")
    for m in MESSAGES:
        out += ["", f"#### `{m.id:#04x}` {m.name}", "", m.doc + f" CRC extra `{m.crc_extra:#04x}`.", "",
                "| offset | field | type | unit | scale | notes |", "|---:|---|---|---|---|---|"]
        off = 0
        for f in m.fields:
            out.append(f"| {off} | {f.name} | {f.type} | {f.unit} | {_scale(f)} | {f.doc} |")
            off += f.size
    for b in BUS_FORMS:
        out += ["", f"#### Bus form of {b.name}", "",
                f"One classic 8-byte frame on {b.name}'s identifier: {b.doc}. Bits of the 8 data bytes read as "
                "one little-endian 64-bit integer.", "",
                "| first bit | field | type | unit | scale | notes |", "|---:|---|---|---|---|---|"]
        for f in b.fields:
            scale = "" if f.scale == 1.0 else f"{f.scale:g}"
            out.append(f"| {f.first_bit} | {f.name} | {'i' if f.signed else 'u'}{f.bits} | {f.unit} | {scale} | {f.doc} |")
    out += ["", "#### Constants", ""]
    for title, prefix in _CONSTANT_GROUPS:
        names = [n for n in vars(schema) if n.startswith(prefix) and isinstance(getattr(schema, n), int)]
        if not names:
            continue
        out.append(f"{title}: " + ", ".join(f"`{n}` = {getattr(schema, n)}" for n in names) + ".")
        out.append("")
    out.append(END)
    return "\n".join(out) + "\n"


def extract_generated(text: str) -> str | None:
    """The generated block of a document (markers included), or None."""
    i = text.find(BEGIN)
    j = text.find(END)
    if i < 0 or j < 0:
        return None
    return text[i:j + len(END)] + "\n"
