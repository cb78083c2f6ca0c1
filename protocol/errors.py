"""Every decoding failure is a :class:`ProtocolError` subclass, never another exception."""


class ProtocolError(Exception):
    """Base of every protocol failure."""


class FramingError(ProtocolError):
    """COBS decoding failed, or a frame is too short or too long."""


class CrcError(ProtocolError):
    """The CRC (with the message's CRC extra byte) does not match."""


class LengthError(ProtocolError):
    """The payload length disagrees with the schema for that message id."""


class UnknownMessageError(ProtocolError):
    """The message id is not in this node's schema table."""


class EncodeError(ProtocolError):
    """A value does not fit its wire type."""


class SchemaMismatchError(ProtocolError):
    """A peer reported another protocol version or schema hash."""


class SignatureError(ProtocolError):
    """A signed frame failed verification (forged, replayed or unsigned)."""
