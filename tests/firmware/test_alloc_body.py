"""The body-worn tick allocates nothing either: the gyroscope-turned pulse
windows (``measure.gyro_baseline``) and the adaptive inclination variance
(``estimate.orientation``) on ``roetenberg-flexion-back`` (moving source,
its own IMU module, fused). After a 3.5 s warm-up (filters initialised, the
first bursts fused) every tick of the next 1.5 s (two and a half magnetic
cycles: windows closed, turned, solved and fused; for the tight tracker also
its quiet-field updates, at least 20 of them) must count 0 numpy
allocations (``tools.bench.alloc.NumpyAllocationCounter``, as ``test_alloc``).
Catches a temporary array in the turned extraction, the gyro ring, the
motion variance or the quiet-field update."""
import pytest

from coiltrack.firmware.loop import Firmware
from coiltrack.tools import scenarios
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup

pytestmark = pytest.mark.skipif(not available(), reason="numpy memory handler API not reachable")


@pytest.mark.parametrize("name", ["roetenberg-flexion-back", "roetenberg-flexion-back-loose"])
def test_body_ticks_allocate_no_numpy_array(name):
    """(The tightly coupled tracker, and the loosely coupled one.)"""
    sc = scenarios.get(name)
    cfg = sc.firmware_config()
    assert cfg.body.baseline_gyro and cfg.body.acc_adapt_gain > 0
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, 5.2, emu_end)
    fw = Firmware(cfg, fw_end)
    counter = NumpyAllocationCounter()
    bad = 0
    t = 0
    quiet0 = None
    while t < 5_000_000:
        bench.emulator.step(t)
        if t >= 3_500_000:
            if quiet0 is None:
                quiet0 = fw.status().get("fusion_quiet_updates", 0)
            before = counter.count
            with counter:
                fw.tick(t)
            bad += counter.count != before
        else:
            fw.tick(t)
        t += cfg.timing.tick_us
    turned = sum(ch.extractor.turned_windows for ch in fw.channels)
    assert turned >= 20, turned
    assert fw.status().get("fused_poses", 0) > 100
    if cfg.tight.tight_fusion:
        assert fw.status()["fusion_quiet_updates"] - quiet0 >= 20
    assert bad == 0, f"{bad} ticks allocated numpy arrays"
