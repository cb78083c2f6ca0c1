"""The AC drive comes back after the coil driver's power cut (``node_off=driver``)."""
from coiltrack.firmware.loop import Firmware
from coiltrack.hil.faults import BenchFaults
from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID
from coiltrack.tools import scenarios
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup


def test_driver_power_cut_replans_and_poses_resume():
    """The driver is off from 2 to 3 s (its drive stops, it reboots and forgets the plan): the
    firmware sees no AC_DRIVE_STATUS for ``ac_status_timeout_us`` (3 s), sends a new plan, and
    valid magnetic poses come back within 1 s of it; during the cut no block solves (no coil
    field): catches a firmware that keeps demodulating a drive that is gone, for ever."""
    sc = scenarios.get("ac-vs-dc-clean")
    cfg = sc.firmware_config()
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 2, 6.5, emu_end, BenchFaults.parse("node_off=driver@2s-3s"), cfg=cfg)
    fw = Firmware(cfg, fw_end)
    t = 0
    while t <= 6_500_000:
        bench.emulator.step(t)
        fw.tick(t)
        t += cfg.timing.tick_us
    st = fw.status()
    assert st["ac_status_timeouts"] == 1 and st["ac_plans_sent"] == 2, st
    valid = [rp["msg"].t_us for rp in bench.recorder.poses
             if rp["msg"].status & POSE_VALID and not rp["msg"].status & POSE_FUSED]
    assert not [v for v in valid if 2_100_000 < v < 3_000_000]
    replan = 1_000_000 * 4.2
    assert [v for v in valid if replan < v < replan + 1_300_000]
    assert len([v for v in valid if v > 5_500_000]) >= 100
