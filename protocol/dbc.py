"""DBC export of the CAN side of the schema (cantools writes the file).

What the DBC describes (protocol v4)
------------------------------------
A DBC message is one frame layout on one identifier. Every coiltrack message
has a single-frame form (``protocol.can``, "Single frames"): the schema
payload without the sender's ``node`` byte where the identifier carries it,
or, for the frequent messages longer than 8 bytes, their bus form
(``protocol.busform``). The export describes each message in that form, so it
decodes frames straight off the bus:

- MAG_PACKED, IMU_DELTA and CONFIG_GET (<= 8 bytes) and the bus forms of
  HEARTBEAT, TIME_SYNC, COIL_PULSE_CMD, COIL_STATUS and (v4) TIME_SYNC_REPLY
  as classic 8-byte frames: on a classic bus and on CAN FD (every frequent
  message);
- every other message as a CAN FD frame of its padded length (POSE,
  MAG_FLIP_CMD, ...): straight off a CAN FD bus. On a
  classic bus these are segmented (ISO-TP, 11-bit identifiers) and the DBC
  decodes the reassembled payload after :func:`dbc_data` (drop the sender
  byte, pad);
- signed commands and the full form of a bus-form message its form cannot
  carry (29-bit identifiers, segmented) are not in the DBC.

A bus form's signals are its fields: ``start_8us`` of COIL_PULSE_CMD is the
start modulo 2.097152 s (restore it against the latest TIME_SYNC), and
``start_late_us`` / ``end_late_us`` of COIL_STATUS are the edges less the
commanded ones; ``sync_seq_lo`` of TIME_SYNC_REPLY is ``sync_seq mod 64`` and
``node_time_late_us`` is ``node_time_us`` less the echoed TIME_SYNC's master time
and ``offset_us``.

The compact stamps carry sub-fields as signals of their own: ``t_8us``
(14 bits, 8 us units; the master time modulo 131.072 ms), ``saturated`` and
``flip`` (MAG_PACKED), ``dvel`` (IMU_DELTA: 0 delta angle, 1 delta velocity).

Every message is on the identifier with node bits zero
(``protocol.can.BASE_ID``), which no node sends on. Load the file with
``cantools.database.load_file(path, frame_id_mask=0x7C0)`` and
``db.get_message_by_frame_id(bus_id).decode(data)`` finds the message
whatever the sender (``frame_id_mask`` is a loading option, not part of the
file); the sender is ``bus_id & 0x3F``. The DBC nodes are FIRMWARE (node 1),
COIL_DRIVER (2) and SENSOR (16..63).
"""
from __future__ import annotations

from .busform import BUS_FORM_IDS
from .can import BASE_ID, FUNCTION_MASK, direct_data, direct_size, fd_length
from .schema import MESSAGES, PROTOCOL_VERSION, SCHEMA_HASH

_FLOAT = {"f32", "f64"}


def _signal(name, start_byte, f=None, bits=None, signed=False, scale=1.0, unit="", comment=None,
            is_float=False):
    from cantools.database.can import Signal
    from cantools.database.conversion import BaseConversion

    return Signal(name=name, start=start_byte * 8, length=bits, byte_order="little_endian",
                  is_signed=signed, conversion=BaseConversion.factory(scale=scale, offset=0, is_float=is_float),
                  unit=unit or None, comment=comment)


_HEADER = """VERSION "{version}"

NS_ :

BS_:

BU_: FIRMWARE COIL_DRIVER SENSOR

CM_ BU_ FIRMWARE "node id 1";
CM_ BU_ COIL_DRIVER "node id 2";
CM_ BU_ SENSOR "node ids 16..63";
BA_DEF_  "BusType" STRING ;
BA_DEF_DEF_  "BusType" "CAN FD";
BA_ "BusType" "CAN FD";
"""


def _subfield_signals(f, pos: int) -> list:
    return [_bit_signal(name, pos * 8 + b0, n, scale, unit, f"{f.name} bits {b0}..{b0 + n - 1}")
            for name, b0, n, scale, unit in f.bits]


def _bit_signal(name, start_bit, bits, scale, unit, comment):
    from cantools.database.can import Signal
    from cantools.database.conversion import BaseConversion

    return Signal(name=name, start=start_bit, length=bits, byte_order="little_endian", is_signed=False,
                  conversion=BaseConversion.factory(scale=scale, offset=0, is_float=False),
                  unit=unit or None, comment=comment)


def _bus_form_signals(form) -> list:
    from cantools.database.can import Signal
    from cantools.database.conversion import BaseConversion

    return [Signal(name=f.name, start=f.first_bit, length=f.bits, byte_order="little_endian", is_signed=f.signed,
                   conversion=BaseConversion.factory(scale=f.scale, offset=0, is_float=False),
                   unit=f.unit or None, comment=f.doc or None) for f in form.fields]


def _single_frame_signals(mdef) -> list:
    if mdef.id in BUS_FORM_IDS:
        return _bus_form_signals(BUS_FORM_IDS[mdef.id])
    sigs = []
    pos = 0
    for i, f in enumerate(mdef.fields):
        if i == 0 and mdef.sender_field:
            continue                                   # the identifier's node bits
        if f.bits:
            sigs += _subfield_signals(f, pos)
        else:
            sigs.append(_signal(f.name, pos, bits=f.size * 8, signed=f.type[0] == "i", scale=f.scale,
                                unit=f.unit, comment=f.doc or None, is_float=f.type in _FLOAT))
        pos += f.size
    return sigs


def build_database():
    """A :class:`cantools.database.can.Database` of the coiltrack messages."""
    import cantools
    from cantools.database.can import Message

    db = cantools.database.load_string(
        _HEADER.format(version=f"coiltrack protocol v{PROTOCOL_VERSION} schema {SCHEMA_HASH:#010x}"),
        database_format="dbc")
    for m in MESSAGES:
        base = BASE_ID[m.id]
        n = direct_size(m.id)
        classic = n <= 8
        where = (f"its bus form, one classic frame (classic and CAN FD bus): {BUS_FORM_IDS[m.id].doc}"
                 if m.id in BUS_FORM_IDS else
                 "one classic frame (classic and CAN FD bus)" if classic else
                 f"one CAN FD frame ({fd_length(n)} bytes, padded 0xCC); segmented on a classic bus")
        comment = (f"{m.doc} Schema id {m.id:#04x}, class {m.priority}. Single-frame form: {where}; the "
                   f"message from node n uses id {base:#05x} | n"
                   + (" (n is the sender, the payload's node field)." if m.sender_field else "."))
        db.messages.append(Message(frame_id=base, name=m.name, length=n if classic else fd_length(n),
                                   is_fd=not classic, signals=_single_frame_signals(m), comment=comment,
                                   strict=True))
    db.refresh()
    return db


def dbc_string() -> str:
    return build_database().as_dbc_string()


def dbc_data(msg_id: int, payload: bytes, context=None) -> bytes:
    """The bytes the DBC message ``msg_id`` decodes, from a schema payload (e.g. the
    payload of a reassembled classic PDU, ``pdu[1:1 + size]``): the single-frame data
    (a bus form against ``context``, a :class:`protocol.busform.BusContext`)."""
    return direct_data(msg_id, payload, fd=True, context=context)
