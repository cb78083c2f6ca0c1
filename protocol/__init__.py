"""coiltrack binary protocol: one schema table, codecs, framing and transports."""
from .codec import CLASS_BY_ID, MSG, physical, unpack_payload
from .errors import (CrcError, EncodeError, FramingError, LengthError, ProtocolError,
                     SchemaMismatchError, SignatureError, UnknownMessageError)
from .framing import FrameDecoder, FrameEncoder, cobs_decode, cobs_encode, decode_frame, encode_frame
from .schema import BY_ID, BY_NAME, MESSAGES, PROTOCOL_VERSION, SCHEMA_HASH, schema_hash

__all__ = [
    "MSG", "CLASS_BY_ID", "physical", "unpack_payload", "ProtocolError", "CrcError", "EncodeError",
    "FramingError", "LengthError", "SchemaMismatchError", "SignatureError", "UnknownMessageError",
    "FrameDecoder", "FrameEncoder", "cobs_decode", "cobs_encode", "decode_frame", "encode_frame",
    "BY_ID", "BY_NAME", "MESSAGES", "PROTOCOL_VERSION", "SCHEMA_HASH", "schema_hash",
]
