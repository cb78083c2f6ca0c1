"""The receive stage's frame decode on the compiled core (``core/src/rxdecode.c``).

:class:`coiltrack.protocol.framing.FrameDecoder` is the reference and the specification: the
compiled decoder takes the same byte stream, decodes the same frames, counts every bad frame
in the same counter (COBS, length, unknown id, flags, CRC: ``parse_frame``'s order), skips it
and resynchronises at the next 0x00 the same way, and counts the same sequence gaps and
overflows. ``protocol`` never imports the firmware, so the compiled decode lives here, on the
firmware's receive side.

The messages of the sample rates are unpacked in C into one start-up table of int64 rows
(``rows``; ``ct_rxdecode.h`` names the columns): ``MAG_PACKED`` already restored as
:meth:`coiltrack.firmware.receive.Receiver._unpack_mag` restores it (the stamp's time at the
tick, the set/reset and saturation bits), ``MAG_SAMPLE``, and ``IMU_SAMPLE`` with its
clipped-axis check (``receive._clipped``). Every other message is rare (heartbeats, coil
status, time-sync replies, IMU_DELTA pairs) and is unpacked from its payload by
:mod:`coiltrack.protocol.codec`, the same value as the Python decoder's.

:func:`frame_decoder` chooses once, at composition: this decoder on the compiled core, the
protocol's on the Python core (the firmware has no verifier: its decoder takes signed frames
as the Python one does, signature unchecked).
"""
from __future__ import annotations

import numpy as np

from coiltrack.protocol import FrameDecoder
from coiltrack.protocol.codec import CLASS_BY_ID, MSG, STRUCTS
from coiltrack.protocol.framing import MAX_ENCODED
from coiltrack.protocol.schema import BY_ID, MAX_PAYLOAD

_MAG_PACKED = MSG["MAG_PACKED"]
_MAG_SAMPLE = MSG["MAG_SAMPLE"]
_IMU_SAMPLE = MSG["IMU_SAMPLE"]
#: the payload layouts the C unpacks (core/src/rxdecode.c ct_rx_row)
_LAYOUTS = {_MAG_PACKED.ID: "<BhhhH", _MAG_SAMPLE.ID: "<BQhhhB", _IMU_SAMPLE.ID: "<BQhhhhhh"}
#: FrameDecoder's counters, in the order of the C state (CT_RX_*)
COUNTERS = ("frames_ok", "crc_errors", "framing_errors", "length_errors", "unknown_ids", "overflows",
            "rejected", "seq_gaps", "bytes_in")
#: rows decoded per call; a longer read is decoded in several calls
ROWS = 64
#: the row columns and kinds (``ct_rxdecode.h``; checked against the extension at construction)
RXR_W, RXR_KIND, RXR_CLIP, RXR_STAMP = 11, 10, 9, 7
RXK_RAW, RXK_MAG_PACKED, RXK_MAG, RXK_IMU = 0, 1, 2, 3
#: the route's modes and its answer to new data of the frame limit or more (``ct_rxdecode.h`` CT_RX_*)
RX_NEW, RX_RESUME, RX_TAKEN, RX_OVER_LIMIT = 0, 1, 2, -2


def _counter(k: int, doc: str):
    return property(lambda self: int(self._stv[k]), doc=doc)


class CompiledFrameDecoder:
    """:class:`coiltrack.protocol.framing.FrameDecoder` on the compiled core (module docstring).

    :meth:`decode` is the receive stage's interface (rows in :attr:`rows`); :meth:`feed` gives
    the protocol decoder's list of messages, for tools and tests. Its counters are the
    protocol decoder's (:meth:`counters`, :attr:`frames_bad`)."""

    frames_ok = _counter(0, "frames decoded")
    crc_errors = _counter(1, "frames with a bad CRC")
    framing_errors = _counter(2, "frames with bad COBS, too short or with unknown flags")
    length_errors = _counter(3, "frames whose length does not match")
    unknown_ids = _counter(4, "frames of an unknown message id")
    overflows = _counter(5, "runs longer than any legal frame, dropped")
    rejected = _counter(6, "frames a verifier refused (none here: always 0)")
    seq_gaps = _counter(7, "sequence numbers that did not follow their source's last")
    bytes_in = _counter(8, "bytes fed")

    def __init__(self, ext, rows: int = ROWS):
        for mid, fmt in _LAYOUTS.items():
            if BY_ID[mid].fmt != fmt:
                raise AssertionError(f"{BY_ID[mid].name}: the compiled decode unpacks {fmt}, the schema says "
                                     f"{BY_ID[mid].fmt}")
        assert ext.STAMP_FLIP == 1 << 15 and (ext.RXR_W, ext.RXR_KIND, ext.RXR_CLIP, ext.RXR_STAMP) == (
            RXR_W, RXR_KIND, RXR_CLIP, RXR_STAMP) and (ext.RXK_RAW, ext.RXK_MAG_PACKED, ext.RXK_MAG, ext.RXK_IMU) == (
            RXK_RAW, RXK_MAG_PACKED, RXK_MAG, RXK_IMU) and (
            ext.RX_NEW, ext.RX_RESUME, ext.RX_TAKEN, ext.RX_OVER_LIMIT) == (RX_NEW, RX_RESUME, RX_TAKEN, RX_OVER_LIMIT)
        sizes = np.full(256, -1, dtype=np.int64)
        extras = np.zeros(256, dtype=np.int64)
        for mid, d in BY_ID.items():
            sizes[mid], extras[mid] = d.size, d.crc_extra
        self._st = np.zeros(ext.RX_NST, dtype=np.int64)
        self._stv = memoryview(self._st)
        self._seq = np.full(256, -1, dtype=np.int64)
        self._rows = np.zeros((rows, ext.RXR_W), dtype=np.int64)
        #: the rows of the last :meth:`decode` (flat, ``RXR_W`` per row): see ``ct_rxdecode.h``
        self.rows = memoryview(self._rows).cast("B").cast("q")
        self._pay = bytearray(rows * MAX_PAYLOAD)
        self.payloads = memoryview(self._pay)
        self._buf = bytearray(MAX_ENCODED)
        self._raw = bytearray(MAX_ENCODED)
        self._rx = ext.RxDecode(sizes, extras, self._st, self._seq, self._rows, self._pay, self._buf, self._raw,
                                MAX_ENCODED, MAX_PAYLOAD)
        self.decode = self._rx.decode
        #: the compiled core's extension this decoder runs on
        self.ext = ext
        self._pos = ext.RX_POS
        self.width = ext.RXR_W
        #: rows one :meth:`decode` writes at most (fewer: it took all its data, :attr:`pos` is its end)
        self.capacity = rows
        self.verifier = self.on_frame = None

    def route_kernel(self, sup, nodes, pushes, st, lsb: float, limit: int = 0):
        """The receive stage's decode and routing of its magnetometer rows on this decoder
        (``ext.RxRoute``, ``core/src/rxdecode.c`` ``ct_rx_step``, ``ct_rx_route``): ``sup`` the
        supervisor's ``SupMag`` (None: every row to the caller), ``nodes`` node -> index into
        ``pushes`` (int64, 256, -1 the caller's), ``pushes`` the channels' ``SamplePush``, ``st``
        its state (int64, ``RXS_N``: rows, next row, MAG_PACKED count), ``lsb`` MAG_LSB_T, ``limit``
        the frames a tick routes at most (0: all). ``step(data, mode, now_us)`` decodes ``data`` into
        :attr:`rows` and routes them up to the next row the caller routes (its index), -1 when all
        are; mode ``RX_NEW`` new data (``RX_OVER_LIMIT``: it holds ``limit`` frames or more, nothing
        done), ``RX_RESUME`` on after the row handed back, ``RX_TAKEN`` new data cut to the limit
        (see :meth:`coiltrack.firmware.receive.Receiver._step_rows`)."""
        return self.ext.RxRoute(self._rx, sup, nodes, pushes, st, lsb, limit)

    @property
    def pos(self) -> int:
        """Where the last :meth:`decode` stopped in its data (its length when all was taken)."""
        return self._stv[self._pos]

    @property
    def frames_bad(self) -> int:
        return (self.crc_errors + self.framing_errors + self.length_errors
                + self.unknown_ids + self.overflows + self.rejected)

    def counters(self) -> dict:
        return {k: getattr(self, k) for k in (
            "frames_ok", "frames_bad", "crc_errors", "framing_errors", "length_errors",
            "unknown_ids", "overflows", "rejected", "seq_gaps", "bytes_in")}

    def message(self, i: int):
        """Row ``i`` of the last :meth:`decode` as the protocol decoder's message (a new value)."""
        q, b = self.rows, i * self.width
        kind = q[b + RXR_KIND]
        if kind == RXK_MAG_PACKED:
            return _MAG_PACKED(q[b + 1], q[b + 3], q[b + 4], q[b + 5], q[b + RXR_STAMP])
        if kind == RXK_MAG:
            return _MAG_SAMPLE(*q[b + 1:b + 7])
        if kind == RXK_IMU:
            return _IMU_SAMPLE(*q[b + 1:b + 9])
        return self.raw_message(i)

    def raw_message(self, i: int):
        """The message of a raw row (``RXK_RAW``): its payload unpacked by protocol.codec."""
        q, b = self.rows, i * self.width
        mid = q[b]
        return CLASS_BY_ID[mid]._make(STRUCTS[mid].unpack_from(self.payloads, q[b + 1]))

    def feed(self, data, now_us: int = 0) -> list:
        """``FrameDecoder.feed``: the messages of ``data`` (MAG_PACKED keep their stamp; ``now_us``
        only restores the rows' times)."""
        out = []
        data = bytes(data)
        pos = 0
        while True:
            n = self.decode(data, pos, now_us)
            out += [self.message(i) for i in range(n)]
            pos = self.pos
            if pos >= len(data):
                return out


def frame_decoder(core):
    """The receive stage's frame decoder on ``core`` (``coiltrack.firmware.core.Core``): compiled
    where its extension is, else the protocol's :class:`FrameDecoder`."""
    return FrameDecoder() if core.ext is None else CompiledFrameDecoder(core.ext)
