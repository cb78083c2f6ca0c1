"""The steady-state tick allocates nothing.

Three checks on a fused bench run (``roetenberg-fusion``: IMU at 120 Hz,
magnetic bursts every 600 ms, solves, motion compensation, delayed fusion
updates with replay, fused poses at the IMU rate):

1. 100,000 ticks (100 s) live against the emulated bench, each tick inside
   ``tools.bench.alloc.NumpyAllocationCounter``: numpy's own array-data allocator
   is replaced by one that counts every malloc/calloc/realloc, so a single
   temporary 3-vector in a tick counts 1. After a 5 s warm-up every tick must
   count 0.
2. The same 100 s of inputs (recorded by the live run) replayed into a fresh
   firmware under tracemalloc, started after the warm-up: the memory held by
   objects allocated in ``firmware_py`` and ``protocol`` does not grow
   (snapshots at 40, 70 and 100 s), and no numpy-domain block is left alive.
3. An opcode-level tracemalloc check (``sys.settrace`` with opcode events,
   live numpy-domain blocks counted before every instruction) over the last
   ticks of a magnetic cycle (IMU samples, fused poses, the last pulse
   windows), the tick that closes the burst and solves it, the tick that
   solves it again from the motion-compensated signals and the tick that
   fuses it at its middle and replays the IMU samples since. It costs seconds per solve, so it covers one cycle; the
   counting allocator of check 1 sees every allocation call, temporaries
   included, in all 100,000 ticks.

``test_the_checks_catch_one_temporary_array`` proves each check sees a single
``np.empty(3)`` added to the tick.
"""
import tracemalloc

import numpy as np
import pytest

from coiltrack.firmware.loop import Firmware
from coiltrack.tools import scenarios
from coiltrack.tools.bench.alloc import NUMPY_DOMAIN, NumpyAllocationCounter, available, numpy_blocks_alive_during
from coiltrack.tools.bench.framelog import RecordingPort, ReplayPort, config_to_dict, log_config
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup

WARMUP_US = 5_000_000
TICKS = 100_000
pytestmark = pytest.mark.skipif(not available(), reason="numpy memory handler API not reachable")


@pytest.fixture(scope="module")
def live_run():
    sc = scenarios.get("roetenberg-fusion")
    duration = TICKS / 1000.0 + 1.0
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 4, duration, emu_end)
    cfg = sc.firmware_config()
    port = RecordingPort(fw_end)
    fw = Firmware(cfg, port)
    counter = NumpyAllocationCounter()
    per_tick = []
    t = 0
    measured = 0
    while measured < TICKS:
        bench.emulator.step(t)
        port.now_us = t
        before = counter.count
        with counter:
            fw.tick(t)
        if t >= WARMUP_US:
            per_tick.append(counter.count - before)
            measured += 1
        t += cfg.timing.tick_us
    header = {"scenario": sc.name, "seed": 4, "duration_s": t * 1e-6, "tick_us": cfg.timing.tick_us,
              "config": config_to_dict(cfg)}
    return {"fw": fw, "per_tick": np.asarray(per_tick), "header": header, "reads": port.reads}


def test_100k_ticks_allocate_no_numpy_array(live_run):
    per_tick = live_run["per_tick"]
    fw = live_run["fw"]
    st = fw.status()
    assert per_tick.size == TICKS
    assert int(per_tick.sum()) == 0, f"{int((per_tick > 0).sum())} ticks allocated numpy arrays"
    # the measured ticks did everything the fused firmware does
    assert st["cycles"] >= 160 and st["poses"] >= 150
    assert st["fusion_updates"] >= 150 and st["fusion_compensated"] >= 100
    assert st["fused_poses"] >= 11_000


def _replay_firmware(live_run):
    cfg = log_config(live_run["header"])
    port = ReplayPort(live_run["reads"])
    return Firmware(cfg, port), port


def test_no_net_growth_under_tracemalloc(live_run):
    fw, port = _replay_firmware(live_run)
    files = [tracemalloc.Filter(True, "*/firmware_py/*"), tracemalloc.Filter(True, "*/protocol/*")]
    marks = {40_000_000: None, 70_000_000: None}
    end = WARMUP_US + TICKS * 1000
    t = 0
    try:
        while t < end:
            if t == WARMUP_US:
                tracemalloc.start()
            if t in marks:
                marks[t] = tracemalloc.take_snapshot()
            port.now_us = t
            fw.tick(t)
            t += 1000
        last = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    size = lambda snap: sum(tr.size for tr in snap.filter_traces(files).traces)  # noqa: E731
    s40, s70, s100 = size(marks[40_000_000]), size(marks[70_000_000]), size(last)
    # bounded, not growing: a few ints/floats held in fixed slots may be replaced by larger ones
    assert s100 - s70 <= 1024, (s40, s70, s100)
    assert s100 - s40 <= 2048, (s40, s70, s100)
    # no numpy array block allocated after the warm-up is still alive
    assert len(last.filter_traces([NUMPY_DOMAIN]).traces) == 0
    assert fw.status()["fusion_updates"] == live_run["fw"].status()["fusion_updates"]   # same run replayed


def test_opcode_level_check_over_a_cycle_with_solve_and_fusion(live_run):
    fw, port = _replay_firmware(live_run)
    t = 0
    # run up to 100 ticks before a burst closes (cycles advance every 600 ms)
    while t < 9_000_000:
        port.now_us = t
        fw.tick(t)
        t += 1000
    cycles0 = fw.cycles
    fused0 = fw.tracker.inertial[16].fused
    peak = 0
    ticks = 0
    closing = False
    while fw.tracker.inertial[16].fused == fused0:
        port.now_us = t
        tt = t
        closing = closing or (fw.schedule.burst_start is not None and fw.schedule.burst_start + 285_000 <= tt)
        if closing:
            peak = max(peak, numpy_blocks_alive_during(lambda: fw.tick(tt)))
            ticks += 1
        else:
            fw.tick(tt)
        t += 1000
    # the checked ticks closed the burst and solved it, solved it again from the
    # compensated signals, and fused it at its middle with the replay
    assert fw.cycles == cycles0 + 1 and fw.tracker.inertial[16].compensated >= 1
    assert ticks >= 10
    assert peak == 0


def test_the_checks_catch_one_temporary_array(live_run):
    fw, port = _replay_firmware(live_run)
    t = 0
    while t < 6_000_000:
        port.now_us = t
        fw.tick(t)
        t += 1000
    kept = []
    real_transmit = fw.stages[-1]

    def transmit_with_temporary(now_us):
        real_transmit(now_us)
        np.empty(3)                      # created and dropped at once

    def transmit_with_kept_array(now_us):
        real_transmit(now_us)
        kept.append(np.empty(3))

    counter = NumpyAllocationCounter()
    fw.stages = fw.stages[:-1] + (transmit_with_temporary,)
    for _ in range(50):
        port.now_us = t
        with counter:
            fw.tick(t)
        t += 1000
    assert counter.count == 50
    tt = t
    assert numpy_blocks_alive_during(lambda: fw.tick(tt)) == 1
    t += 1000
    fw.stages = fw.stages[:-1] + (transmit_with_kept_array,)
    tracemalloc.start()
    try:
        for _ in range(50):
            port.now_us = t
            fw.tick(t)
            t += 1000
        snap = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    assert len(snap.filter_traces([NUMPY_DOMAIN]).traces) == 50
