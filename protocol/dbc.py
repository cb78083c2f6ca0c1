"""DBC export of the CAN side of the schema (cantools writes the file).

What the DBC describes
----------------------
A DBC message is one frame layout on one identifier. The coiltrack
identifiers carry the sender node in their low 5 bits and most messages
span several ISO-TP frames, so the export contains:

- a message that fits **one classic frame** (an ISO-TP single frame, PDU
  <= 7 bytes; today CONFIG_GET) as that frame: signals are the single-frame
  PCI byte, the seq byte, the schema fields and the PDU CRC. It decodes the
  frame as it is on the bus.
- every other message's **reassembled payload** as a CAN FD message (the
  schema payload is up to 63 bytes): ``length`` = payload size, signals =
  the schema fields (little endian, scale and unit from the schema). Decode
  the bytes after the seq byte of the reassembled PDU, ``pdu[1:1 + size]``,
  with it. Real FD frames do not carry this layout (they carry the ISO-TP
  PCI and the PDU).

Every message is on the identifier with node bits zero
(``protocol.can.BASE_ID``), which no node sends on, so a tool matching
identifiers exactly never misreads a segment. Load the file with
``cantools.database.load_file(path, frame_id_mask=0x7E0)`` and
``db.get_message_by_frame_id(bus_id).decode(data)`` finds the message
whatever the sender (``frame_id_mask`` is a loading option, not part of the
file; ``decode_message`` does not apply it), where
``data`` is the frame for single-frame messages and the reassembled payload
for the others. The DBC nodes are FIRMWARE (node 1), COIL_DRIVER (2) and
SENSOR (16..31).
"""
from __future__ import annotations

from .can import BASE_ID, PDU_OVERHEAD, fd_length
from .schema import MESSAGES, PROTOCOL_VERSION, SCHEMA_HASH

_FLOAT = {"f32", "f64"}


def _signal(name, start_byte, f=None, bits=None, signed=False, scale=1.0, unit="", comment=None,
            is_float=False):
    from cantools.database.can import Signal
    from cantools.database.conversion import BaseConversion

    return Signal(name=name, start=start_byte * 8, length=bits, byte_order="little_endian",
                  is_signed=signed, conversion=BaseConversion.factory(scale=scale, offset=0, is_float=is_float),
                  unit=unit or None, comment=comment)


def _field_signals(mdef, offset: int) -> list:
    sigs = []
    pos = offset
    for f in mdef.fields:
        bits = f.size * 8
        sigs.append(_signal(f.name, pos, bits=bits, signed=f.type[0] == "i", scale=f.scale,
                            unit=f.unit, comment=f.doc or None, is_float=f.type in _FLOAT))
        pos += f.size
    return sigs


_HEADER = """VERSION "{version}"

NS_ :

BS_:

BU_: FIRMWARE COIL_DRIVER SENSOR

CM_ BU_ FIRMWARE "node id 1";
CM_ BU_ COIL_DRIVER "node id 2";
CM_ BU_ SENSOR "node ids 16..31";
BA_DEF_  "BusType" STRING ;
BA_DEF_DEF_  "BusType" "CAN FD";
BA_ "BusType" "CAN FD";
"""


def build_database():
    """A :class:`cantools.database.can.Database` of the coiltrack messages."""
    import cantools
    from cantools.database.can import Message

    db = cantools.database.load_string(
        _HEADER.format(version=f"coiltrack protocol v{PROTOCOL_VERSION} schema {SCHEMA_HASH:#010x}"),
        database_format="dbc")
    for m in MESSAGES:
        base = BASE_ID[m.id]
        pdu = PDU_OVERHEAD + m.size
        if pdu <= 7:
            sigs = [_signal("ISOTP_PCI", 0, bits=8, comment="single frame: 0x0L, L = PDU length"),
                    _signal("SEQ", 1, bits=8, comment="sender sequence number")]
            sigs += _field_signals(m, 2)
            sigs.append(_signal("CRC", 2 + m.size, bits=16,
                                comment="CRC-16/CCITT-FALSE of the serial header and payload, then the CRC extra"))
            comment = (f"{m.doc} Schema id {m.id:#04x}, class {m.priority}. One classic ISO-TP single frame "
                       f"({1 + pdu} bytes) as on the bus; the message from node n uses id {base:#05x} | n.")
            db.messages.append(Message(frame_id=base, name=m.name, length=1 + pdu, signals=sigs,
                                       comment=comment, strict=True))
        else:
            comment = (f"{m.doc} Schema id {m.id:#04x}, class {m.priority}. Reassembled payload "
                       f"(PDU bytes 1..{m.size}); on the bus the message from node n uses id {base:#05x} | n, "
                       f"segmented ISO-TP style (docs/protocol.md).")
            db.messages.append(Message(frame_id=base, name=m.name, length=m.size, is_fd=m.size > 8,
                                       signals=_field_signals(m, 0), comment=comment, strict=True))
    db.refresh()
    return db


def dbc_string() -> str:
    return build_database().as_dbc_string()


def payload_from_pdu(pdu: bytes, size: int) -> bytes:
    """The bytes a ``NAME`` DBC message decodes: the payload of a PDU."""
    return bytes(pdu[1:1 + size])


def padded(payload: bytes) -> bytes:
    """A payload padded with zeros to the next CAN FD length."""
    return payload + bytes(fd_length(len(payload)) - len(payload))
