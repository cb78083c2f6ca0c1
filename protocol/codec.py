"""Payload codecs compiled once from the schema table.

Each message becomes a plain value class (a ``namedtuple`` with the schema's
field names, like python-can's ``Message`` a value object with no behaviour)
and a precompiled :class:`struct.Struct`. Values are the raw wire values
(``physical = raw * scale``; see :func:`physical`).
"""
from __future__ import annotations

import struct
from collections import namedtuple

from .errors import EncodeError, LengthError, UnknownMessageError
from .schema import BY_ID, MESSAGES, MessageDef


def _class_name(name: str) -> str:
    return "".join(p.capitalize() for p in name.lower().split("_"))


#: message classes by schema name, e.g. ``MSG["MAG_SAMPLE"](node=16, ...)``
MSG: dict[str, type] = {}
#: compiled payload structs by message id
STRUCTS: dict[int, struct.Struct] = {}

for _m in MESSAGES:
    _cls = namedtuple(_class_name(_m.name), _m.field_names)
    _cls.ID = _m.id
    _cls.NAME = _m.name
    _cls.DEF = _m
    _cls.__doc__ = f"{_m.name} (id {_m.id:#04x}): {_m.doc}"
    MSG[_m.name] = _cls
    STRUCTS[_m.id] = struct.Struct(_m.fmt)
    globals()[_cls.__name__] = _cls
del _m, _cls

CLASS_BY_ID: dict[int, type] = {cls.ID: cls for cls in MSG.values()}


def message_def(msg_id: int) -> MessageDef:
    try:
        return BY_ID[msg_id]
    except KeyError:
        raise UnknownMessageError(f"unknown message id {msg_id:#04x}") from None


def pack_payload_into(msg, buf: bytearray, offset: int) -> int:
    """Pack ``msg`` into ``buf`` at ``offset``; returns the payload length."""
    st = STRUCTS[msg.ID]
    try:
        st.pack_into(buf, offset, *msg)
    except struct.error as exc:
        raise EncodeError(f"{msg.NAME}: {exc}") from None
    return st.size


def unpack_payload(msg_id: int, data, offset: int = 0, length: int | None = None):
    """Decode one payload; raises :class:`ProtocolError` subclasses only."""
    st = STRUCTS.get(msg_id)
    if st is None:
        raise UnknownMessageError(f"unknown message id {msg_id:#04x}")
    if length is not None and length != st.size:
        raise LengthError(f"{BY_ID[msg_id].name}: payload {length} bytes, schema says {st.size}")
    try:
        values = st.unpack_from(data, offset)
    except struct.error as exc:
        raise LengthError(f"{BY_ID[msg_id].name}: {exc}") from None
    return CLASS_BY_ID[msg_id]._make(values)


def physical(msg, name: str) -> float:
    """A field's physical value: ``raw * scale`` in the schema's unit."""
    f = msg.DEF.fields[msg._fields.index(name)]
    return getattr(msg, name) * f.scale
