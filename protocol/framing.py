"""Serial framing: header, payload, CRC-16, COBS, 0x00 delimiter.

Frame before COBS (little endian)::

    0  u8   len       payload length
    1  u8   flags     bit0: signed (13-byte signature follows the CRC)
    2  u8   seq       per-sender sequence number, wraps at 256
    3  u8   src       sender node id
    4  u8   msg_id    schema id
    5  len  payload   struct-packed fields, see protocol.schema
    5+len   u16 crc   CRC-16/CCITT-FALSE over bytes 0..5+len-1, then the
                      message's CRC extra byte (schema-derived, as MAVLink)
    [7+len  13 bytes  signature: link id u8, timestamp u48 (10 us units),
                      HMAC-SHA256 truncated to 6 bytes]

The whole is COBS-encoded (no 0x00 inside) and terminated by one 0x00. A
receiver resynchronises at the next 0x00 after any garbage.
"""
from __future__ import annotations

import crcmod

from .codec import CLASS_BY_ID, STRUCTS, pack_payload_into, unpack_payload
from .errors import CrcError, FramingError, LengthError, ProtocolError, UnknownMessageError
from .schema import BY_ID, MAX_PAYLOAD

HEADER_LEN = 5
CRC_LEN = 2
SIG_LEN = 13
FLAG_SIGNED = 0x01
MAX_FRAME = HEADER_LEN + MAX_PAYLOAD + CRC_LEN + SIG_LEN
#: longest COBS-encoded frame, without the delimiter
MAX_ENCODED = MAX_FRAME + MAX_FRAME // 254 + 1

crc16 = crcmod.mkCrcFun(0x11021, initCrc=0xFFFF, rev=False, xorOut=0x0000)
_EXTRA = {mid: bytes([d.crc_extra]) for mid, d in BY_ID.items()}


def frame_crc(data, msg_id: int) -> int:
    """CRC-16/CCITT-FALSE of header+payload, then the message's CRC extra."""
    return crc16(_EXTRA[msg_id], crc16(bytes(data)))


def cobs_encode(data) -> bytes:
    """Consistent Overhead Byte Stuffing; the result contains no 0x00.

    Works block by block on ``bytes.split`` (no per-byte Python loop): each
    run of non-zero bytes becomes ``len+1`` followed by the run, runs of 254
    bytes or more are cut into ``0xFF`` blocks that imply no zero.
    """
    out = bytearray()
    for block in bytes(data).split(b"\x00"):
        while len(block) >= 254:
            out.append(0xFF)
            out += block[:254]
            block = block[254:]
        out.append(len(block) + 1)
        out += block
    return bytes(out)


def cobs_decode(data) -> bytes:
    """Inverse of :func:`cobs_encode`; raises :class:`FramingError` on bad input."""
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise FramingError("zero byte inside COBS data")
        end = i + code
        if end > n:
            raise FramingError("COBS block runs past the end of the frame")
        out += data[i + 1:end]
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


def _cobs_decode_short(data):
    """:func:`cobs_decode` of one delimited frame ``data`` (COBS, then 0x00) without a block of 254
    bytes (every frame shorter than 254 bytes): each code byte after the first stands where a zero
    was, so it becomes that zero in place; None for anything else (a code of 0 or 0xFF, a block
    running past the end), which :func:`cobs_decode` then judges."""
    n = len(data) - 1
    buf = bytearray(data)
    i = buf[0]
    if i == 0 or i == 0xFF:
        return None
    while i < n:
        c = buf[i]
        if c == 0 or c == 0xFF:
            return None
        buf[i] = 0
        i += c
    if i != n:
        return None
    del buf[n:]
    del buf[0]
    return buf


def build_frame(msg, seq: int = 0, src: int = 0, flags: int = 0, signature: bytes = b"") -> bytes:
    """Unencoded frame bytes (header, payload, CRC[, signature])."""
    st = STRUCTS[msg.ID]
    raw = bytearray(HEADER_LEN + st.size + CRC_LEN)
    raw[0] = st.size
    raw[1] = flags & 0xFF
    raw[2] = seq & 0xFF
    raw[3] = src & 0xFF
    raw[4] = msg.ID
    pack_payload_into(msg, raw, HEADER_LEN)
    crc = frame_crc(memoryview(raw)[:HEADER_LEN + st.size], msg.ID)
    raw[-2] = crc & 0xFF
    raw[-1] = crc >> 8
    return bytes(raw) + signature


def encode_frame(msg, seq: int = 0, src: int = 0) -> bytes:
    """One message as it goes on a serial link: COBS(frame) + b'\\x00'."""
    return cobs_encode(build_frame(msg, seq, src)) + b"\x00"


class DecodedFrame:
    """Header fields of the last decoded frame (kept by the decoder)."""
    __slots__ = ("seq", "src", "flags", "msg_id", "signature", "signed_part")

    def __init__(self):
        self.seq = self.src = self.flags = self.msg_id = 0
        self.signature = b""
        self.signed_part = b""


def parse_frame(raw, hdr: DecodedFrame | None = None):
    """Decode one unencoded frame; raises ProtocolError subclasses only."""
    n = len(raw)
    if n < HEADER_LEN + CRC_LEN:
        raise FramingError(f"frame of {n} bytes is shorter than header+CRC")
    length, flags, seq, src, msg_id = raw[0], raw[1], raw[2], raw[3], raw[4]
    d = BY_ID.get(msg_id)
    if d is None:
        raise UnknownMessageError(f"unknown message id {msg_id:#04x}")
    sig_len = SIG_LEN if flags & FLAG_SIGNED else 0
    if flags & ~FLAG_SIGNED:
        raise FramingError(f"unknown flags {flags:#04x}")
    if n != HEADER_LEN + length + CRC_LEN + sig_len:
        raise LengthError(f"frame of {n} bytes does not match its length byte {length}")
    if length != d.size:
        raise LengthError(f"{d.name}: payload {length} bytes, schema says {d.size}")
    end = HEADER_LEN + length
    crc = raw[end] | (raw[end + 1] << 8)
    if crc != frame_crc(raw[:end], msg_id):
        raise CrcError(f"{d.name}: CRC mismatch")
    msg = unpack_payload(msg_id, raw, HEADER_LEN, length)
    if hdr is not None:
        hdr.seq, hdr.src, hdr.flags, hdr.msg_id = seq, src, flags, msg_id
        hdr.signature = bytes(raw[end + CRC_LEN:]) if sig_len else b""
        hdr.signed_part = bytes(raw[:end + CRC_LEN]) if sig_len else b""
    return msg


#: per message id: (payload size, frame length, struct ``unpack_from``, class ``_make``, CRC extra byte),
#: the receive hot path's table (an unsigned frame of a known id in one lookup)
_FAST = {mid: (d.size, HEADER_LEN + d.size + CRC_LEN, STRUCTS[mid].unpack_from, CLASS_BY_ID[mid]._make, _EXTRA[mid])
         for mid, d in BY_ID.items()}


def parse_frame_fast(raw, hdr: DecodedFrame):
    """:func:`parse_frame` for the common case, an unsigned frame of a known message of the right
    length, in one table lookup and one CRC call; anything else goes to :func:`parse_frame` (the
    same result, or the same error)."""
    f = _FAST.get(raw[4]) if len(raw) > 4 else None
    if f is None or raw[1] or len(raw) != f[1] or raw[0] != f[0]:
        return parse_frame(raw, hdr)
    end = f[1] - CRC_LEN
    if crc16(f[4], crc16(raw[:end])) != raw[end] | (raw[end + 1] << 8):
        raise CrcError(f"{BY_ID[raw[4]].name}: CRC mismatch")
    msg = f[3](f[2](raw, HEADER_LEN))
    hdr.seq, hdr.src, hdr.flags, hdr.msg_id = raw[2], raw[3], 0, raw[4]
    hdr.signature = hdr.signed_part = b""
    return msg


def decode_frame(data: bytes):
    """Decode one COBS-encoded frame (with or without its trailing 0x00)."""
    if data.endswith(b"\x00"):
        data = data[:-1]
    return parse_frame(cobs_decode(data))


class FrameEncoder:
    """Per-sender encoder: keeps the sequence number and source id."""

    def __init__(self, src: int):
        self.src = src
        self.seq = 0
        self.frames = 0

    def encode(self, msg) -> bytes:
        out = encode_frame(msg, self.seq, self.src)
        self.seq = (self.seq + 1) & 0xFF
        self.frames += 1
        return out

    def encode_prepared(self, msg, seq: int, data: bytes) -> bytes:
        """``data``, the frame of ``msg`` encoded ahead at sequence number ``seq``
        (``encode_frame(msg, seq, src)``), counted and the number advanced as :meth:`encode` would,
        if ``seq`` is still the next one; else ``msg`` encoded now."""
        if seq != self.seq:
            return self.encode(msg)
        self.seq = (seq + 1) & 0xFF
        self.frames += 1
        return data

    def take_seq(self) -> int:
        """The sequence number of a frame built elsewhere (a signed one): returned, then advanced."""
        seq = self.seq
        self.seq = (seq + 1) & 0xFF
        return seq


class FrameDecoder:
    """Streaming decoder: ``feed(bytes) -> list of messages``.

    Never raises on bad input: every bad frame is counted by kind and
    skipped, and decoding resumes at the next 0x00 delimiter. The receive
    buffer is bounded (``MAX_ENCODED``); a run of bytes longer than any legal
    frame is dropped and counted as an overflow.
    """

    def __init__(self, on_frame=None, verifier=None):
        self._buf = bytearray()
        self._dropping = False
        self.header = DecodedFrame()
        self.on_frame = on_frame   # optional callback(header, msg)
        self.verifier = verifier   # optional callable(header, msg) -> bool (signing)
        self.frames_ok = 0
        self.crc_errors = 0
        self.framing_errors = 0
        self.length_errors = 0
        self.unknown_ids = 0
        self.overflows = 0
        self.rejected = 0
        self.seq_gaps = 0
        self.bytes_in = 0
        self._last_seq: dict[int, int] = {}
        self.last_error: ProtocolError | None = None

    @property
    def frames_bad(self) -> int:
        return (self.crc_errors + self.framing_errors + self.length_errors
                + self.unknown_ids + self.overflows + self.rejected)

    def counters(self) -> dict:
        return {k: getattr(self, k) for k in (
            "frames_ok", "frames_bad", "crc_errors", "framing_errors", "length_errors",
            "unknown_ids", "overflows", "rejected", "seq_gaps", "bytes_in")}

    def feed(self, data) -> list:
        out = []
        self.bytes_in += len(data)
        buf = self._buf
        start = 0
        n = len(data)
        while start < n:
            z = data.find(b"\x00", start) if isinstance(data, (bytes, bytearray)) else bytes(data).find(b"\x00", start)
            if z < 0:
                if not self._dropping:
                    buf += data[start:]
                    if len(buf) > MAX_ENCODED:
                        self.overflows += 1
                        buf.clear()
                        self._dropping = True
                break
            if self._dropping:
                self._dropping = False
                buf.clear()
            else:
                buf += data[start:z]
                if len(buf) > MAX_ENCODED:
                    self.overflows += 1
                elif buf:
                    msg = self._decode(buf)
                    if msg is not None:
                        out.append(msg)
                buf.clear()
            start = z + 1
        return out

    def take_raw(self, data):
        """:meth:`feed` of ``data`` when it is exactly one whole, good, unsigned frame of a known
        message (COBS, then the one 0x00) and nothing is buffered or verified: the same counters
        and sequence check as :meth:`feed`, the header into :attr:`header`, and the unencoded frame
        returned instead of the message (``on_frame`` is not called: the caller has the bytes, and
        :func:`parse_frame_fast` of them gives the message). Anything else: None, nothing done (the
        caller then feeds ``data``)."""
        n = len(data)
        if (n < 2 or self._buf or self._dropping or self.verifier is not None or data[-1] != 0
                or n - 1 > MAX_ENCODED or data.find(b"\x00") != n - 1):
            return None
        raw = _cobs_decode_short(data)
        f = _FAST.get(raw[4]) if raw is not None and len(raw) > 4 else None
        if f is None or raw[1] or len(raw) != f[1] or raw[0] != f[0]:
            return None
        end = f[1] - CRC_LEN
        if crc16(f[4], crc16(raw[:end])) != raw[end] | (raw[end + 1] << 8):
            return None
        self.bytes_in += n
        hdr = self.header
        hdr.seq, hdr.src, hdr.flags, hdr.msg_id = raw[2], raw[3], 0, raw[4]
        hdr.signature = hdr.signed_part = b""
        last = self._last_seq.get(hdr.src)
        if last is not None and hdr.seq != ((last + 1) & 0xFF):
            self.seq_gaps += 1
        self._last_seq[hdr.src] = hdr.seq
        self.frames_ok += 1
        return raw

    def _decode(self, enc):
        hdr = self.header
        try:
            msg = parse_frame_fast(cobs_decode(enc), hdr)
        except CrcError as exc:
            self.crc_errors += 1
            self.last_error = exc
            return None
        except LengthError as exc:
            self.length_errors += 1
            self.last_error = exc
            return None
        except UnknownMessageError as exc:
            self.unknown_ids += 1
            self.last_error = exc
            return None
        except ProtocolError as exc:
            self.framing_errors += 1
            self.last_error = exc
            return None
        if self.verifier is not None and not self.verifier(hdr, msg):
            self.rejected += 1
            return None
        last = self._last_seq.get(hdr.src)
        if last is not None and hdr.seq != ((last + 1) & 0xFF):
            self.seq_gaps += 1
        self._last_seq[hdr.src] = hdr.seq
        self.frames_ok += 1
        if self.on_frame is not None:
            self.on_frame(hdr, msg)
        return msg
