"""Message signing (MAVLink 2 style) for commands that move coil current or
change configuration (``signable=True`` in the schema).

A signed frame is an ordinary frame with header flag bit0 set and 13 bytes
appended after the CRC (see :mod:`protocol.framing`)::

    +0  u8   link_id     the sender's signing link (one per sender stream)
    +1  u48  timestamp   little endian, units of 10 us since 2015-01-01 UTC
    +7  6    mac         HMAC-SHA256(key, signed_part || link_id || timestamp)[:6]

``signed_part`` is the unencoded frame up to and including the CRC (header
with the signed flag set, payload, CRC), exactly as
:class:`protocol.framing.DecodedFrame` exposes it. Link id and timestamp are
inside the MAC, so neither can be altered. A receiver accepts a signed
frame only if the MAC matches and the timestamp is strictly newer than the
last one it accepted for the same (link id, sender); anything else is a
forgery or a replay. Over CAN the signature travels in the reassembled PDU
(:mod:`protocol.can`), so the same bytes are verified on both links.

The key is a shared secret (32 bytes recommended). :func:`key_from_text`
accepts a hex string or derives a key from a passphrase with SHA-256.
"""
from __future__ import annotations

import hashlib
import hmac
import time

from .errors import SignatureError
from .framing import FLAG_SIGNED, SIG_LEN, build_frame, cobs_encode

#: 2015-01-01T00:00:00Z as a Unix time (MAVLink's signing epoch)
SIGNING_EPOCH_UNIX = 1420070400
TIMESTAMP_MAX = (1 << 48) - 1
MAC_LEN = 6


def key_from_text(text: str) -> bytes:
    """A key from the command line: 32+ hex digits are taken as the key
    bytes; anything else is a passphrase hashed with SHA-256."""
    t = text.strip()
    if len(t) >= 32 and len(t) % 2 == 0:
        try:
            return bytes.fromhex(t)
        except ValueError:
            pass
    return hashlib.sha256(text.encode()).digest()


def now_timestamp() -> int:
    """Current time in signing units (10 us since 2015-01-01 UTC)."""
    return int((time.time() - SIGNING_EPOCH_UNIX) * 100_000) & TIMESTAMP_MAX


def compute_mac(key: bytes, signed_part: bytes, link_id: int, timestamp: int) -> bytes:
    tail = bytes([link_id & 0xFF]) + (timestamp & TIMESTAMP_MAX).to_bytes(6, "little")
    return hmac.new(key, bytes(signed_part) + tail, hashlib.sha256).digest()[:MAC_LEN]


def make_signature(key: bytes, signed_part: bytes, link_id: int, timestamp: int) -> bytes:
    """The 13 signature bytes for ``signed_part`` (header+payload+CRC)."""
    tail = bytes([link_id & 0xFF]) + (timestamp & TIMESTAMP_MAX).to_bytes(6, "little")
    return tail + compute_mac(key, signed_part, link_id, timestamp)


def parse_signature(sig: bytes) -> tuple[int, int, bytes]:
    """``(link_id, timestamp, mac)``; raises SignatureError if malformed."""
    if len(sig) != SIG_LEN:
        raise SignatureError(f"signature of {len(sig)} bytes, expected {SIG_LEN}")
    return sig[0], int.from_bytes(sig[1:7], "little"), bytes(sig[7:])


class Signer:
    """Produces signed frames for one signing link.

    ``timestamp`` defaults to the wall clock in 10 us units and is forced to
    increase strictly from one signed frame to the next, as receivers require.
    """

    def __init__(self, key: bytes, link_id: int = 0):
        if not key:
            raise ValueError("signing key must not be empty")
        if not 0 <= link_id <= 255:
            raise ValueError("link_id must be 0..255")
        self.key = bytes(key)
        self.link_id = link_id
        self.last_timestamp = -1
        self.signed = 0

    def next_timestamp(self, timestamp: int | None = None) -> int:
        if timestamp is None:
            timestamp = max(now_timestamp(), self.last_timestamp + 1)
        timestamp &= TIMESTAMP_MAX
        self.last_timestamp = max(self.last_timestamp, timestamp)
        return timestamp

    def signed_frame(self, msg, seq: int = 0, src: int = 0, timestamp: int | None = None) -> bytes:
        """Unencoded signed frame: header (flags bit0), payload, CRC, signature."""
        ts = self.next_timestamp(timestamp)
        raw = build_frame(msg, seq, src, flags=FLAG_SIGNED)
        self.signed += 1
        return raw + make_signature(self.key, raw, self.link_id, ts)

    def encode_signed(self, msg, seq: int = 0, src: int = 0, timestamp: int | None = None) -> bytes:
        """One signed message as it goes on a serial link: COBS(frame) + 0x00."""
        return cobs_encode(self.signed_frame(msg, seq, src, timestamp)) + b"\x00"


class SignedFrameEncoder:
    """Like :class:`protocol.framing.FrameEncoder` (keeps seq and src), but
    signs signable messages (every message with ``sign_all``)."""

    def __init__(self, src: int, signer: Signer, sign_all: bool = False):
        self.src = src
        self.signer = signer
        self.sign_all = sign_all
        self.seq = 0
        self.frames = 0

    def encode(self, msg, timestamp: int | None = None) -> bytes:
        from .framing import encode_frame

        if self.sign_all or msg.DEF.signable:
            out = self.signer.encode_signed(msg, self.seq, self.src, timestamp)
        else:
            out = encode_frame(msg, self.seq, self.src)
        self.seq = (self.seq + 1) & 0xFF
        self.frames += 1
        return out


class SignatureVerifier:
    """Verifier for ``FrameDecoder(verifier=...)`` and ``CanReassembler``.

    Called as ``verifier(header, msg) -> bool`` with the decoded header
    (``.flags``, ``.src``, ``.signature``, ``.signed_part``). Rejects, and
    counts by kind:

    - ``unsigned``: a signable command without signature (when ``require``);
    - ``forged``: a signature whose MAC does not match (wrong key, altered
      frame, altered link id or timestamp);
    - ``replayed``: a valid signature whose timestamp is not newer than the
      last accepted one for that link id (and sender).

    Unsigned messages that are not signable always pass; signed ones of any
    kind are verified. :meth:`verify` raises :class:`SignatureError` instead
    of returning False.
    """

    def __init__(self, key: bytes, require: bool = True):
        self.key = bytes(key)
        self.require = require
        self.accepted = 0
        self.unsigned = 0
        self.forged = 0
        self.replayed = 0
        self.passed_unsigned = 0
        self.last_error: SignatureError | None = None
        self._last_ts: dict[tuple[int, int], int] = {}

    def counters(self) -> dict:
        return {"accepted": self.accepted, "unsigned": self.unsigned, "forged": self.forged,
                "replayed": self.replayed, "passed_unsigned": self.passed_unsigned}

    @property
    def rejected(self) -> int:
        return self.unsigned + self.forged + self.replayed

    def verify(self, header, msg) -> None:
        if not header.flags & FLAG_SIGNED:
            if self.require and msg.DEF.signable:
                self.unsigned += 1
                raise SignatureError(f"{msg.NAME} from node {header.src} is not signed")
            self.passed_unsigned += 1
            return
        try:
            link_id, ts, mac = parse_signature(header.signature)
        except SignatureError:
            self.forged += 1
            raise
        expect = compute_mac(self.key, header.signed_part, link_id, ts)
        if not hmac.compare_digest(expect, mac):
            self.forged += 1
            raise SignatureError(f"{msg.NAME} from node {header.src}: bad signature (link {link_id})")
        k = (link_id, header.src)
        last = self._last_ts.get(k)
        if last is not None and ts <= last:
            self.replayed += 1
            raise SignatureError(f"{msg.NAME} from node {header.src}: replayed timestamp {ts} "
                                 f"(last accepted {last} on link {link_id})")
        self._last_ts[k] = ts
        self.accepted += 1

    def __call__(self, header, msg) -> bool:
        try:
            self.verify(header, msg)
        except SignatureError as exc:
            self.last_error = exc
            return False
        return True
