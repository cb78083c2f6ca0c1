"""coiltrack binary protocol: one schema table, codecs, framing and transports."""
from .codec import CLASS_BY_ID, MSG, physical, unpack_payload
from .errors import (CrcError, EncodeError, FramingError, LengthError, ProtocolError,
                     SchemaMismatchError, SignatureError, UnknownMessageError)
from .framing import FrameDecoder, FrameEncoder, cobs_decode, cobs_encode, decode_frame, encode_frame
from .peer import check_peer
from .schema import BY_ID, BY_NAME, MESSAGES, PROTOCOL_VERSION, SCHEMA_HASH, schema_hash
from .signing import SignatureVerifier, SignedFrameEncoder, Signer

__all__ = [
    "MSG", "CLASS_BY_ID", "physical", "unpack_payload", "ProtocolError", "CrcError", "EncodeError",
    "FramingError", "LengthError", "SchemaMismatchError", "SignatureError", "UnknownMessageError",
    "FrameDecoder", "FrameEncoder", "cobs_decode", "cobs_encode", "decode_frame", "encode_frame",
    "BY_ID", "BY_NAME", "MESSAGES", "PROTOCOL_VERSION", "SCHEMA_HASH", "schema_hash",
    "check_peer", "Signer", "SignatureVerifier", "SignedFrameEncoder",
    # CAN (python-can), imported on first use: protocol.can
    "CanCodec", "CanLink", "CanReassembler", "open_bus", "virtual_bus_pair",
]

_LAZY_CAN = ("CanCodec", "CanLink", "CanReassembler", "open_bus", "virtual_bus_pair")


def __getattr__(name):
    """``protocol.CanLink`` and friends import python-can only when used."""
    if name in _LAZY_CAN:
        from . import can

        return getattr(can, name)
    raise AttributeError(f"module 'protocol' has no attribute {name!r}")
