"""The periodic frames on the compiled core (``core/src/periodic.c``): TIME_SYNC, HEARTBEAT and
FAULT_EVENT byte for byte as ``protocol.framing.encode_frame`` builds them (the independent
reference: struct packing, crcmod's CRC-16, COBS in Python), refused where ``struct.pack`` refuses
them, and the transmitter's frames (sequence numbers, tx errors, a full link) the same on both cores.
Skipped where the extension is not built."""
from __future__ import annotations

import random

import pytest

from coiltrack.firmware import core
from coiltrack.firmware.supervise.timesync import TimeSyncMaster
from coiltrack.protocol import MSG, FrameDecoder
from coiltrack.protocol.framing import cobs_decode, encode_frame, parse_frame
from coiltrack.protocol.schema import PROTOCOL_VERSION, ROLE_FIRMWARE, SCHEMA_HASH, STATE_RUNNING

pytestmark = pytest.mark.skipif(not core.available(), reason="compiled core not built")

SYNC, HB, FAULT = MSG["TIME_SYNC"], MSG["HEARTBEAT"], MSG["FAULT_EVENT"]
U64 = (1 << 64) - 1


def _ext():
    return core.load("compiled").ext


def test_frames_equal_encode_frame_on_random_and_edge_values():
    """Each frame equals ``encode_frame``'s bytes, the fields at 0, their maxima and at random, and
    decodes back to its message. Catches a byte order, a field's width or offset, the CRC extra or
    a COBS code (payloads full of zeros and of 0xFF) wrong."""
    ext = _ext()
    rng = random.Random(11)
    for _ in range(3000):
        seq, src = rng.randrange(256), rng.randrange(256)
        t = rng.choice((0, U64, rng.randrange(1 << 40), rng.randrange(1 << 64)))
        s = rng.choice((0, 0xFFFF, rng.randrange(1 << 16)))
        got = ext.sync_frame(seq, src, t, s)
        assert got == encode_frame(SYNC(t, s), seq, src)
        assert parse_frame(cobs_decode(got[:-1])) == SYNC(t, s)
        f = [rng.choice((0, 255, rng.randrange(256))) for _ in range(4)]
        h = rng.choice((0, 0xFFFFFFFF, SCHEMA_HASH, rng.randrange(1 << 32)))
        e = rng.choice((0, 0xFFFF, rng.randrange(1 << 16)))
        got = ext.heartbeat_frame(seq, src, *f, h, e)
        assert got == encode_frame(HB(*f, h, e), seq, src)
        node, code = rng.choice((0, 255, rng.randrange(256))), rng.choice((0, 0xFFFF, rng.randrange(1 << 16)))
        detail = rng.choice((0, 0xFFFFFFFF, rng.randrange(1 << 32)))
        got = ext.event_frame(seq, src, node, t, code, detail)
        assert got == encode_frame(FAULT(node, t, code, detail), seq, src)
        assert parse_frame(cobs_decode(got[:-1])) == FAULT(node, t, code, detail)


def test_values_out_of_range_are_refused_as_struct_pack_refuses_them():
    """A field beyond its width, a negative one or not an integer: None (the transmitter counts a
    tx error), where ``encode_frame`` raises."""
    ext = _ext()
    bad_sync = ((-1, 0), (1 << 64, 0), (0, -1), (0, 1 << 16), (0.5, 0))
    for t, s in bad_sync:
        with pytest.raises(Exception):
            encode_frame(SYNC(t, s), 0, 1)
        assert ext.sync_frame(0, 1, t, s) is None
    good = [1, 2, 3, 4, 5, 6]
    for i, v in ((0, 256), (1, -1), (2, 300), (3, 256), (4, 1 << 32), (5, 1 << 16), (5, -1)):
        f = list(good)
        f[i] = v
        with pytest.raises(Exception):
            encode_frame(HB(*f), 0, 1)
        assert ext.heartbeat_frame(0, 1, *f) is None
    for args in ((256, 0, 0, 0), (0, -1, 0, 0), (0, 0, 1 << 16, 0), (0, 0, 0, 1 << 32), (0, 0, 0, -1)):
        with pytest.raises(Exception):
            encode_frame(FAULT(*args), 0, 1)
        assert ext.event_frame(0, 1, *args) is None
    with pytest.raises(TypeError):
        ext.sync_frame("a", 1, 0, 0)
    with pytest.raises(TypeError):
        ext.sync_frame(0, 1, 0)


def test_transmitter_sends_the_same_bytes_on_both_cores(transmitter_pair):
    """Time syncs, heartbeats and events mixed with other frames, a link that fails every 7th
    write and a refused event detail: the same bytes, sequence numbers and tx errors on both cores.
    Catches a frame numbered apart from the others (the shared sequence) or a sequence moved by a
    refused frame."""
    for fail_every in (0, 7):
        ref, got = transmitter_pair(fail_every)
        rng = random.Random(5)
        for k in range(400):
            now = 1000 * k
            for tx in (ref, got):
                tx.begin_tick(now)
            u = rng.random()
            for tx in (ref, got):
                if u < 0.3:
                    tx.time_sync(now + 13, k & 0xFFFF)
                elif u < 0.5:
                    tx.event(3, k * 7919)
                elif u < 0.6:
                    tx.mag_flip(3, now, k & 1)
                tx.step(now)
        for tx in (ref, got):
            tx.time_sync(-5, 0)                  # refused ('Q'): a tx error
            tx.time_sync(7, 1)
        assert ref.port.frames == got.port.frames
        assert ref.tx_errors == got.tx_errors >= 1
        assert len(ref.port.frames) > 200


class _Bad:
    """A receiver's frame decoder as the heartbeat reads it (its bad frames counted)."""
    frames_bad = 0


class _Port:
    def __init__(self):
        self.frames = []

    def write(self, data):
        self.frames.append(bytes(data))


def test_heartbeat_carries_the_decoders_bad_frames_saturated():
    """The heartbeat's error count is the receiver's bad frames, saturating at 0xFFFF, on both cores,
    one a ``heartbeat_us``."""
    from coiltrack.firmware.transmit import Transmitter

    dec = _Bad()
    txs = [Transmitter(_Port(), 7, 100_000, dec, core=c) for c in (core.PYTHON, core.load("compiled"))]
    for bad, now in ((0, 0), (5, 50_000), (5, 100_000), (70_000, 200_000)):
        dec.frames_bad = bad
        for tx in txs:
            tx.begin_tick(now)
            tx.step(now)
    ref, got = txs
    assert ref.port.frames == got.port.frames
    fd = FrameDecoder()
    msgs = [m for f in got.port.frames for m in fd.feed(f)]
    assert [m.errors for m in msgs] == [0, 5, 0xFFFF]
    assert all((m.node, m.role, m.state, m.proto_version, m.schema_hash) == (7, ROLE_FIRMWARE, STATE_RUNNING,
                                                                             PROTOCOL_VERSION, SCHEMA_HASH)
               for m in msgs)


def test_time_sync_master_broadcasts_through_the_transmitter(transmitter_pair):
    """``TimeSyncMaster.step`` with ``Transmitter.time_sync``: the periodic broadcasts and the
    requested ones leave as TIME_SYNC frames with the master time plus the latency and the
    sequence numbers, the same bytes on both cores."""
    ref, got = transmitter_pair()
    outs = []
    for tx in (ref, got):
        ts = TimeSyncMaster((1, 2), period_us=250_000, latency_us=40)
        for k in range(3000):
            now = 1000 * k
            if k % 600 == 0:
                ts.request(now + 3000)
            ts.step(now, tx.time_sync)
        outs.append(ts.sent)
    assert outs[0] == outs[1] > 12
    assert ref.port.frames == got.port.frames
    dec = FrameDecoder()
    msgs = [m for f in got.port.frames for m in dec.feed(f)]
    assert [m.sync_seq for m in msgs] == list(range(len(msgs)))
    assert msgs[0].master_time_us == 40 and all(m.master_time_us % 1000 == 40 for m in msgs)
