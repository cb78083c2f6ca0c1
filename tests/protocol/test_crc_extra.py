"""The per-message CRC extra (MAVLink CRC_EXTRA) computed here from the
documented algorithm, independently of protocol.framing: CRC-16/CCITT-FALSE
(crcmod's predefined ``crc-ccitt-false``) over header and payload, then over
the one extra byte folded from the message definition
(``sha256(canonical)[0] ^ sha256(canonical)[1]``, canonical text
``"NAME type name type name ... "``, protocol/schema.py)."""
import hashlib
import struct

import crcmod.predefined
import pytest

from coiltrack.protocol import BY_ID, BY_NAME, CrcError, decode_frame
from coiltrack.protocol.can import build_pdu, decode_pdu
from coiltrack.protocol.examples import EXAMPLES
from coiltrack.protocol.framing import build_frame, cobs_encode, parse_frame
from coiltrack.protocol.schema import Field, MessageDef

CRC = crcmod.predefined.mkCrcFun("crc-ccitt-false")
TYPES = {"u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i", "u64": "Q", "i64": "q",
         "f32": "f", "f64": "d"}


def extra(name, fields) -> int:
    """The CRC extra of a definition: ``fields`` as ``(type, name)`` pairs."""
    text = name + " " + " ".join(f"{t} {n}" for t, n in fields) + " "
    d = hashlib.sha256(text.encode()).digest()
    return d[0] ^ d[1]


def frame(msg_id, fields, values, seq=0, src=0, crc_extra=None) -> bytes:
    """An unencoded frame laid out by hand (header, payload, CRC LE)."""
    payload = struct.pack("<" + "".join(TYPES[t] for t, _ in fields), *values)
    body = bytes([len(payload), 0, seq, src, msg_id]) + payload
    crc = CRC(body + (bytes([crc_extra]) if crc_extra is not None else b""))
    return body + struct.pack("<H", crc)


def fields_of(name):
    return [(f.type, f.name) for f in BY_NAME[name].fields]


def test_check_value_of_the_crc():
    assert CRC(b"123456789") == 0x29B1


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_every_frame_carries_the_documented_crc_with_the_extra(name):
    """Catches a dropped or constant CRC extra even after the golden files
    were regenerated from the same code: the CRC here is computed from the
    definition, not by the framing module."""
    ex = EXAMPLES[name]
    mine = frame(ex.msg.ID, fields_of(name), tuple(ex.msg), ex.seq, ex.src, extra(name, fields_of(name)))
    assert build_frame(ex.msg, ex.seq, ex.src) == mine
    # the same PDU on CAN (seq, payload, the same CRC)
    assert build_pdu(ex.msg, ex.seq, ex.src) == bytes([ex.seq]) + mine[5:]


def test_the_extra_differs_per_message():
    extras = {extra(m.name, fields_of(m.name)) for m in BY_ID.values()}
    assert len(extras) >= len(BY_ID) - 2           # one byte: a collision or two are possible, not all


def test_frame_without_the_extra_is_rejected():
    """A peer that computes the CRC over header and payload only."""
    ex = EXAMPLES["MAG_SAMPLE"]
    plain = frame(ex.msg.ID, fields_of("MAG_SAMPLE"), tuple(ex.msg), ex.seq, ex.src)
    with pytest.raises(CrcError):
        parse_frame(plain)
    with pytest.raises(CrcError):
        decode_pdu(ex.msg.ID, ex.src, bytes([ex.seq]) + plain[5:])


# TIME_SYNC of another schema version: same id, same 10-byte payload, fields in
# another order (u16 sync_seq first). Its payload is byte-compatible: without
# the extra the receiver would decode it with the master time shifted by two
# bytes and the sequence number taken from the time.
OTHER_TIME_SYNC = [("u16", "sync_seq"), ("u64", "master_time_us")]


def test_same_id_same_length_other_layout_is_rejected():
    d = BY_NAME["TIME_SYNC"]
    assert struct.calcsize("<HQ") == d.size
    assert extra("TIME_SYNC", OTHER_TIME_SYNC) != extra("TIME_SYNC", fields_of("TIME_SYNC"))
    raw = frame(d.id, OTHER_TIME_SYNC, (7, 123_456_789), seq=3, src=1,
                crc_extra=extra("TIME_SYNC", OTHER_TIME_SYNC))
    with pytest.raises(CrcError):
        parse_frame(raw)
    with pytest.raises(CrcError):
        decode_frame(cobs_encode(raw) + b"\x00")
    # the same bytes with this schema's extra decode (to the misread values the extra prevents)
    ours = raw[:-2] + struct.pack("<H", CRC(raw[:-2] + bytes([extra("TIME_SYNC", fields_of("TIME_SYNC"))])))
    msg = parse_frame(ours)
    assert msg.NAME == "TIME_SYNC" and msg.master_time_us != 123_456_789


def test_the_schema_folds_names_and_types_into_the_extra():
    """``MessageDef.crc_extra`` follows the documented algorithm for this
    table and for definitions that keep every byte but rename a field or
    reorder the fields (so a peer built from them fails the CRC)."""
    for m in BY_ID.values():
        assert m.crc_extra == extra(m.name, fields_of(m.name)), m.name
    base = BY_NAME["TIME_SYNC"]
    renamed = MessageDef(base.id, base.name, (Field("master_time_10us", "u64"), Field("sync_seq", "u16")))
    reordered = MessageDef(base.id, base.name, tuple(Field(n, t) for t, n in OTHER_TIME_SYNC))
    for d in (renamed, reordered):
        assert d.size == base.size
        assert d.crc_extra == extra(d.name, [(f.type, f.name) for f in d.fields]) != base.crc_extra
