"""DBC export of the CAN side of the schema (cantools writes the file).

What the DBC describes
----------------------
A DBC message is one frame layout on one identifier. The coiltrack
identifiers carry the sender node in their low 5 bits and most messages
span several ISO-TP frames, so the export contains:

- every message's **payload** as a CAN FD message ``NAME`` on the
  identifier with node bits zero (``protocol.can.BASE_ID``), ``length`` =
  payload size, signals = the schema fields (little endian, scale and unit
  from the schema). Decode the *reassembled* payload with it: the bytes after
  the seq byte of the PDU, ``pdu[1:1 + size]``.
- every message that fits **one classic frame** (an ISO-TP single frame,
  PDU <= 7 bytes) also as ``NAME_SF``, a classic 8-byte message whose
  signals are the single-frame PCI byte, the seq byte, the fields and the
  PDU CRC, on ``BASE_ID | 1`` (sent by the firmware, node 1). It decodes the
  frame as it is on the bus.

Load it with ``cantools.database.load_file(path, frame_id_mask=0x7E0)`` to
look messages up by function code whatever the sender (the mask is a
loading option, not part of the DBC file); ``NAME_SF`` then needs
``get_message_by_name``. Node ids of senders are in the comment of each
message; DBC nodes are FIRMWARE, COIL_DRIVER and SENSOR.
"""
from __future__ import annotations

from .can import BASE_ID, PDU_OVERHEAD, fd_length
from .schema import MESSAGES, NODE_FIRMWARE, PROTOCOL_VERSION, SCHEMA_HASH

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


def build_database():
    """A :class:`cantools.database.can.Database` of the coiltrack messages."""
    from cantools.database.can import Database, Message, Node

    nodes = [Node("FIRMWARE", comment="node id 1"), Node("COIL_DRIVER", comment="node id 2"),
             Node("SENSOR", comment="node ids 16..31")]
    msgs = []
    for m in MESSAGES:
        base = BASE_ID[m.id]
        comment = (f"{m.doc} Schema id {m.id:#04x}, class {m.priority}. Reassembled payload "
                   f"(PDU bytes 1..{m.size}); on the bus the message from node n uses id {base:#05x} | n, "
                   f"segmented ISO-TP style (see docs/protocol.md).")
        msgs.append(Message(frame_id=base, name=m.name, length=max(m.size, 1), is_fd=m.size > 8,
                            signals=_field_signals(m, 0), comment=comment, strict=True))
        pdu = PDU_OVERHEAD + m.size
        if pdu <= 7:
            sigs = [_signal("ISOTP_PCI", 0, bits=8, comment="single frame: 0x0L, L = PDU length"),
                    _signal("SEQ", 1, bits=8, comment="sender sequence number")]
            sigs += _field_signals(m, 2)
            sigs.append(_signal("CRC", 2 + m.size, bits=16,
                                comment="CRC-16/CCITT-FALSE of the serial header and payload, then the CRC extra"))
            msgs.append(Message(frame_id=base | NODE_FIRMWARE, name=m.name + "_SF", length=8,
                                signals=sigs, senders=["FIRMWARE"], strict=True,
                                comment=f"{m.name} as one classic ISO-TP single frame ({1 + pdu} bytes) "
                                        f"from node {NODE_FIRMWARE}."))
    db = Database(messages=msgs, nodes=nodes,
                  version=f"coiltrack protocol v{PROTOCOL_VERSION} schema {SCHEMA_HASH:#010x}")
    return db


def dbc_string() -> str:
    return build_database().as_dbc_string()


def payload_from_pdu(pdu: bytes, size: int) -> bytes:
    """The bytes a ``NAME`` DBC message decodes: the payload of a PDU."""
    return bytes(pdu[1:1 + size])


def padded(payload: bytes) -> bytes:
    """A payload padded with zeros to the next CAN FD length."""
    return payload + bytes(fd_length(len(payload)) - len(payload))
