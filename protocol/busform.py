"""Bus forms (protocol v3, v4): HEARTBEAT, TIME_SYNC, COIL_PULSE_CMD, COIL_STATUS and
(v4) TIME_SYNC_REPLY in one classic 8-byte frame each, mapped to and from the schema messages.

The layouts are the schema's ``BUS_FORMS`` table (bit fields of the 8 data
bytes read as one little-endian 64-bit integer, DBC ``@1``). Two of them carry
times relative to what every listener on the bus has heard (a
:class:`BusContext`):

- ``COIL_PULSE_CMD.start_us`` as ``start_us / 8 mod 2**18`` (wraps every
  2.097152 s); a receiver restores the one time in
  ``[ref - 524288 us, ref + 1572864 us)``, ``ref`` the master time of the
  latest TIME_SYNC on the bus (sent or heard). At 4 TIME_SYNC a second and a
  command lead of at most 0.3 s, the start lies within ``ref + 0.6 s``; a late
  command (start behind ``ref``) is still restored as late up to 0.52 s;
- ``COIL_STATUS.start_us`` / ``end_us`` as signed microsecond offsets (12 bits,
  +-2047 us) from the start and the end of the command with the same
  ``pulse_id`` (and coil) on the bus: a driver's edges lie within its clock's
  sync error (tens of us) of the commanded ones;
- ``TIME_SYNC_REPLY.sync_seq`` as its low 6 bits: the one sequence number at
  or below the latest TIME_SYNC heard with those bits (64 broadcasts back,
  6.4 s at the firmware's 10 Hz); ``node_time_us`` as its lateness, signed
  14-bit microseconds, against ``master_time_us`` of that TIME_SYNC (the
  station keeps the last 64 broadcasts) plus ``offset_us``: a node stamps
  its counter when the broadcast arrives and its offset is fitted to the
  lower envelope of those arrivals, so the lateness is the frame's delay
  above that envelope (the link's jitter) plus a correction still being
  slewed; ``offset_us`` in 26 bits (+-33.5 s) and ``drift_ppb`` in 18 bits
  (+-131 ppm) as they are. A reply to a broadcast the station did not hear
  cannot be restored.

A message is sent in its bus form only when the form carries it exactly
(:func:`encode`: every field in range, ``start_us`` a multiple of 8 in the
window, ``duration_us`` a multiple of 16 below 262.144 ms, ``pulse_id`` below
4096, the status's command known and its edges within 2047 us); otherwise the
sender falls back to the full schema payload, ISO-TP segmented on the 29-bit
identifier (``protocol.can``), so no value is ever rounded on the bus. A
receiver that cannot restore a bus form (no TIME_SYNC heard yet, the
command of a status not heard) counts it and drops it (:func:`decode`
returns None).

Sizes: ``(msg, data)`` are the schema message (a namedtuple of
``protocol.codec.MSG``) and the 8 data bytes; times in microseconds.
"""
from __future__ import annotations

from .codec import MSG
from .schema import (BUS_DURATION_BITS, BUS_DURATION_LSB_US, BUS_EDGE_MAX_US, BUS_FORM_BY_NAME, BUS_FORMS,
                     BUS_REPLY_DRIFT_BITS, BUS_REPLY_LATE_BITS, BUS_REPLY_OFFSET_BITS, BUS_REPLY_SEQ_BITS,
                     BUS_START_BEHIND_US, BUS_START_BITS, BUS_START_LSB_US, PULSE_ID_MASK)

_HB, _TS, _CMD, _ST, _RP = (MSG[n] for n in ("HEARTBEAT", "TIME_SYNC", "COIL_PULSE_CMD", "COIL_STATUS",
                                             "TIME_SYNC_REPLY"))
#: message id -> bus form
BUS_FORM_IDS: dict[int, object] = {MSG[b.name].ID: b for b in BUS_FORMS}
BUS_FORM_SIZE = 8
_START_MASK = (1 << BUS_START_BITS) - 1
_DUR_MAX = (1 << BUS_DURATION_BITS) - 1
_M48 = (1 << 48) - 1
#: commands remembered for the statuses (pulse ids within this many of the latest are known)
COMMANDS_KEPT = 64
#: TIME_SYNC broadcasts remembered for the replies (by sync_seq mod 64)
SYNCS_KEPT = 1 << BUS_REPLY_SEQ_BITS
_SEQ_MASK = SYNCS_KEPT - 1
_LATE_SHIFT = BUS_REPLY_SEQ_BITS
_OFF_SHIFT = _LATE_SHIFT + BUS_REPLY_LATE_BITS
_DRIFT_SHIFT = _OFF_SHIFT + BUS_REPLY_OFFSET_BITS
assert _DRIFT_SHIFT + BUS_REPLY_DRIFT_BITS == 64


class BusContext:
    """What a station has heard on the bus: the master time of the latest TIME_SYNC (``ref_us``,
    None before the first) and the latest commands by 12-bit pulse id (``(coil, start_us,
    duration_us)``, at most :data:`COMMANDS_KEPT`). One per station, shared by its sending and
    receiving side; allocation-free once ``COMMANDS_KEPT`` commands are kept."""

    __slots__ = ("ref_us", "ref_seq", "sync_seq", "sync_us", "commands", "_order", "_next")

    def __init__(self):
        self.ref_us: int | None = None
        #: sync_seq of the latest TIME_SYNC (None before the first) and the last SYNCS_KEPT
        #: broadcasts by ``sync_seq mod 64``: their sequence numbers (-1: none) and master times
        self.ref_seq: int | None = None
        self.sync_seq = [-1] * SYNCS_KEPT
        self.sync_us = [0] * SYNCS_KEPT
        self.commands: dict[int, tuple[int, int, int]] = {}
        self._order = [-1] * COMMANDS_KEPT
        self._next = 0

    def note(self, msg) -> None:
        """Remember a TIME_SYNC or a COIL_PULSE_CMD (any form, sent or heard)."""
        mid = msg.ID
        if mid == _TS.ID:
            self.ref_us = msg.master_time_us
            seq = msg.sync_seq & 0xFFFF
            self.ref_seq = seq
            self.sync_seq[seq & _SEQ_MASK] = seq
            self.sync_us[seq & _SEQ_MASK] = msg.master_time_us
        elif mid == _CMD.ID:
            key = msg.pulse_id & PULSE_ID_MASK
            old = self._order[self._next]
            if old >= 0 and old != key:
                self.commands.pop(old, None)
            self._order[self._next] = key
            self._next = (self._next + 1) % COMMANDS_KEPT
            self.commands[key] = (msg.coil, msg.start_us, msg.duration_us)


def _signed(v: int, bits: int) -> int:
    return v - (1 << bits) if v >> (bits - 1) else v


def _fits(v: int, bits: int) -> bool:
    return 0 <= v < (1 << bits)


def _fits_signed(v: int, bits: int) -> bool:
    h = 1 << (bits - 1)
    return -h <= v < h


def encode(msg, ctx: BusContext | None) -> bytes | None:
    """The 8 data bytes of ``msg``'s bus form, or None when the form cannot carry it exactly."""
    mid = msg.ID
    if mid == _TS.ID:
        t, seq = msg.master_time_us, msg.sync_seq
        if not (0 <= t <= _M48 and _fits(seq, 16)):
            return None
        v = t | seq << 48
    elif mid == _HB.ID:
        if not (_fits(msg.role, 4) and _fits(msg.state, 4) and _fits(msg.proto_version, 8)
                and _fits(msg.errors, 16) and _fits(msg.schema_hash, 32)):
            return None
        v = msg.role | msg.state << 4 | msg.proto_version << 8 | msg.errors << 16 | msg.schema_hash << 32
    elif mid == _CMD.ID:
        ref = None if ctx is None else ctx.ref_us
        s, d = msg.start_us, msg.duration_us
        if (ref is None or not _fits(msg.coil, 4) or not _fits(msg.pulse_id, 12)
                or not _fits_signed(msg.current_ma, 16) or s % BUS_START_LSB_US or d % BUS_DURATION_LSB_US
                or not 0 <= d // BUS_DURATION_LSB_US <= _DUR_MAX or restore_start(s // BUS_START_LSB_US, ref) != s):
            return None
        v = (msg.coil | msg.pulse_id << 4 | (msg.current_ma & 0xFFFF) << 16
             | ((s // BUS_START_LSB_US) & _START_MASK) << 32 | (d // BUS_DURATION_LSB_US) << 50)
    elif mid == _ST.ID:
        cmd = None if ctx is None else ctx.commands.get(msg.pulse_id & PULSE_ID_MASK)
        if cmd is None or cmd[0] != msg.coil or not _fits(msg.pulse_id, 12):
            return None
        ds = msg.start_us - cmd[1]
        de = msg.end_us - (cmd[1] + cmd[2])
        if not (_fits(msg.coil, 4) and _fits_signed(msg.current_ma, 16) and _fits(msg.faults, 8)
                and -BUS_EDGE_MAX_US <= ds <= BUS_EDGE_MAX_US and -BUS_EDGE_MAX_US <= de <= BUS_EDGE_MAX_US):
            return None
        v = (msg.coil | msg.pulse_id << 4 | (msg.current_ma & 0xFFFF) << 16 | msg.faults << 32
             | (ds & 0xFFF) << 40 | (de & 0xFFF) << 52)
    elif mid == _RP.ID:
        base = None if ctx is None else sync_base(msg.sync_seq & _SEQ_MASK, ctx)
        if base is None or base[0] != msg.sync_seq:
            return None
        late = msg.node_time_us - (base[1] + msg.offset_us)
        if not (_fits_signed(late, BUS_REPLY_LATE_BITS) and _fits_signed(msg.offset_us, BUS_REPLY_OFFSET_BITS)
                and _fits_signed(msg.drift_ppb, BUS_REPLY_DRIFT_BITS)):
            return None
        v = (msg.sync_seq & _SEQ_MASK | (late & ((1 << BUS_REPLY_LATE_BITS) - 1)) << _LATE_SHIFT
             | (msg.offset_us & ((1 << BUS_REPLY_OFFSET_BITS) - 1)) << _OFF_SHIFT
             | (msg.drift_ppb & ((1 << BUS_REPLY_DRIFT_BITS) - 1)) << _DRIFT_SHIFT)
    else:
        return None
    return v.to_bytes(8, "little")


def restore_seq(bits: int, latest: int) -> int:
    """TIME_SYNC_REPLY's ``sync_seq`` from its 6 bits: the one sequence number (16 bits, wrapping)
    with those bits in ``[latest - 63, latest]``, ``latest`` the sync_seq of the latest TIME_SYNC heard."""
    return (latest - ((latest - bits) & _SEQ_MASK)) & 0xFFFF


def sync_base(bits: int, ctx: BusContext):
    """``(sync_seq, master_time_us)`` of the TIME_SYNC a reply's 6 sequence bits refer to, or None
    when the station has not heard it (none heard yet, or not among the last 64)."""
    if ctx.ref_seq is None:
        return None
    seq = restore_seq(bits, ctx.ref_seq)
    k = seq & _SEQ_MASK
    if ctx.sync_seq[k] != seq:
        return None
    return seq, ctx.sync_us[k]


def restore_start(bits: int, ref_us: int) -> int:
    """The master time (us) of COIL_PULSE_CMD's 18 start bits (``start_us / 8 mod 2**18``): the one
    time with those bits in ``[ref - BUS_START_BEHIND_US, ref - BUS_START_BEHIND_US + 2.097152 s)``."""
    lo = (ref_us - BUS_START_BEHIND_US) // BUS_START_LSB_US      # the window's first unit
    return (lo + ((bits - lo) & _START_MASK)) * BUS_START_LSB_US


def decode(msg_id: int, src: int, data, ctx: BusContext | None):
    """The schema message of a bus form's 8 data bytes from sender ``src``, or None when ``ctx``
    lacks what it is relative to (no TIME_SYNC heard, the status's command not heard, a reply's
    TIME_SYNC not heard)."""
    v = int.from_bytes(data, "little")
    if msg_id == _TS.ID:
        return _TS(v & _M48, v >> 48)
    if msg_id == _HB.ID:
        return _HB(src, v & 0xF, (v >> 4) & 0xF, (v >> 8) & 0xFF, v >> 32, (v >> 16) & 0xFFFF)
    if msg_id == _RP.ID:
        base = None if ctx is None else sync_base(v & _SEQ_MASK, ctx)
        if base is None:
            return None
        late = _signed((v >> _LATE_SHIFT) & ((1 << BUS_REPLY_LATE_BITS) - 1), BUS_REPLY_LATE_BITS)
        off = _signed((v >> _OFF_SHIFT) & ((1 << BUS_REPLY_OFFSET_BITS) - 1), BUS_REPLY_OFFSET_BITS)
        t = base[1] + off + late
        if not 0 <= t < 1 << 64:
            return None
        return _RP(src, base[0], t, off, _signed(v >> _DRIFT_SHIFT, BUS_REPLY_DRIFT_BITS))
    coil, pid, cur = v & 0xF, (v >> 4) & 0xFFF, _signed((v >> 16) & 0xFFFF, 16)
    if msg_id == _CMD.ID:
        if ctx is None or ctx.ref_us is None:
            return None
        return _CMD(coil, pid, cur, restore_start((v >> 32) & _START_MASK, ctx.ref_us),
                    (v >> 50) * BUS_DURATION_LSB_US)
    if msg_id == _ST.ID:
        cmd = None if ctx is None else ctx.commands.get(pid)
        if cmd is None or cmd[0] != coil:
            return None
        start, end = cmd[1], cmd[1] + cmd[2]
        return _ST(coil, pid, cur, start + _signed((v >> 40) & 0xFFF, 12), end + _signed(v >> 52, 12),
                   (v >> 32) & 0xFF)
    raise KeyError(msg_id)


def bus_form(name: str):
    return BUS_FORM_BY_NAME[name]
