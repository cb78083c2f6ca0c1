"""The coiltrack protocol on CAN (python-can): identifiers, ISO-TP style
segmentation, a reassembler, and ``CanLink``, an adapter that lets the
firmware and the emulator run unchanged over a CAN bus.

Identifiers (standard 11-bit)
-----------------------------
::

    bit  10 9 8 | 7 6 | 5 4 3 2 1 0
         class  | index | sender node id (0..63)

``class`` is the schema's ``priority`` (0 most urgent) and ``index`` the
rank of the message among the messages of its class, ordered by message id
(so a message added later with a higher id never renumbers the others). The
upper six bits are the function code, as in CANopen (whose SYNC is 0x080
and whose node id fills the low bits); the identifier is unique per
(message, sender node), so two nodes never contend with the same id, and
since a lower identifier wins arbitration TIME_SYNC (class 0) beats
everything, then COIL_PULSE_CMD (class 1), coil status, magnetometer flips
and fault events (class 2), samples (3), poses (4), configuration and sync
replies (5), heartbeats and diagnostics (6). Class 7 is unused. Node ids on
CAN are 6 bits (protocol v2; v1 had 3 index and 5 node bits): firmware 1,
coil driver 2, sensors 16..63. A class holds at most 4 messages.

A signed message travels segmented on the 29-bit identifier ``id11 << 18``
(the 11-bit identifier in the base-id bits, extension bits zero), so its
priority among the messages is that of its 11-bit identifier.

Single frames (protocol v2)
---------------------------
A message whose payload fits one frame, unsigned, travels as that frame
alone: the data bytes are the schema payload (little endian), without the
first field ``node`` when the schema marks it as the sender
(``sender_field``: the identifier carries it), with no PCI, seq or PDU CRC
(the CAN CRC guards the frame, the HEARTBEAT schema hash the definition).
It fits a classic frame when that payload is at most 8 bytes (MAG_PACKED,
IMU_DELTA, CONFIG_GET) and a CAN FD frame when it is at most 64 bytes
(every message of the schema; padded with 0xCC to a valid FD length). A
receiver tells the forms apart by the identifier alone: an 11-bit
identifier of a message that fits the frame it arrived in (classic: 8 bytes;
FD: 64) is a single frame; a 29-bit identifier, or a message too long for
the frame, is ISO-TP. On receipt the link gives the message the next number
after the last seq it saw from that sender as its serial ``seq`` (exact for
a sender that numbers all its messages, as the serial link does, and whose
frames the receiver heard from the first); a gap in a sender's seq is counted
only between two of its PDUs (``seq_gaps``).

PDU (what is segmented)
-----------------------
Each message travels as one PDU::

    seq u8 | payload (schema size) | crc u16 LE | [signature, 13 bytes]

``crc`` is the serial frame's CRC: CRC-16/CCITT-FALSE over the five header
bytes the serial link would carry (``len, flags, seq, src, msg_id``, with
``src`` and ``msg_id`` taken from the CAN identifier) and the payload, then
the message's CRC extra byte. The CAN CRC guards each frame; this CRC guards
the reassembled PDU and, through the CRC extra, catches a peer built from
another schema on CAN exactly as on serial. A PDU 13 bytes longer than the
unsigned length is signed (serial header flag bit0); the signature is the
serial one, so a signed command verifies identically on both links.

Segmentation (ISO 15765-2 framing)
----------------------------------
Classic CAN (8 data bytes), frames not padded (DLC = bytes used)::

    single frame       0x0L | L PDU bytes                     (L <= 7)
    first frame        0x1H LL | first 6 PDU bytes            (length HLL, 12 bits)
    consecutive frame  0x2N | next 7 PDU bytes                (N = 1, 2, .. 15, 0, 1, ..)

MAG_SAMPLE (19-byte PDU) takes 3 classic frames: FF 8 bytes, CF 8, CF 7 (MAG_PACKED: one 8-byte
single frame).
With ``fd=True`` frames are CAN FD (64 bytes, padded with 0xCC to a valid FD
length): single frame ``0x00 L`` (escape) for PDUs up to 62 bytes, first
frame with 62 and consecutive frames with 63 PDU bytes. The receiver accepts
either on any bus.

The bus is a broadcast bus with many receivers, so there is no flow control:
the sender sends FF and all CFs back to back (block size 0, STmin 0), and
receivers must keep up (ISO-TP's flow control is point to point). A receiver
keeps one reassembly per identifier, i.e. per (message, sender), so messages
from different senders and different messages of one sender may interleave.
A CF with the wrong sequence nibble, a CF without FF, a CF more than
``timeout_s`` after the previous frame of its message, a new FF or SF while a
reassembly is open: the partial message is dropped and counted, and the next
SF/FF starts afresh. An exact repeat of the previous CF, or of the previous
complete PDU on the same identifier, is a duplicate and is dropped.

CanLink
-------
``CanLink(bus, node_id)`` presents the firmware's byte Port (``read() ->
bytes``, ``write(bytes)``): ``write`` takes serial COBS frames, decodes them
with :class:`protocol.framing.FrameDecoder` and sends each message as CAN
frames with the identifier of (message, frame's ``src``); ``read`` drains the
bus without blocking (``bus.recv(timeout=0)``; over slcan only the frames the
adapter held when the read began), reassembles, and returns each
good message re-encoded as a serial frame with the sender's ``seq`` and
``src`` (and its signature). Bad CAN traffic is counted in
``link.reassembler`` and never reaches the byte stream, so firmware and
emulator run unchanged.
"""
from __future__ import annotations

import itertools
import struct
import time

import can

from . import busform
from .busform import BUS_FORM_IDS, BUS_FORM_SIZE, BusContext
from .codec import CLASS_BY_ID, STRUCTS
from .errors import (CrcError, EncodeError, FramingError, LengthError, ProtocolError,
                     UnknownMessageError)
from .framing import (_EXTRA, CRC_LEN, FLAG_SIGNED, HEADER_LEN, SIG_LEN, DecodedFrame, FrameDecoder,
                      build_frame, cobs_encode, crc16, parse_frame, parse_frame_fast)
from .interfaces import message
from .slcan import line_length as slcan_line_length
from .schema import BY_ID, MAX_PAYLOAD, MESSAGES

# --- identifiers ----------------------------------------------------------
CLASS_SHIFT = 8
INDEX_SHIFT = 6
NODE_BITS = 6
INDEX_MAX = 1 << (CLASS_SHIFT - INDEX_SHIFT)
#: shift of the 11-bit identifier inside the 29-bit one of a signed (segmented) message
EXT_SHIFT = 18
NODE_MASK = (1 << NODE_BITS) - 1
MAX_CAN_NODE = NODE_MASK
#: mask that keeps the function code (class and index) of an identifier
FUNCTION_MASK = 0x7FF & ~NODE_MASK


def _assign_indices() -> dict[int, int]:
    idx: dict[int, int] = {}
    for prio in range(8):
        members = sorted(m.id for m in MESSAGES if m.priority == prio)
        if len(members) > INDEX_MAX:
            raise AssertionError(f"CAN class {prio} has {len(members)} messages; at most {INDEX_MAX} fit")
        for k, mid in enumerate(members):
            idx[mid] = k
    for m in MESSAGES:
        if not 0 <= m.priority <= 7:
            raise AssertionError(f"{m.name}: priority {m.priority} outside 0..7")
    return idx


#: message id -> index within its class
CAN_INDEX: dict[int, int] = _assign_indices()
#: message id -> identifier with node bits zero
BASE_ID: dict[int, int] = {m.id: (m.priority << CLASS_SHIFT) | (CAN_INDEX[m.id] << INDEX_SHIFT)
                           for m in MESSAGES}
_MSG_BY_BASE: dict[int, int] = {b: mid for mid, b in BASE_ID.items()}


def can_id(msg_id: int, node: int) -> int:
    """11-bit identifier of message ``msg_id`` sent by ``node``."""
    if msg_id not in BASE_ID:
        raise UnknownMessageError(f"unknown message id {msg_id:#04x}")
    if not 0 <= node <= MAX_CAN_NODE:
        raise EncodeError(f"node id {node} does not fit the {NODE_BITS}-bit CAN node field (0..{MAX_CAN_NODE})")
    return BASE_ID[msg_id] | node


def parse_id(arbitration_id: int) -> tuple[int, int]:
    """``(msg_id, sender node)`` of an identifier; raises UnknownMessageError."""
    mid = _MSG_BY_BASE.get(arbitration_id & FUNCTION_MASK)
    if mid is None or arbitration_id > 0x7FF:
        raise UnknownMessageError(f"CAN id {arbitration_id:#05x} is not a coiltrack identifier")
    return mid, arbitration_id & NODE_MASK


def ext_id(std_id: int) -> int:
    """The 29-bit identifier of a signed (segmented) message with 11-bit identifier ``std_id``."""
    return std_id << EXT_SHIFT


def std_of_ext(arbitration_id: int) -> int | None:
    """The 11-bit identifier inside a coiltrack 29-bit one, None for a foreign identifier."""
    if arbitration_id & ((1 << EXT_SHIFT) - 1) or arbitration_id >> EXT_SHIFT > 0x7FF:
        return None
    return arbitration_id >> EXT_SHIFT


def direct_size(msg_id: int) -> int:
    """Data bytes of the single-frame form of a message (payload less a sender ``node``; 8 for a
    message with a bus form, ``protocol.busform``)."""
    if msg_id in BUS_FORM_IDS:
        return BUS_FORM_SIZE
    d = BY_ID[msg_id]
    return d.size - (1 if d.sender_field else 0)


def is_direct(msg_id: int, fd: bool) -> bool:
    """True when the unsigned message travels as one frame (classic: <= 8 bytes, FD: <= 64; a
    message with a bus form: its 8-byte frame on either bus)."""
    return direct_size(msg_id) <= (64 if fd else 8)


# --- PDU ------------------------------------------------------------------
PDU_OVERHEAD = 1 + CRC_LEN           # seq + crc
MAX_PDU = PDU_OVERHEAD + MAX_PAYLOAD + SIG_LEN


def pdu_length(msg_id: int, signed: bool = False) -> int:
    return PDU_OVERHEAD + STRUCTS[msg_id].size + (SIG_LEN if signed else 0)


def pdu_from_raw(raw) -> tuple[int, int, bytes]:
    """``(msg_id, src, pdu)`` from an unencoded serial frame (validated)."""
    parse_frame(raw)
    return raw[4], raw[3], bytes([raw[2]]) + bytes(raw[HEADER_LEN:])


def build_pdu(msg, seq: int = 0, src: int = 0, signature: bytes = b"") -> bytes:
    """The PDU of ``msg`` as sent by ``src`` (signature: 13 bytes or empty)."""
    flags = FLAG_SIGNED if signature else 0
    raw = build_frame(msg, seq, src, flags, signature)
    return bytes([seq & 0xFF]) + raw[HEADER_LEN:]


def raw_from_pdu(msg_id: int, src: int, pdu) -> bytes:
    """The serial frame (unencoded) equivalent to a CAN PDU; checks lengths only."""
    d = BY_ID.get(msg_id)
    if d is None:
        raise UnknownMessageError(f"unknown message id {msg_id:#04x}")
    n = len(pdu)
    if n == PDU_OVERHEAD + d.size:
        flags = 0
    elif n == PDU_OVERHEAD + d.size + SIG_LEN:
        flags = FLAG_SIGNED
    else:
        raise LengthError(f"{d.name}: PDU of {n} bytes, expected {PDU_OVERHEAD + d.size} "
                          f"(or {PDU_OVERHEAD + d.size + SIG_LEN} signed)")
    return bytes([d.size, flags, pdu[0], src, msg_id]) + bytes(pdu[1:])


def decode_pdu(msg_id: int, src: int, pdu, hdr: DecodedFrame | None = None):
    """Decode one reassembled PDU; raises ProtocolError subclasses only."""
    return parse_frame(raw_from_pdu(msg_id, src, pdu), hdr)


# --- segmentation ---------------------------------------------------------
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
PAD = 0xCC


def fd_length(n: int) -> int:
    for L in FD_LENGTHS:
        if L >= n:
            return L
    raise EncodeError(f"{n} bytes do not fit one CAN FD frame")


def segment(pdu: bytes, fd: bool = False) -> list[bytes]:
    """Frame data bytes for one PDU (ISO 15765-2 framing, no flow control)."""
    n = len(pdu)
    if n == 0 or n > 4095:
        raise EncodeError(f"PDU of {n} bytes cannot be segmented")
    if n <= 7:
        return [bytes([n]) + pdu]
    if fd:
        if n <= 62:
            data = bytes([0x00, n]) + pdu
            return [data + bytes([PAD]) * (fd_length(len(data)) - len(data))]
        first, cf = 62, 63
    else:
        first, cf = 6, 7
    out = [bytes([0x10 | (n >> 8), n & 0xFF]) + pdu[:first]]
    sn = 1
    for i in range(first, n, cf):
        data = bytes([0x20 | sn]) + pdu[i:i + cf]
        if fd and len(data) > 8:
            data += bytes([PAD]) * (fd_length(len(data)) - len(data))
        out.append(data)
        sn = (sn + 1) & 0x0F
    return out


def frame_data_lengths(msg_id: int, signed: bool = False, fd: bool = False) -> list[int]:
    """Data bytes of each CAN frame one message takes (for bus load)."""
    if not signed and is_direct(msg_id, fd):
        n = direct_size(msg_id)
        return [fd_length(n) if fd else n]
    return [len(d) for d in segment(bytes(pdu_length(msg_id, signed)), fd)]


def direct_data(msg_id: int, payload: bytes, fd: bool, context: BusContext | None = None) -> bytes:
    """The data bytes of a single frame from a schema payload (a bus form: against ``context``;
    raises EncodeError when the bus form cannot carry it)."""
    d = BY_ID[msg_id]
    if msg_id in BUS_FORM_IDS:
        data = busform.encode(CLASS_BY_ID[msg_id]._make(STRUCTS[msg_id].unpack(payload)), context)
        if data is None:
            raise EncodeError(f"{d.name}: the bus form cannot carry this message (see protocol.busform)")
        return data
    data = bytes(payload[1:]) if d.sender_field else bytes(payload)
    if fd and len(data) > 8:
        data += bytes([PAD]) * (fd_length(len(data)) - len(data))
    return data


class CanCodec:
    """Message <-> CAN frames.

    ``encode(msg, seq, src)`` returns the list of :class:`can.Message` frames
    of one message; ``frames_from_raw(raw)`` does the same for an unencoded
    serial frame (keeping its seq, src and signature). ``reassembler()`` gives
    a :class:`CanReassembler` for the other direction; :meth:`decode_frames`
    decodes the frames of exactly one message and raises ProtocolError
    subclasses (the explicit, strict decoder).
    """

    def __init__(self, fd: bool = False, brs: bool = True, context: BusContext | None = None):
        self.fd = fd
        self.brs = brs
        #: what this station has heard (TIME_SYNC, commands), shared with its reassembler
        self.context = BusContext() if context is None else context
        #: bus-form messages the form could not carry, sent as the full payload on the 29-bit id
        self.fallbacks = 0

    def _messages(self, arb: int, pdu: bytes, timestamp: float = 0.0, signed: bool = False) -> list[can.Message]:
        if signed:
            arb = ext_id(arb)
        fd, brs = self.fd, self.fd and self.brs
        return [message(arb, signed, d, fd, brs, timestamp) for d in segment(pdu, fd)]

    def _direct(self, arb: int, msg_id: int, payload: bytes, timestamp: float) -> list[can.Message]:
        return [can.Message(arbitration_id=arb, is_extended_id=False, data=direct_data(msg_id, payload, self.fd),
                            is_fd=self.fd, bitrate_switch=self.fd and self.brs, timestamp=timestamp)]

    def encode(self, msg, seq: int = 0, src: int = 0, signature: bytes = b"",
               timestamp: float = 0.0) -> list[can.Message]:
        if msg.ID in BUS_FORM_IDS:
            return self._bus_form(msg, seq, src, signature, timestamp)
        if not signature and is_direct(msg.ID, self.fd):
            if msg.DEF.sender_field:
                src = msg.node
            st = STRUCTS[msg.ID]
            try:
                payload = st.pack(*msg)
            except struct.error as exc:
                raise EncodeError(f"{msg.NAME}: {exc}") from None
            return self._direct(can_id(msg.ID, src), msg.ID, payload, timestamp)
        return self._messages(can_id(msg.ID, src), build_pdu(msg, seq, src, signature), timestamp,
                              bool(signature))

    def _bus_form(self, msg, seq: int, src: int, signature: bytes, timestamp: float) -> list[can.Message]:
        """A message with a bus form: its 8-byte frame when the form carries it exactly, else
        (and when signed) the full PDU segmented on the 29-bit identifier."""
        if msg.DEF.sender_field and not signature:
            src = msg.node
        arb = can_id(msg.ID, src)
        ctx = self.context
        data = None if signature else busform.encode(msg, ctx)
        ctx.note(msg)
        if data is not None:
            return [can.Message(arbitration_id=arb, is_extended_id=False, data=data, is_fd=self.fd,
                                bitrate_switch=self.fd and self.brs, timestamp=timestamp)]
        if not signature:
            self.fallbacks += 1
        return self._messages(arb, build_pdu(msg, seq, src, signature), timestamp, True)

    def frames_from_raw(self, raw, timestamp: float = 0.0) -> list[can.Message]:
        msg_id, src, pdu = pdu_from_raw(raw)
        d = BY_ID[msg_id]
        signed = bool(raw[1] & FLAG_SIGNED)
        if msg_id in BUS_FORM_IDS:
            hdr = DecodedFrame()
            msg = parse_frame(raw, hdr)
            return self._bus_form(msg, hdr.seq, src, hdr.signature, timestamp)
        if not signed and is_direct(msg_id, self.fd):
            if d.sender_field:
                src = raw[HEADER_LEN]
            return self._direct(can_id(msg_id, src), msg_id, bytes(raw[HEADER_LEN:HEADER_LEN + d.size]), timestamp)
        return self._messages(can_id(msg_id, src), pdu, timestamp, signed)

    def reassembler(self, **kwargs) -> "CanReassembler":
        kwargs.setdefault("context", self.context)
        return CanReassembler(**kwargs)

    @staticmethod
    def decode_frames(frames, hdr: DecodedFrame | None = None, context: BusContext | None = None):
        """Strictly decode the frames of one message (all on one identifier); a bus form of a
        command or status is restored against ``context`` (what the station heard before)."""
        r = CanReassembler(timeout_s=None, strict=True, context=context)
        out = []
        for f in frames:
            out += r.feed_with_headers(f)
        if len(out) != 1 or r.open_reassemblies():
            raise FramingError(f"{len(frames)} frames gave {len(out)} messages"
                               + (" and an incomplete one" if r.open_reassemblies() else ""))
        h, msg = out[0]
        if hdr is not None:
            for k in DecodedFrame.__slots__:
                setattr(hdr, k, getattr(h, k))
        return msg


class _Partial:
    __slots__ = ("total", "first", "buf", "next_sn", "last_sn", "last_data", "t_last")

    def __init__(self, total: int, first: bytes, t: float):
        self.total = total
        self.first = first
        self.buf = bytearray(first[2:])
        self.next_sn = 1
        self.last_sn = 0
        self.last_data = b""
        self.t_last = t

    def add(self, sn: int, data: bytes, t: float) -> bool:
        """Append a consecutive frame's payload (``data[1:]``, up to the announced total);
        True once the PDU is complete."""
        self.buf += data[1:1 + self.total - len(self.buf)]
        self.last_sn, self.last_data, self.t_last = sn, data, t
        self.next_sn = (sn + 1) & 0x0F
        return len(self.buf) >= self.total


def _plain_singles() -> dict[int, tuple]:
    """Function code -> ``(n, msg_id, size, sender_field)`` of the messages whose single frame
    :meth:`CanReassembler.feed_serial` turns into the serial frame straight from its bytes: no bus
    form, at most 8 data bytes (a single frame on a classic and an FD bus alike), integer fields
    only (``unpack`` then ``pack`` gives back the very bytes)."""
    out = {}
    for mid, base in BASE_ID.items():
        d = BY_ID[mid]
        if mid in BUS_FORM_IDS or direct_size(mid) > 8 or set(STRUCTS[mid].format) - set("<bBhHiIqQ"):
            continue
        out[base] = (direct_size(mid), mid, d.size, bool(d.sender_field))
    return out


_PLAIN_SINGLE = _plain_singles()


class _Segmented:
    """What :meth:`CanLink.write` needs of a message it segments straight from a serial frame's bytes."""
    __slots__ = ("sender", "f32")

    def __init__(self, sender: bool, f32: tuple):
        self.sender = sender
        #: the frame offsets of the message's f32 fields: a NaN there takes the message's way (a NaN's
        #: bits need not survive struct's unpack and pack, which that way applies)
        self.f32 = f32


def _raw_segmented(fd: bool) -> dict[int, _Segmented]:
    """Message id -> :class:`_Segmented` of the messages an unsigned sender sends as a segmented PDU
    on a classic (``fd`` False) or CAN FD bus (no bus form, too long for one frame), whose frames
    :meth:`CanLink.write` takes from the serial bytes."""
    out = {}
    for mid, d in BY_ID.items():
        if mid in BUS_FORM_IDS or is_direct(mid, fd):
            continue
        offs, at = [], HEADER_LEN
        for ch in STRUCTS[mid].format.lstrip("<"):
            if ch == "f":
                offs.append(at)
            at += struct.calcsize("<" + ch)
        assert at == HEADER_LEN + d.size, d.name
        out[mid] = _Segmented(bool(d.sender_field), tuple(offs))
    return out


def _f32_nan(offsets: tuple, raw) -> bool:
    """Whether an f32 field at one of ``offsets`` of ``raw`` holds a NaN."""
    for o in offsets:
        if raw[o + 3] & 0x7F == 0x7F and raw[o + 2] & 0x80 and (raw[o + 2] & 0x7F or raw[o + 1] or raw[o]):
            return True
    return False


#: function code -> message id of the messages with a bus form (their 8-byte single frame:
#: :meth:`CanReassembler.feed_serial` restores it and builds the serial frame without the generic path)
_BUS_SINGLE = {BASE_ID[mid]: mid for mid in BUS_FORM_IDS}
#: per bus (classic, FD): :func:`_raw_segmented`
_RAW_SEGMENTED = {False: _raw_segmented(False), True: _raw_segmented(True)}


def _copy_header(h: DecodedFrame) -> DecodedFrame:
    c = DecodedFrame()
    c.seq, c.src, c.flags, c.msg_id, c.signature, c.signed_part = (
        h.seq, h.src, h.flags, h.msg_id, h.signature, h.signed_part)
    return c


class CanReassembler:
    """Per-identifier (i.e. per sender and message) reassembly.

    ``feed(frame) -> list of messages`` never raises: every bad or unexpected
    frame is counted by kind and skipped. Time comes from ``frame.timestamp``
    (or the ``now`` argument); a reassembly idle for more than ``timeout_s``
    is dropped and counted when the next frame of its identifier arrives or
    when :meth:`expire` is called. ``verifier(header, msg) -> bool`` works as
    in :class:`protocol.framing.FrameDecoder` (signing).
    """

    COUNTERS = ("frames_in", "messages_ok", "frames_bad", "framing_errors", "crc_errors", "length_errors",
                "unknown_ids", "out_of_order", "unexpected_cf", "timeouts", "aborted", "duplicates",
                "rejected", "seq_gaps", "ignored", "single_frames", "unresolved")

    def __init__(self, timeout_s: float | None = 0.5, verifier=None, on_frame=None, strict: bool = False,
                 context: BusContext | None = None):
        #: what this station has heard (TIME_SYNC, commands): the bus forms are restored against it
        self.context = BusContext() if context is None else context
        self.timeout_s = timeout_s
        self.verifier = verifier
        self.on_frame = on_frame
        self._strict = strict
        self._partials: dict[int, _Partial] = {}
        self._last_pdu: dict[int, bytes] = {}
        self._last_seq: dict[int, int] = {}
        #: whether the sender's last seq was numbered by this receiver (a single frame carries none)
        self._synth_seq: dict[int, bool] = {}
        self.header = DecodedFrame()
        self.frames_in = 0
        self.messages_ok = 0
        self.framing_errors = 0
        self.crc_errors = 0
        self.length_errors = 0
        self.unknown_ids = 0
        self.out_of_order = 0
        self.unexpected_cf = 0
        self.timeouts = 0
        self.aborted = 0
        self.duplicates = 0
        self.rejected = 0
        self.seq_gaps = 0
        self.ignored = 0
        self.single_frames = 0
        #: bus forms that could not be restored (no TIME_SYNC heard yet, a status's command not heard)
        self.unresolved = 0
        #: bad frames or PDUs attributed to a message name
        self.bad_by_message: dict[str, int] = {}
        self.last_error: ProtocolError | None = None

    @property
    def frames_bad(self) -> int:
        """Frames or PDUs lost to errors (duplicates and ignored frames excluded)."""
        return (self.framing_errors + self.crc_errors + self.length_errors + self.unknown_ids
                + self.out_of_order + self.unexpected_cf + self.timeouts + self.aborted + self.rejected
                + self.unresolved)

    def counters(self) -> dict:
        return {k: getattr(self, k) for k in self.COUNTERS}

    def open_reassemblies(self) -> int:
        return len(self._partials)

    def expire(self, now: float) -> int:
        """Drop reassemblies idle for longer than ``timeout_s``; returns how many."""
        if self.timeout_s is None:
            return 0
        stale = [k for k, p in self._partials.items() if now - p.t_last > self.timeout_s]
        for k in stale:
            del self._partials[k]
            self._bad(k, "timeouts")
        return len(stale)

    def _bad(self, arb: int, kind: str, exc: ProtocolError | None = None) -> None:
        setattr(self, kind, getattr(self, kind) + 1)
        mid = _MSG_BY_BASE.get(arb & FUNCTION_MASK)
        if mid is not None:
            name = BY_ID[mid].name
            self.bad_by_message[name] = self.bad_by_message.get(name, 0) + 1
        if exc is not None:
            self.last_error = exc
        if self._strict:
            raise exc if exc is not None else FramingError(f"CAN id {arb:#05x}: {kind.replace('_', ' ')}")

    def feed(self, frame, now: float | None = None) -> list:
        return [m for _, m in self.feed_with_headers(frame, now)]

    def feed_with_headers(self, frame, now: float | None = None) -> list:
        """Like :meth:`feed`, returning ``(header, msg)`` pairs (header copies)."""
        self.frames_in += 1
        if frame.is_error_frame or frame.is_remote_frame:
            self.ignored += 1
            return []
        arb = frame.arbitration_id
        if frame.is_extended_id:
            std = std_of_ext(arb)
            if std is None or (std & FUNCTION_MASK) not in _MSG_BY_BASE:
                self.ignored += 1
                return []
            arb = std
        try:
            msg_id, src = parse_id(arb)
        except UnknownMessageError as exc:
            self._bad(arb, "unknown_ids", exc)
            return []
        t = frame.timestamp if now is None else now
        data = bytes(frame.data or b"")
        if not frame.is_extended_id and is_direct(msg_id, bool(frame.is_fd)):
            return self._single(arb, msg_id, src, data)
        if not data:
            self._bad(arb, "framing_errors", FramingError(f"CAN id {arb:#05x}: empty frame"))
            return []
        pci = data[0] >> 4
        part = self._partials.get(arb)
        if part is not None and self.timeout_s is not None and t - part.t_last > self.timeout_s:
            del self._partials[arb]
            part = None
            self._bad(arb, "timeouts")
        if pci == 0:
            return self._iso_single(arb, msg_id, src, data, part)
        if pci == 1:
            return self._iso_first(arb, data, part, t)
        if pci == 2:
            return self._iso_consecutive(arb, msg_id, src, data, part, t)
        if pci == 3:                                   # flow control: not used on a broadcast bus
            self.ignored += 1
            return []
        self._bad(arb, "framing_errors", FramingError(f"CAN id {arb:#05x}: unknown PCI {data[0]:#04x}"))
        return []

    def feed_serial(self, frame, out: bytearray) -> None:
        """:meth:`feed_with_headers`, each message appended to ``out`` as the serial link carries it
        (``build_frame`` with its header's seq, src, flags and signature, COBS-encoded, then 0x00:
        what :meth:`CanLink.read` returns). A plain single frame (``_PLAIN_SINGLE``: a sample's
        MAG_PACKED, IMU_DELTA) of the exact length, with no verifier or ``on_frame`` to see the
        message, becomes that frame straight from its bytes: the same counters, seq and header as
        :meth:`_single`, the same bytes as ``build_frame`` of the unpacked message; a bus form's
        frame (TIME_SYNC_REPLY, COIL_STATUS, HEARTBEAT, ...) that its context restores takes
        :meth:`_bus_single`, the same as :meth:`_single` without the generic path."""
        arb = frame.arbitration_id
        fast = bus = None
        if not (frame.is_extended_id or frame.is_error_frame or frame.is_remote_frame or arb > 0x7FF
                or self.verifier is not None or self.on_frame is not None):
            fast = _PLAIN_SINGLE.get(arb & FUNCTION_MASK)
            if fast is None:
                bus = _BUS_SINGLE.get(arb & FUNCTION_MASK)
        data = frame.data
        if bus is not None and data is not None and len(data) == BUS_FORM_SIZE:
            msg = busform.decode(bus, arb & NODE_MASK, data, self.context)
            if msg is not None:
                self._bus_single(msg, arb & NODE_MASK, out)
                return
        if fast is None or data is None or len(data) != fast[0]:
            for hdr, msg in self.feed_with_headers(frame):
                out += cobs_encode(build_frame(msg, hdr.seq, hdr.src, hdr.flags, hdr.signature))
                out.append(0)
            return
        n, msg_id, size, sender = fast
        src = arb & NODE_MASK
        self.frames_in += 1
        seq = (self._last_seq.get(src, -1) + 1) & 0xFF      # the sender's previous seq + 1 (_single)
        self._last_seq[src] = seq
        self._synth_seq[src] = True
        hdr = self.header
        hdr.seq, hdr.src, hdr.flags, hdr.msg_id, hdr.signature, hdr.signed_part = seq, src, 0, msg_id, b"", b""
        self.single_frames += 1
        self.messages_ok += 1
        raw = bytearray((size, 0, seq, src, msg_id))
        if sender:
            raw.append(src)
        raw += data
        crc = crc16(_EXTRA[msg_id], crc16(raw))
        raw.append(crc & 0xFF)
        raw.append(crc >> 8)
        for block in raw.split(b"\x00"):                 # COBS (cobs_encode; a frame this short has
            out.append(len(block) + 1)                  # no block of 254 bytes)
            out += block
        out.append(0)

    def _bus_single(self, msg, src: int, out: bytearray) -> None:
        """:meth:`feed_serial` of a bus form's frame (``protocol.busform``) whose message ``msg`` was
        restored: :meth:`_single`'s counters, seq, header and context, then the serial frame
        (``build_frame``, COBS inline: a frame this short has no block of 254 bytes)."""
        self.frames_in += 1
        self.context.note(msg)
        seq = (self._last_seq.get(src, -1) + 1) & 0xFF      # the sender's previous seq + 1 (_single)
        self._last_seq[src] = seq
        self._synth_seq[src] = True
        hdr = self.header
        hdr.seq, hdr.src, hdr.flags, hdr.msg_id, hdr.signature, hdr.signed_part = seq, src, 0, msg.ID, b"", b""
        self.single_frames += 1
        self.messages_ok += 1
        for block in build_frame(msg, seq, src).split(b"\x00"):
            out.append(len(block) + 1)
            out += block
        out.append(0)

    def _iso_single(self, arb: int, msg_id: int, src: int, data: bytes, part) -> list:
        """An ISO-TP single frame (PCI 0): its length (CAN FD: in byte 1), then the PDU."""
        L = data[0] & 0x0F
        start = 1
        if L == 0:                                  # CAN FD escape: length in byte 1
            if len(data) < 2:
                self._bad(arb, "framing_errors", FramingError("FD single frame without length"))
                return []
            L, start = data[1], 2
        if L == 0 or start + L > len(data):
            self._bad(arb, "framing_errors", FramingError(f"single frame length {L} in {len(data)} bytes"))
            return []
        if part is not None:
            del self._partials[arb]
            self._bad(arb, "aborted")
        return self._complete(arb, msg_id, src, data[start:start + L])

    def _iso_first(self, arb: int, data: bytes, part, t: float) -> list:
        """An ISO-TP first frame (PCI 1): starts a PDU (a repeated first frame is a duplicate)."""
        if len(data) < 3:
            self._bad(arb, "framing_errors", FramingError("first frame too short"))
            return []
        total = ((data[0] & 0x0F) << 8) | data[1]
        if total <= len(data) - 2 or total > MAX_PDU:
            self._bad(arb, "framing_errors", FramingError(f"first frame announces {total} bytes"))
            return []
        if part is not None:
            if part.next_sn == 1 and data == part.first:
                self.duplicates += 1           # the same first frame twice
                return []
            self._bad(arb, "aborted")
        self._partials[arb] = _Partial(total, data, t)
        return []

    def _iso_consecutive(self, arb: int, msg_id: int, src: int, data: bytes, part, t: float) -> list:
        """An ISO-TP consecutive frame (PCI 2): in sequence, a repeat, or out of order."""
        if part is None:
            self._bad(arb, "unexpected_cf", FramingError(f"CAN id {arb:#05x}: consecutive frame without first frame"))
            return []
        sn = data[0] & 0x0F
        if sn == part.last_sn and data == part.last_data:
            self.duplicates += 1
            return []
        if sn != part.next_sn or len(data) < 2:
            del self._partials[arb]
            self._bad(arb, "out_of_order", FramingError(f"CAN id {arb:#05x}: sequence nibble {sn}, expected {part.next_sn}"))
            return []
        if not part.add(sn, data, t):
            return []
        del self._partials[arb]
        return self._complete(arb, msg_id, src, bytes(part.buf))

    def _single(self, arb: int, msg_id: int, src: int, data: bytes) -> list:
        """A single-frame message (no PCI, seq or PDU CRC): its length is checked, nothing else."""
        d = BY_ID[msg_id]
        n = direct_size(msg_id)
        if len(data) < n or len(data) > (fd_length(n) if n > 8 else n):
            self._bad(arb, "length_errors", LengthError(f"{d.name}: single frame of {len(data)} bytes, "
                                                        f"schema says {n}"))
            return []
        if msg_id in BUS_FORM_IDS:
            msg = busform.decode(msg_id, src, data, self.context)
            if msg is None:
                self._bad(arb, "unresolved", FramingError(
                    f"{d.name}: bus form not restorable (no TIME_SYNC heard, or the status's command not heard)"))
                return []
            self.context.note(msg)
        else:
            payload = (bytes([src]) if d.sender_field else b"") + data[:n]
            msg = CLASS_BY_ID[msg_id]._make(STRUCTS[msg_id].unpack(payload))
        seq = (self._last_seq.get(src, -1) + 1) & 0xFF      # the sender's previous seq + 1
        self._last_seq[src] = seq
        self._synth_seq[src] = True         # numbered here: the next PDU's seq is not judged against it
        hdr = self.header
        hdr.seq, hdr.src, hdr.flags, hdr.msg_id, hdr.signature, hdr.signed_part = seq, src, 0, msg_id, b"", b""
        if self.verifier is not None and not self.verifier(hdr, msg):
            self._bad(arb, "rejected", getattr(self.verifier, "last_error", None))
            return []
        self.single_frames += 1
        self.messages_ok += 1
        if self.on_frame is not None:
            self.on_frame(hdr, msg)
        return [(_copy_header(hdr), msg)]

    def _complete(self, arb: int, msg_id: int, src: int, pdu: bytes) -> list:
        if self._last_pdu.get(arb) == pdu:
            self.duplicates += 1
            return []
        hdr = self.header
        try:
            msg = decode_pdu(msg_id, src, pdu, hdr)
        except CrcError as exc:
            self._bad(arb, "crc_errors", exc)
            return []
        except LengthError as exc:
            self._bad(arb, "length_errors", exc)
            return []
        except ProtocolError as exc:
            self._bad(arb, "framing_errors", exc)
            return []
        if self.verifier is not None and not self.verifier(hdr, msg):
            self._bad(arb, "rejected", getattr(self.verifier, "last_error", None))
            return []
        self._last_pdu[arb] = pdu
        if msg_id in BUS_FORM_IDS:
            self.context.note(msg)
        last = self._last_seq.get(src)
        if last is not None and hdr.seq != ((last + 1) & 0xFF) and not self._synth_seq.get(src, False):
            self.seq_gaps += 1
        self._last_seq[src] = hdr.seq
        self._synth_seq[src] = False
        self.messages_ok += 1
        if self.on_frame is not None:
            self.on_frame(hdr, msg)
        return [(_copy_header(hdr), msg)]


# --- the Port adapter -----------------------------------------------------
class CanLink:
    """Byte-stream Port over a python-can bus (see the module docstring).

    It implements the firmware's link contract ``coiltrack.firmware.port.Port``
    (``read``, ``write``, ``close``) structurally: ``protocol`` never imports the firmware.

    ``node_id`` is this station's node id: it is used as the CAN sender for
    frames written with ``src`` 0, and frames arriving from any id this link
    has sent as (``node_id`` and every ``src`` written) are ignored, so an
    adapter that echoes our own frames does not loop them back.
    """

    def __init__(self, bus, node_id: int, *, fd: bool = False, brs: bool = True,
                 send_timeout: float | None = 0.1, timeout_s: float = 0.5,
                 max_frames_per_read: int = 4096, verifier=None):
        if not 0 <= node_id <= MAX_CAN_NODE:
            raise ValueError(f"node id {node_id} does not fit the CAN node field (0..{MAX_CAN_NODE})")
        self.bus = bus
        self.node_id = node_id
        self.codec = CanCodec(fd=fd, brs=brs)
        self.reassembler = CanReassembler(timeout_s=timeout_s, verifier=verifier, context=self.codec.context)
        self.send_timeout = send_timeout
        self.max_frames_per_read = max_frames_per_read
        self.local_ids = {node_id}
        self._tx_decoder = FrameDecoder(on_frame=self._send_message)
        self._segmented = _RAW_SEGMENTED[bool(fd)]
        # a bus of protocol.interfaces.slcan: the frames it holds at a read's start, in one read of
        # its tty; its queued lines written at once by flush
        self._held_frames = getattr(bus, "held_frames", None)
        self._send_queued = getattr(bus, "send_queued", None)
        tty_fd = getattr(bus, "fd", None) if self._held_frames is not None else None
        #: the descriptor a loop can wait on for arriving frames (``emulator_loop``), or None
        self.fd = tty_fd if isinstance(tty_fd, int) else None
        self.frames_tx = 0
        self.messages_tx = 0
        self.frames_rx = 0
        self.tx_errors = 0
        self.rx_errors = 0
        self.echoes = 0
        self.bytes_tx = 0

    # Port interface -------------------------------------------------------
    def write(self, data: bytes) -> None:
        self.bytes_tx += len(data)
        dec = self._tx_decoder
        raw = dec.take_raw(data) if type(data) is bytes else None
        if raw is None:
            dec.feed(data)
            return
        mid, src = raw[4], raw[3]
        seg = self._segmented.get(mid) if 0 < src <= MAX_CAN_NODE else None
        if seg is None or (seg.f32 and _f32_nan(seg.f32, raw)):
            self._send_message(dec.header, parse_frame_fast(raw, dec.header))
            return
        # an unsigned message sent as its PDU segmented (no bus form, no single frame): the PDU is
        # the serial frame's seq, payload and CRC (the CRC covers the same header: len, flags 0, seq,
        # src, msg_id), so the frames come straight from the bytes (_send_message's, to the bit)
        self.local_ids.add(raw[HEADER_LEN] if seg.sender else src)
        self._send_frames(self.codec._messages(BASE_ID[mid] | src, bytes(raw[2:3]) + bytes(raw[HEADER_LEN:])))

    def read(self) -> bytes:
        out = bytearray()
        # an slcan adapter: only the bytes (python-can's slcan) or the frames (protocol.interfaces.slcan)
        # it held when the read began (see _adapter_held)
        frames = self._held_frames() if self._held_frames is not None else None
        left = self._adapter_held() if frames is None else None
        feed = self.reassembler.feed_serial
        recv = self.bus.recv
        local = self.local_ids
        for _ in range(self.max_frames_per_read if frames is None else min(frames, self.max_frames_per_read)):
            if left is not None and left <= 0:
                break
            try:
                frame = recv(timeout=0)
            except (can.CanError, OSError, ValueError):
                self.rx_errors += 1
                break
            if frame is None:
                if left is not None and getattr(self.bus, "_buffer", None):
                    break               # the rest of a line still to arrive: the next read's
                if self._adapter_pending():
                    if left is not None:
                        left -= 1       # a line that is no frame (an adapter's reply): 1 byte at least
                    continue
                break
            if left is not None:
                left -= slcan_line_length(frame.is_extended_id, frame.is_remote_frame, len(frame.data))
            self.frames_rx += 1
            arb = frame.arbitration_id
            if frame.is_extended_id:
                arb = std_of_ext(arb)
            if arb is not None and not frame.is_error_frame and (arb & NODE_MASK) in local \
                    and (arb & FUNCTION_MASK) in _MSG_BY_BASE:
                self.echoes += 1
                continue
            feed(frame, out)
        return bytes(out)

    def flush(self) -> None:
        """Write the frames a coalescing bus queued (``protocol.interfaces.slcan``: one system call
        for a tick's or a step's frames); nothing for another bus."""
        if self._send_queued is not None:
            try:
                self._send_queued()
            except (can.CanError, OSError):
                self.tx_errors += 1

    def close(self) -> None:
        try:
            self.bus.shutdown()
        except (can.CanError, OSError):
            pass

    # ---------------------------------------------------------------------
    def _adapter_held(self) -> int | None:
        """slcan: the bytes of frame lines the adapter holds now (the serial port's input and
        python-can's partial line), None for another bus. ``read`` returns the frames of those
        bytes only, as a CAN controller's receive FIFO read at the tick would: python-can reads
        an slcan adapter a byte at a time, each read of a pty may wait for the tty's flush work
        (one firmware read took 6.8 ms), and frames keep arriving meanwhile. The firmware judges
        every frame of a read against the tick's clock, taken before the read; a sample taken
        during that read would be from its future (docs/protocol.md, sample time stamps)."""
        port = getattr(self.bus, "serialPortOrig", None)
        if port is None:
            return None
        try:
            return port.in_waiting + len(getattr(self.bus, "_buffer", b""))
        except (OSError, ValueError):
            return None

    def _adapter_pending(self) -> bool:
        """slcan: python-can returns None for a non-frame line (an adapter's
        reply) even when frames follow; keep reading while bytes wait."""
        port = getattr(self.bus, "serialPortOrig", None)
        if port is None:
            return False
        try:
            return port.in_waiting > 0
        except (OSError, ValueError):
            return False

    @property
    def tx_bad(self) -> int:
        """Serial frames handed to ``write`` that did not decode (not sent)."""
        return self._tx_decoder.frames_bad

    def counters(self) -> dict:
        d = {"frames_tx": self.frames_tx, "messages_tx": self.messages_tx, "frames_rx": self.frames_rx,
             "tx_errors": self.tx_errors, "rx_errors": self.rx_errors, "tx_bad": self.tx_bad,
             "echoes": self.echoes, "tx_bus_form_fallbacks": self.codec.fallbacks}
        d.update({"rx_" + k: v for k, v in self.reassembler.counters().items()})
        return d

    def send_message(self, msg, seq: int = 0, src: int | None = None, signature: bytes = b"") -> int:
        """Send one message directly (no serial framing); returns frames sent."""
        src = self.node_id if src is None else src
        self.local_ids.add(msg.node if msg.DEF.sender_field and not signature else src)
        return self._send_frames(self.codec.encode(msg, seq, src, signature))

    def _send_message(self, hdr, msg) -> None:
        src = hdr.src
        if src == 0 and not hdr.flags & FLAG_SIGNED:
            src = self.node_id
        try:
            frames = self.codec.encode(msg, hdr.seq, src, hdr.signature)
        except ProtocolError:
            self.tx_errors += 1
            return
        self.local_ids.add(msg.node if msg.DEF.sender_field else src)
        self._send_frames(frames)

    def _send_frames(self, frames) -> int:
        for f in frames:
            try:
                self.bus.send(f, timeout=self.send_timeout)
            except (can.CanError, OSError, ValueError):
                self.tx_errors += 1
                return 0
            self.frames_tx += 1
        self.messages_tx += 1
        return len(frames)


# --- buses ----------------------------------------------------------------
_channel_counter = itertools.count(1)


def unique_channel(prefix: str = "coiltrack") -> str:
    """A virtual channel name not used before in this process."""
    return f"{prefix}-{time.monotonic_ns()}-{next(_channel_counter)}"


def open_bus(interface: str, channel: str, bitrate: int = 500_000, fd: bool = False,
             data_bitrate: int = 2_000_000, **kwargs):
    """Open a python-can bus the way the coiltrack tools do.

    - ``virtual``: in-process bus (``channel`` is any name; buses with the
      same name in one process hear each other, not themselves);
    - ``slcan-tty``: slcan on a tty (a pseudo-terminal of :class:`protocol.slcan.SlcanBridge`)
      through :mod:`protocol.interfaces.slcan`: every frame held read in one system call, the
      frames sent queued until :meth:`CanLink.flush` (``coalesce``, the default here);
    - ``slcan``: a serial slcan adapter, or a pseudo-terminal of
      :class:`protocol.slcan.SlcanBridge`; opened without python-can's
      2 s settling sleep and with a non-blocking serial read (``timeout=0``),
      so ``recv(timeout=0)`` never stalls a firmware tick;
    - anything else (``socketcan`` on a board, ...) is passed to ``can.Bus``.

    Network interfaces (``udp_multicast``) are refused: this project never
    puts a bus on a network address.
    """
    if interface in ("udp_multicast",):
        raise ValueError(f"interface '{interface}' uses the network; use virtual or slcan")
    if interface == "virtual":
        kwargs.setdefault("receive_own_messages", False)
        return can.Bus(interface="virtual", channel=channel, **kwargs)
    if interface == "slcan-tty":
        if fd:
            raise ValueError("interface 'slcan-tty' carries classic CAN frames only here; use slcan for CAN FD")
        from .interfaces.slcan import SlcanTtyBus

        kwargs.setdefault("coalesce", True)
        return SlcanTtyBus(channel, bitrate, **kwargs)
    if interface == "slcan":
        kwargs.setdefault("sleep_after_open", 0)
        kwargs.setdefault("timeout", 0)
        bus = can.Bus(interface="slcan", channel=channel, bitrate=bitrate, **kwargs)
        if fd:
            bus.set_bitrate(bitrate, data_bitrate)
        return bus
    if fd:
        kwargs.setdefault("fd", True)
        kwargs.setdefault("data_bitrate", data_bitrate)
    return can.Bus(interface=interface, channel=channel, bitrate=bitrate, **kwargs)


def virtual_bus_pair(channel: str | None = None):
    """Two ends of one in-process virtual bus (a fresh channel by default)."""
    channel = channel or unique_channel()
    return (open_bus("virtual", channel), open_bus("virtual", channel))


def virtual_link_pair(node_a: int, node_b: int, channel: str | None = None, **kwargs):
    """Two :class:`CanLink` on one virtual bus (e.g. firmware and emulator)."""
    a, b = virtual_bus_pair(channel)
    return CanLink(a, node_a, **kwargs), CanLink(b, node_b, **kwargs)



def inproc_link_pair(node_a: int, node_b: int, **kwargs):
    """Two :class:`CanLink` on one in-process bus (:mod:`protocol.interfaces.inproc`: python-can's
    ``BusABC`` and ``Message``, without ``virtual``'s deep copy and locked queue a frame)."""
    from .interfaces.inproc import inproc_bus_pair

    a, b = inproc_bus_pair()
    return CanLink(a, node_a, **kwargs), CanLink(b, node_b, **kwargs)
