"""Protocol v4: TIME_SYNC_REPLY in one classic frame, and the bus load at the firmware's real
TIME_SYNC rate (every node answering every broadcast).

The field values of the golden reply are checked through cantools with the exported DBC in
``test_busform.py`` (``WANT``); here: the sequence restore at its wrap edges against an
enumeration, the range edges of each field (in: one frame, restored exactly; one past: the full
PDU on the 29-bit identifier, unchanged), a receiver that did not hear the echoed TIME_SYNC, and
the busload model's broadcast count against a firmware run on the simulated clock."""
from __future__ import annotations

import json

import pytest

from coiltrack.protocol.busform import BusContext, restore_seq
from coiltrack.protocol.busload import Traffic, bus_load, sync_broadcasts_per_cycle
from coiltrack.protocol.can import CanCodec, CanReassembler, can_id
from coiltrack.protocol.codec import MSG
from coiltrack.protocol.schema import NODE_COIL_DRIVER, NODE_FIRMWARE, NODE_SENSOR_BASE
from coiltrack.tools.cli import main

TS, RP = MSG["TIME_SYNC"], MSG["TIME_SYNC_REPLY"]
M = 2_000_150_250            # master time of the echoed TIME_SYNC
OFF = 3_456_789              # a node counter 3.46 s ahead of the master's (the bench: 0.1-5 s)


def _heard(*syncs) -> BusContext:
    ctx = BusContext()
    for seq, t in syncs:
        ctx.note(TS(t, seq))
    return ctx


def _reference_seq(bits: int, latest: int) -> int:
    """By enumeration: of all 65536 sequence numbers, the one with these low 6 bits that is at most
    63 broadcasts before ``latest`` (counting modulo 2^16)."""
    hits = [s for s in range(1 << 16) if s % 64 == bits and (latest - s) % (1 << 16) < 64]
    assert len(hits) == 1
    return hits[0]


@pytest.mark.parametrize("latest", [0, 1, 63, 64, 100, 65472, 65535])
def test_sequence_restores_at_the_wrap_edges(latest):
    """Every 6-bit value restores to the one number in [latest - 63, latest] modulo 2^16, also
    across the 16-bit wrap (a window centred on ``latest``, one off by one, or a restore that
    forgot the wrap and gave a negative number differ from the enumeration)."""
    for bits in range(64):
        assert restore_seq(bits, latest) == _reference_seq(bits, latest), bits
    assert restore_seq(latest % 64, latest) == latest
    assert restore_seq((latest + 1) % 64, latest) == (latest - 63) % (1 << 16)


def _reply(**kw):
    vals = dict(node=NODE_SENSOR_BASE, sync_seq=7, node_time_us=M + OFF + 120, offset_us=OFF, drift_ppb=-41_000)
    vals.update(kw)
    return RP(**vals)


@pytest.mark.parametrize("change", [
    dict(node_time_us=M + OFF + 8191), dict(node_time_us=M + OFF - 8192),        # lateness +-8.19 ms
    dict(offset_us=(1 << 25) - 1, node_time_us=M + (1 << 25) - 1),                # offset +-33.55 s
    dict(offset_us=-(1 << 25), node_time_us=M - (1 << 25)),
    dict(drift_ppb=131_071), dict(drift_ppb=-131_072),                             # drift +-131 ppm
])
def test_a_reply_at_its_range_edges_is_one_frame_restored_exactly(change):
    """At each field's range edge the reply is one 8-byte frame on the sender's 11-bit identifier
    and the receiver restores node_time_us, offset_us and drift_ppb exactly (a sign bit lost, a
    field one bit narrower than its table row, or node_time restored against the wrong base
    differs)."""
    msg = _reply(**change)
    (f,) = CanCodec(context=_heard((7, M))).encode(msg, 3, NODE_SENSOR_BASE)
    assert not f.is_extended_id and f.arbitration_id == can_id(RP.ID, NODE_SENSOR_BASE) and len(f.data) == 8
    r = CanReassembler(context=_heard((7, M)))
    assert r.feed(f) == [msg] and r.frames_bad == 0


@pytest.mark.parametrize("change, ctx", [
    (dict(node_time_us=M + OFF + 8192), ((7, M),)),                  # a held step, a long stall
    (dict(node_time_us=M + OFF - 8193), ((7, M),)),
    (dict(offset_us=1 << 25, node_time_us=M + (1 << 25)), ((7, M),)),   # a master restarted long after
    (dict(offset_us=-(1 << 25) - 1, node_time_us=M - (1 << 25) - 1), ((7, M),)),
    (dict(drift_ppb=131_072), ((7, M),)),                            # acquiring, or a broken crystal
    (dict(drift_ppb=-131_073), ((7, M),)),
    (dict(), ((6, M - 250_000),)),                                   # sync 7 not heard by the sender
    (dict(), ((7, M), (71, M + 6_400_000))),                         # 64 broadcasts later: 7 forgotten
    (dict(), ()),                                                    # no TIME_SYNC heard at all
])
def test_a_reply_the_form_cannot_carry_goes_in_full_unchanged(change, ctx):
    """One past an edge, or the echoed TIME_SYNC unknown to the sender: the reply travels as the
    full PDU segmented on the 29-bit identifier (4 classic frames) and arrives unchanged at a
    receiver that heard nothing (a codec that clipped the lateness, wrapped the offset or drift,
    or restored the sequence against a newer broadcast would deliver another reply)."""
    msg = _reply(**change)
    codec = CanCodec(context=_heard(*ctx))
    fr = codec.encode(msg, 3, NODE_SENSOR_BASE)
    assert len(fr) == 4 and all(f.is_extended_id and f.arbitration_id >> 18 == can_id(RP.ID, NODE_SENSOR_BASE)
                                for f in fr)
    assert codec.fallbacks == 1
    r = CanReassembler()
    assert [m for f in fr for m in r.feed(f)] == [msg] and r.frames_bad == 0


def test_a_receiver_that_did_not_hear_the_time_sync_drops_the_reply():
    """A receiver without the echoed broadcast counts the reply as unresolved and delivers nothing
    (restoring it against another TIME_SYNC would move node_time_us by the broadcasts' spacing).
    One that heard broadcasts after it (up to 63) still restores it exactly."""
    (f,) = CanCodec(context=_heard((7, M))).encode(_reply(), 3, NODE_SENSOR_BASE)
    r = CanReassembler(context=_heard((7, M), *((s, M + 2000 * (s - 7)) for s in range(8, 71))))
    assert r.feed(f) == [_reply()] and r.frames_bad == 0
    for ctx in (BusContext(), _heard((6, M - 250_000)), _heard((8, M + 250_000))):
        r = CanReassembler(context=ctx)
        assert r.feed(f) == [] and r.unresolved == 1


def test_sync_count_model_follows_the_timer_rules():
    """The model's timer restarts at every broadcast: 250 ms alone gives 4 per second whatever the
    cycle; the firmware's requests (commands at 0, three after the burst at 311-315 ms) give 6 per
    600 ms (a timer that did not restart at a requested broadcast gives 7, one that ignored the
    requests 2.4)."""
    assert sync_broadcasts_per_cycle(1_000_000, 250_000) == pytest.approx(4.0)
    assert sync_broadcasts_per_cycle(600_000, 250_000) == pytest.approx(2.4)
    assert sync_broadcasts_per_cycle(600_000, 250_000, [0, 311_000, 313_000, 315_000]) == pytest.approx(6.0)


def test_busload_counts_the_firmware_traffic_and_fits_the_budget(capsys):
    """`busload` with the defaults: TIME_SYNC at the firmware's 10 Hz, every node's reply one
    8-byte frame (135 bits) per broadcast; 16 sensors classic and 32 on CAN FD within 70 % (a
    model at 1 Hz, or with the reply segmented at 10 Hz, 79.6 %, fails one of these)."""
    assert main(["busload", "--nodes", "16", "--bitrate", "500000", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["traffic"]["sync_hz"] == pytest.approx(10.0) and rep["load_pct"] <= 70.0
    rows = [r for r in rep["rows"] if r["message"] == "TIME_SYNC_REPLY"]
    assert {r["sender"]: r["senders"] for r in rows} == {"sensor": 16, "coil driver": 1}
    assert all(r["frame_bytes"] == [8] and r["bits_per_msg"] == 135.0 and r["rate_hz"] == 10.0 for r in rows)
    assert main(["busload", "--nodes", "32", "--bitrate", "500000", "--fd", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["load_pct"] <= 70.0
    assert bus_load(Traffic(sensors=16, sync_hz=10.0))["load_pct"] == rep["load_pct"]


def test_busload_sync_rate_matches_a_counted_firmware_run():
    """A firmware and the emulated nodes of ``roetenberg-bench`` on the in-process CAN bus,
    simulated clock, 3.2 s: a third station on the bus counts the TIME_SYNC frames between the
    first and the fourth burst of commands (three cycles) and each node's replies to them. The
    count is the busload model's (``firmware_sync_hz``) times the cycles, every node answers every
    one, each reply is one 8-byte frame and none falls back to the full form (a model that
    forgot the per-burst broadcasts, or a node whose reply did not fit the form, fails)."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.protocol.can import open_bus, unique_channel, virtual_link_pair
    from coiltrack.tools.commands.busload import firmware_sync_hz
    from coiltrack.tools.bench.runner import BenchSetup
    from coiltrack.tools.scenarios import SCENARIOS

    sc = SCENARIOS["roetenberg-bench"]
    cfg = sc.firmware_config()
    channel = unique_channel("sync-count")
    fw_end, emu_end = virtual_link_pair(NODE_FIRMWARE, NODE_COIL_DRIVER, channel)
    sniff = open_bus("virtual", channel)
    rx = CanReassembler()
    seen = []                     # (t_us, message, frames on the 11-bit id, extended frames)
    bench = BenchSetup(sc, 1, 3.2, emu_end, cfg=cfg)
    fw = Firmware(cfg, fw_end)
    try:
        t = 0
        while t <= 3_200_000:
            bench.emulator.step(t)
            fw.tick(t)
            while (f := sniff.recv(timeout=0)) is not None:
                for _, m in rx.feed_with_headers(f):
                    seen.append((t, m, f.is_extended_id))
            t += cfg.timing.tick_us
    finally:
        fw_end.close()
        emu_end.close()
        sniff.shutdown()
    bursts = sorted({t for t, m, _ in seen if m.NAME == "COIL_PULSE_CMD"})
    starts = [b for i, b in enumerate(bursts) if i == 0 or b - bursts[i - 1] > 100_000]
    assert len(starts) >= 4
    t0, t1 = starts[0], starts[3]
    syncs = [m.sync_seq for t, m, _ in seen if m.NAME == "TIME_SYNC" and t0 <= t < t1]
    hz = firmware_sync_hz(cfg.timing.cycle_us, len(cfg.source.coils))
    assert len(syncs) == round(hz * cfg.timing.cycle_us * 3e-6) == 18
    nodes = tuple(cfg.link.sensor_ids) + (cfg.link.coil_driver_id,)
    for n in nodes:
        answered = {m.sync_seq for _, m, _ in seen if m.NAME == "TIME_SYNC_REPLY" and m.node == n}
        assert set(syncs) <= answered, n
    replies = [ext for _, m, ext in seen if m.NAME == "TIME_SYNC_REPLY"]
    assert len(replies) >= 30 * len(nodes) and not any(replies)    # acquisition included: one frame each
    assert fw_end.codec.fallbacks == emu_end.codec.fallbacks == 0 and rx.frames_bad == 0
