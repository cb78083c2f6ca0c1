"""The AC pipeline's steady-state tick allocates no numpy array.

``raab-ac`` (AC plan, demodulation of a 1 kHz magnetometer in sliding blocks,
a magnetic solve per block, delayed fusion updates with replay, fused poses
at 1 kHz) against the emulated bench: after a 1 s warm-up (plan sent, driver
answered, fusion filter initialised) 1,500 ticks inside
``tools.bench.alloc.NumpyAllocationCounter`` (numpy's array-data allocator replaced
by a counting one, see ``tests/firmware/test_alloc.py``) must count 0, and
those ticks must have demodulated, solved and fused blocks. Catches a
temporary array in the demodulator, the block hand-over, the AC trackers or
the actuation's status handling (a single ``np.empty(3)`` counts 1)."""
import pytest

from coiltrack.firmware.loop import Firmware
from coiltrack.tools import scenarios
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup

WARMUP_US = 1_000_000
TICKS = 1_500
pytestmark = pytest.mark.skipif(not available(), reason="numpy memory handler API not reachable")


def test_ac_ticks_allocate_no_numpy_array():
    sc = scenarios.get("raab-ac")
    cfg = sc.firmware_config()
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 3, (WARMUP_US + TICKS * 1000) * 1e-6 + 0.1, emu_end, cfg=cfg)
    fw = Firmware(cfg, fw_end)
    counter = NumpyAllocationCounter()
    t = 0
    while t < WARMUP_US:
        bench.emulator.step(t)
        fw.tick(t)
        t += cfg.timing.tick_us
    st0 = fw.status()
    allocating = 0
    for _ in range(TICKS):
        bench.emulator.step(t)
        before = counter.count
        with counter:
            fw.tick(t)
        allocating += counter.count != before
        t += cfg.timing.tick_us
    st = fw.status()
    assert allocating == 0, f"{allocating} ticks allocated numpy arrays"
    assert st["ac_blocks"] - st0["ac_blocks"] >= 160          # 1.5 s at 111 blocks/s
    assert st["ac_blocks_fused"] - st0["ac_blocks_fused"] >= 20
    assert st["fused_poses"] - st0["fused_poses"] >= 1400
    assert st["ac_statuses"] > st0["ac_statuses"]             # a driver report inside the window
