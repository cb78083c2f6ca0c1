"""IMU steps given back from IMU_DELTA pairs are spread over ticks (``[budget] imu_steps_per_tick``).

A 10 Hz pair turns into twelve 120 Hz steps at once; run in one tick, each step a strapdown
and covariance prediction, that tick is twelve fused ticks long (1.3-1.6 ms measured with
``coiltrack perf --scenario roetenberg-fusion-delta``, against a 1 ms tick). The fusion
pipeline runs at most ``imu_steps_per_tick`` of them per sensor per tick; the rest wait.
"""
from coiltrack.firmware.loop import Firmware
from coiltrack.tools import scenarios
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup

WARMUP_US = 2_000_000
RUN_US = 5_000_000


def test_delta_pairs_are_fused_a_budget_at_a_time():
    """On ``roetenberg-fusion-delta`` (4 s after a 2 s warm-up): no tick runs more than the budget's
    IMU steps, every step received is fused within a pair interval (none starved, none dropped), and
    the queued steps allocate nothing. Catches a budget that is ignored (12 steps in a tick), a queue
    that never drains or overflows (steps lost), and a bounded drain that allocates."""
    sc = scenarios.get("roetenberg-fusion-delta")
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 2, RUN_US * 1e-6 + 1.0, emu_end)
    cfg = sc.firmware_config()
    fw = Firmware(cfg, fw_end)
    ins = next(iter(fw.tracker.inertial.values()))
    counter = NumpyAllocationCounter() if available() else None
    most, allocs, t = 0, 0, 0
    while t < RUN_US:
        bench.emulator.step(t)
        before, a0 = ins.samples, counter.count if counter else 0
        if counter:
            with counter:
                fw.tick(t)
        else:
            fw.tick(t)
        if t >= WARMUP_US:
            most = max(most, ins.samples - before)
            allocs += (counter.count - a0) if counter else 0
        t += cfg.timing.tick_us
    assert fw.receiver.imu_deltas > 0, "the scenario sends IMU_DELTA pairs"
    assert most == cfg.budget.imu_steps_per_tick            # the budget binds, and is kept
    backlog = fw.receiver.imu_received - ins.samples
    assert 0 <= backlog <= 12, backlog                # at most one pair's steps still queued
    assert ins.imu.dropped == 0
    assert allocs == 0
