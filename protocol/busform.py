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
                     BUS_START_BEHIND_US, BUS_START_BITS, BUS_START_LSB_US, PULSE_ID_MASK, restore_low_bits)

_HB, _TS, _CMD, _ST, _RP = (MSG[n] for n in ("HEARTBEAT", "TIME_SYNC", "COIL_PULSE_CMD", "COIL_STATUS",
                                             "TIME_SYNC_REPLY"))
#: message id -> bus form
BUS_FORM_IDS: dict[int, object] = {MSG[b.name].ID: b for b in BUS_FORMS}
BUS_FORM_SIZE = 8
_START_MASK = (1 << BUS_START_BITS) - 1
#: commands remembered for the statuses (pulse ids within this many of the latest are known)
COMMANDS_KEPT = 64
#: TIME_SYNC broadcasts remembered for the replies (by sync_seq mod 64)
SYNCS_KEPT = 1 << BUS_REPLY_SEQ_BITS
_SEQ_MASK = SYNCS_KEPT - 1


class _Layout:
    """A bus form's bit layout compiled once from its ``BUS_FORMS`` row: :meth:`pack` puts the raw
    field values (in the row's order; signed fields as Python ints of either sign) into the
    64-bit word, or gives None when one does not fit its field; :meth:`unpack` takes them out,
    sign-extended. The one place the layouts' shifts and masks are computed."""

    __slots__ = ("fields",)

    def __init__(self, form):
        #: (first bit, mask, signed, bits) per field, in the table's order
        self.fields = tuple((f.first_bit, (1 << f.bits) - 1, f.signed, f.bits) for f in form.fields)
        assert max(f.first_bit + f.bits for f in form.fields) <= 64

    def pack(self, *raw: int) -> int | None:
        v = 0
        for x, (shift, mask, signed, bits) in zip(raw, self.fields):
            if signed:
                h = 1 << (bits - 1)
                if not -h <= x < h:
                    return None
            elif not 0 <= x <= mask:
                return None
            v |= (x & mask) << shift
        return v

    def unpack(self, v: int) -> tuple[int, ...]:
        out = []
        for shift, mask, signed, bits in self.fields:
            x = (v >> shift) & mask
            if signed and x >> (bits - 1):
                x -= 1 << bits
            out.append(x)
        return tuple(out)


_L_HB, _L_TS, _L_CMD, _L_ST, _L_RP = (_Layout(BUS_FORM_BY_NAME[n]) for n in (
    "HEARTBEAT", "TIME_SYNC", "COIL_PULSE_CMD", "COIL_STATUS", "TIME_SYNC_REPLY"))


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


def encode(msg, ctx: BusContext | None) -> bytes | None:
    """The 8 data bytes of ``msg``'s bus form, or None when the form cannot carry it exactly."""
    mid = msg.ID
    v = None
    if mid == _TS.ID:
        v = _L_TS.pack(msg.master_time_us, msg.sync_seq)
    elif mid == _HB.ID:
        v = _L_HB.pack(msg.role, msg.state, msg.proto_version, msg.errors, msg.schema_hash)
    elif mid == _CMD.ID:
        ref = None if ctx is None else ctx.ref_us
        s, d = msg.start_us, msg.duration_us
        if (ref is not None and s % BUS_START_LSB_US == 0 and d % BUS_DURATION_LSB_US == 0
                and restore_start((s // BUS_START_LSB_US) & _START_MASK, ref) == s):
            v = _L_CMD.pack(msg.coil, msg.pulse_id, msg.current_ma, (s // BUS_START_LSB_US) & _START_MASK,
                            d // BUS_DURATION_LSB_US)
    elif mid == _ST.ID:
        cmd = None if ctx is None else ctx.commands.get(msg.pulse_id & PULSE_ID_MASK)
        if cmd is not None and cmd[0] == msg.coil:
            ds = msg.start_us - cmd[1]
            de = msg.end_us - (cmd[1] + cmd[2])
            if -BUS_EDGE_MAX_US <= ds <= BUS_EDGE_MAX_US and -BUS_EDGE_MAX_US <= de <= BUS_EDGE_MAX_US:
                v = _L_ST.pack(msg.coil, msg.pulse_id, msg.current_ma, msg.faults, ds, de)
    elif mid == _RP.ID:
        base = None if ctx is None else sync_base(msg.sync_seq & _SEQ_MASK, ctx)
        if base is not None and base[0] == msg.sync_seq:
            late = msg.node_time_us - (base[1] + msg.offset_us)
            v = _L_RP.pack(msg.sync_seq & _SEQ_MASK, late, msg.offset_us, msg.drift_ppb)
    return None if v is None else v.to_bytes(8, "little")


def restore_seq(bits: int, latest: int) -> int:
    """TIME_SYNC_REPLY's ``sync_seq`` from its 6 bits: the one sequence number (16 bits, wrapping)
    with those bits in ``[latest - 63, latest]``, ``latest`` the sync_seq of the latest TIME_SYNC heard."""
    return restore_low_bits(bits, latest - _SEQ_MASK, BUS_REPLY_SEQ_BITS) & 0xFFFF


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
    return restore_low_bits(bits, lo, BUS_START_BITS) * BUS_START_LSB_US


def decode(msg_id: int, src: int, data, ctx: BusContext | None):
    """The schema message of a bus form's 8 data bytes from sender ``src``, or None when ``ctx``
    lacks what it is relative to (no TIME_SYNC heard, the status's command not heard, a reply's
    TIME_SYNC not heard)."""
    v = int.from_bytes(data, "little")
    if msg_id == _TS.ID:
        return _TS(*_L_TS.unpack(v))
    if msg_id == _HB.ID:
        role, state, version, errors, schema_hash = _L_HB.unpack(v)
        return _HB(src, role, state, version, schema_hash, errors)
    if msg_id == _RP.ID:
        seq_lo, late, off, drift = _L_RP.unpack(v)
        base = None if ctx is None else sync_base(seq_lo, ctx)
        if base is None:
            return None
        t = base[1] + off + late
        if not 0 <= t < 1 << 64:
            return None
        return _RP(src, base[0], t, off, drift)
    if msg_id == _CMD.ID:
        if ctx is None or ctx.ref_us is None:
            return None
        coil, pid, cur, start_8us, dur_16us = _L_CMD.unpack(v)
        return _CMD(coil, pid, cur, restore_start(start_8us, ctx.ref_us), dur_16us * BUS_DURATION_LSB_US)
    if msg_id == _ST.ID:
        coil, pid, cur, faults, ds, de = _L_ST.unpack(v)
        cmd = None if ctx is None else ctx.commands.get(pid)
        if cmd is None or cmd[0] != coil:
            return None
        return _ST(coil, pid, cur, cmd[1] + ds, cmd[1] + cmd[2] + de, faults)
    raise KeyError(msg_id)


def bus_form(name: str):
    return BUS_FORM_BY_NAME[name]
