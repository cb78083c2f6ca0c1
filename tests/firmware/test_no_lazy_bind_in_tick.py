"""No tick binds a kernel: each sensor's compiled per-sample kernels (the orientation filter's
one-call sample ``ext.OriStep``, the compass sample's search ``ext.QuietSample``, the fused
one-call sample ``ext.ImuSample``) are bound to the sensor's magnetometer ring when the firmware
is composed (``SensorInertial.bind_ring``, ``SourceInertial``'s own ring).

Bound at a sensor's first IMU sample instead, multi16's first contact with its sixteen sensors
made sixteen such bindings in one tick (2.2-3.7 ms: its one deadline miss on CAN): the fused
one-call path bound itself at its first drain of a sensor's IMU ring, empty or not. The check:
after the firmware is built, a run through the first IMU samples, acquisitions and poses makes
not one binding (a kernel bound lazily on the tick fails it)."""
import pytest

from coiltrack.firmware.loop import Firmware
from coiltrack.firmware.track import burst_fusion
from coiltrack.tools import scenarios
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")


@pytest.mark.parametrize("name,imu", [("multi16", False), ("roetenberg-fusion-srcimu", True), ("raab-ac", True)])
def test_no_tick_binds_a_kernel(name, imu, monkeypatch):
    sc = scenarios.get(name)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, 1.5, emu_end)
    fw = Firmware(sc.firmware_config().with_(core={"impl": "compiled"}), fw_end)
    calls = []

    def counted(cls, name):
        real = getattr(cls, name)
        monkeypatch.setattr(cls, name, lambda self, *a: calls.append(name) or real(self, *a))

    counted(burst_fusion._Ori, "_bind_sample")
    counted(burst_fusion._OneCall, "_bind")
    counted(burst_fusion.PulseGate, "sample_kernel")
    for t in range(0, 1_200_001, 1000):
        bench.emulator.step(t)
        fw.tick(t)
    ins = list(fw.tracker.inertial.values())
    assert fw.poses > 0                                       # the run got through acquisition to poses
    assert all(i.ori.sample_kernel is not None for i in ins)  # the compiled one-call path, bound
    if imu:                                                   # ... and run: every sensor's IMU samples
        assert all(i.samples > 100 for i in ins)
    assert calls == [], f"kernels bound inside a tick: {sorted(set(calls))}"
