"""The two-process bench's link and loops, on injected clocks and in-process links
(no wall-clock assertions):

* physics computed ahead between steps (``Emulator.prefetch``) gives the very
  bytes the on-demand path gives, and leaves no physics on the sampling path;
* the emulator loop steps when a sample is due, fills its horizon before the
  start and computes ahead only while no sample is near;
* a coalescing pty link sends a step's frames in one write, and its read of an
  empty pty returns at once;
* the firmware loop flushes after every tick; the emulator's real-time set-up
  is undone on exit.
"""
from __future__ import annotations

import gc
import os
import select

import numpy as np
import pytest

from coiltrack.firmware.loop import Firmware
from coiltrack.hil.clock import SimClock
from coiltrack.tools.bench.links import FdLink, inproc_pair, is_pty_path, make_raw_pty, open_pty_slave
from coiltrack.tools.bench.realtime import (AHEAD_US, PREFETCH_AFTER_SEND_US, PREFETCH_GUARD_US, PREFETCH_PIECE,
                                      EmulatorRealtime,
                                      EmulatorTiming, emulator_loop, firmware_loop)
from coiltrack.tools.bench.runner import BenchSetup
from coiltrack.tools.scenarios import get

from .conftest import capture_writes, flag_inside_step


def _run_inproc(prefetch: bool, duration_us: int = 2_500_000):
    """Firmware and emulator on the simulated clock (as ``tools.bench.runner``), returning every byte
    the emulator sent, the sensor node, and how many physics evaluations its sampling path did."""
    sc = get("roetenberg-bench")
    cfg = sc.firmware_config()
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 3, duration_us * 1e-6, emu_end, None, cfg=cfg)
    fw = Firmware(cfg, fw_end)
    sensor, world, emu = bench.sensor, bench.sensor.world, bench.emulator
    on_path = {"precompute": 0, "pose": 0}
    real_pre, real_pose = world.precompute, world.trajectory.pose

    def precompute(times):
        on_path["precompute"] += inside[0]
        real_pre(times)

    def pose(t):
        on_path["pose"] += inside[0] and np.ndim(t) == 0      # the uncached field read
        return real_pose(t)
    world.precompute, world.trajectory.pose = precompute, pose
    inside = flag_inside_step(sensor)
    sent = capture_writes(emu_end)
    if prefetch:
        while emu.prefetch(AHEAD_US, 256):
            pass
    t = 0
    while t <= duration_us:
        emu.step(t)
        fw.tick(t)
        if prefetch:
            emu.prefetch(t + AHEAD_US, PREFETCH_PIECE, PREFETCH_PIECE)
        t += cfg.timing.tick_us
    return bytes(sent), sensor, on_path


def test_prefetched_physics_gives_the_same_bytes_and_leaves_the_sampling_path():
    """Computing the physics ahead must change nothing the firmware sees: the emulator's byte
    stream is identical with and without it (a prefetch that cached an instant under another's
    time, skipped the flip reads at t -+ flip_delta, or advanced past an instant it never computed
    changes a sample or its flip artefact). And with it the sampling path does no physics: no
    chunk precompute and no uncached field read inside a sensor step (a prefetch that stopped
    short of the horizon or missed the commanded flips' reads leaves some there)."""
    plain, s0, path0 = _run_inproc(False)
    ahead, s1, path1 = _run_inproc(True)
    assert s1.samples == s0.samples >= 150
    assert len(s1.flip_log) == len(s0.flip_log) >= 3
    assert any(f["commanded"] for f in s1.flip_log)
    assert ahead == plain
    assert path0["precompute"] > 0 and path0["pose"] > 0      # the on-demand path does work there ...
    assert path1 == {"precompute": 0, "pose": 0}              # ... and none once it is done ahead


class _DueEmu:
    """An emulator whose samples are due at ``due`` (us); records steps and prefetch calls."""

    def __init__(self, clock, due, prefetch_cost_us=0):
        self.clock = clock
        self.due = list(due)
        self.steps = []
        self.prefetches = []
        self.cost = prefetch_cost_us
        self.horizon = -1
        self.recorder = type("R", (), {"poses": []})()

    def next_due_us(self):
        return self.due[0] if self.due else None

    def step(self, now):
        self.steps.append(now)
        while self.due and self.due[0] <= now:
            self.due.pop(0)

    def prefetch(self, until, max_n, min_n=1):
        self.prefetches.append((self.clock.now(), until, max_n, min_n, self.next_due_us()))
        if until - self.horizon < min_n * 1000:
            return 0
        self.horizon = until
        self.clock.now_us += self.cost
        return max_n


def test_emulator_loop_steps_when_a_sample_is_due():
    """A sample due between two polls is taken at its instant, not at the next 250 us poll (a
    loop that ignores ``next_due_us`` steps at 250, 500, 750 and so sends the 1 130 us sample
    120 us late); with nothing due the loop still polls every ``step_us``."""
    clock = SimClock(0)
    emu = _DueEmu(clock, [130, 1130, 1131])
    timing = EmulatorTiming(cap=64)
    emulator_loop(emu, object(), clock, 2_000, step_us=250, wait=clock.sleep, timing=timing, ahead_us=0)
    assert 130 in emu.steps and 1130 in emu.steps and 1131 in emu.steps
    assert emu.steps[:3] == [0, 130, 380]
    assert emu.prefetches == []                                # ahead_us=0: none
    rep = timing.report()
    assert rep["emulator_sample_late_us_max"] == 0.0           # every sample stepped at its instant


def test_emulator_loop_fills_its_horizon_first_and_computes_ahead_only_away_from_samples():
    """Before the start (clock < 0) the horizon is filled (a loop that only tops up while running
    computes the first pieces on the sampling path); while running, a piece is computed only when
    the next sample is more than PREFETCH_GUARD_US away (a piece right before a due sample makes
    it late by the piece's cost)."""
    clock = SimClock(-5_000)
    due = [1_000, 1_000 + PREFETCH_GUARD_US + 2_000, 30_000]
    emu = _DueEmu(clock, due, prefetch_cost_us=700)
    emulator_loop(emu, object(), clock, 40_000, step_us=250, wait=clock.sleep, ahead_us=AHEAD_US)
    first = emu.prefetches[0]
    assert first[0] < 0 and first[1] == AHEAD_US and first[3] == 1
    assert all(p[1] == AHEAD_US for p in emu.prefetches if p[0] < 0)
    running = [p for p in emu.prefetches if p[0] >= 0]
    assert running
    for at, until, max_n, min_n, nxt in running:
        assert (max_n, min_n) == (PREFETCH_PIECE, PREFETCH_PIECE)
        assert nxt is None or nxt - at > PREFETCH_GUARD_US
    for d in due:
        assert d in emu.steps                                  # no sample delayed by a piece


class _CountingLink:
    """A link that counts what the emulator sent (as ``FdLink.bytes_tx``); the emulator's steps
    at the instants ``writes_at`` write 10 bytes each."""

    def __init__(self, emu, writes_at):
        self.bytes_tx = 0
        self.emu, self.writes_at = emu, set(writes_at)

    def flush(self):
        if self.emu.steps and self.emu.steps[-1] in self.writes_at:
            self.writes_at.discard(self.emu.steps[-1])
            self.bytes_tx += 10


def test_emulator_loop_computes_no_piece_right_after_it_sent():
    """A piece waits PREFETCH_AFTER_SEND_US after a step that wrote to the link: the firmware's
    answer (a POSE) comes then, and a piece computed meanwhile stamps it late by the piece's cost
    and, at the loop's SCHED_FIFO priority, keeps the tty's flush work from moving the bytes (a
    loop without the rule computes its pieces right after each sample it sends). Pieces still
    come between the samples, and no sample is delayed."""
    clock = SimClock(-1_000)
    due = [1_000, 12_000, 23_000]
    emu = _DueEmu(clock, due, prefetch_cost_us=700)
    link = _CountingLink(emu, due)
    emulator_loop(emu, link, clock, 30_000, step_us=250, wait=clock.sleep, ahead_us=AHEAD_US)
    running = [p[0] for p in emu.prefetches if p[0] >= 0]
    assert running
    for sent in due:
        assert not [at for at in running if sent <= at < sent + PREFETCH_AFTER_SEND_US]
    assert [at for at in running if 1_000 + PREFETCH_AFTER_SEND_US <= at < 12_000 - PREFETCH_GUARD_US]
    for d in due:
        assert d in emu.steps


def test_coalescing_pty_link_sends_a_step_in_one_write_and_reads_never_wait():
    """Frames queued in a step leave in one write at ``flush`` (a link that writes at once makes
    one write a frame: three here), in order; reading an empty pty returns b'' at once, on the
    slave side opened by path as ``coiltrack firmware`` opens it."""
    master, slave, name = make_raw_pty()
    try:
        assert is_pty_path(name) and not is_pty_path("/dev/ttyUSB0") and not is_pty_path("loop://")
        fw = open_pty_slave(name)
        emu = FdLink(master, coalesce=True)
        assert fw.read() == b""
        for frame in (b"\x01\x02\x00", b"\x03\x00", b"\x04\x05\x06\x00"):
            emu.write(frame)
        assert emu.writes == 0
        emu.flush()
        assert emu.writes == 1 and emu.bytes_tx == 9
        got = b""
        for _ in range(200):            # bounded: the pty's buffer work may be queued
            select.select([fw.fd], [], [], 0.05)
            got += fw.read()
            if len(got) >= 9:
                break
        assert got == b"\x01\x02\x00\x03\x00\x04\x05\x06\x00"
        fw.close()
        assert fw.fd == -1
    finally:
        os.close(master)
        os.close(slave)


def test_firmware_loop_calls_after_tick_once_per_tick():
    """``after_tick`` (a coalescing link's flush) runs after every tick, so no tick's frames wait
    for the next one (a loop that flushes only now and then delays a POSE by a tick or more)."""
    clock = SimClock(0)
    order = []

    class Fw:
        def tick(self, t):
            order.append(("tick", t))

    out = firmware_loop(Fw(), clock, 5_000, 1000, spin_us=0, after_tick=lambda: order.append(("flush",)))
    assert out["ticks"] == 5
    assert order == [x for t in range(0, 5000, 1000) for x in (("tick", t), ("flush",))]


def test_emulator_realtime_is_undone_on_exit():
    """Inside, the cyclic GC is off; after, the scheduling policy and the GC are as before (an
    emulator left at SCHED_FIFO would run the report and the in-process comparison runs at
    real-time priority; a GC left off would leak cycles in a long session)."""
    if not hasattr(os, "sched_getscheduler"):
        pytest.skip("no POSIX scheduling interface")
    pol, par = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    was = gc.isenabled()
    with EmulatorRealtime() as rt:
        assert not gc.isenabled()
        assert rt.info["emulator_sched"] in ("fifo", "other")
    assert os.sched_getscheduler(0) == pol and os.sched_getparam(0).sched_priority == par
    assert gc.isenabled() == was


def test_a_link_whose_peer_does_not_read_drops_and_counts_instead_of_growing():
    """Nobody reads the slave: writes beyond ``MAX_PENDING`` queued bytes are dropped and counted
    (a link that queues without bound grows the firmware's memory for as long as the peer is gone)."""
    master, slave, name = make_raw_pty()
    try:
        link = FdLink(master, coalesce=True)
        link.MAX_PENDING = 4096
        for _ in range(10):
            link.write(b"\x00" * 1000)
        assert len(link._pending) <= 4096 and link.bytes_dropped == 6000
    finally:
        os.close(master)
        os.close(slave)
