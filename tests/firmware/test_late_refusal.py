"""A stall around a coil command costs the burst's pose, never a bad pose (``actuate/burst.py``,
"A pulse refused as late"). In process, on the simulated clock (roetenberg-bench, seed 1, 3 s:
cycles start at 0.2, 0.8, 1.4 s, pulses 100 ms apart, each commanded 50 ms ahead):

* the emulator (the link, the driver's node) stops for 96 ms over one command's time, as the
  hypervisor's 100 ms stalls of the two-process bench do: the command reaches the driver 35 ms
  after its start and is refused (``COIL_FAULT_REFUSED | COIL_FAULT_LATE``, 48, by the driver's
  own rule); the firmware drops that burst (no pose from it), reports the refusal
  (``EVT_COIL_FAULT``) and every pose it sends is valid; the code before sent the burst's pose
  with ``POSE_COIL_FAULT`` and without ``POSE_VALID``;
* the firmware itself stops for 96 ms: the pulse whose start has passed is not commanded at all.

A refusal for another reason (over current) still reaches the pose as ``POSE_COIL_FAULT``.
"""
from __future__ import annotations

import pytest

from coiltrack.firmware.loop import Firmware
from coiltrack.hil.nodes import DriverLimits
from coiltrack.protocol.schema import (COIL_FAULT_LATE, COIL_FAULT_REFUSED, EVT_COIL_FAULT, POSE_COIL_FAULT,
                                       POSE_VALID)
from coiltrack.tools import scenarios
from coiltrack.tools.bench.runner import BenchSetup, sim_link_pair

DURATION_US = 3_000_000
BURST2 = 1_400_000            # the third cycle's first pulse starts here (X; Y at +100 ms, Z at +200 ms)


def _run(stall=None, who="emulator", limits=None):
    """The bench with the emulator (``who="emulator"``) or the firmware not stepped over
    ``stall`` = (t0, t1) us; returns (bench, firmware)."""
    sc = scenarios.get("roetenberg-bench")
    cfg = sc.firmware_config()
    fw_end, emu_end = sim_link_pair("inproc")
    b = BenchSetup(sc, 1, DURATION_US * 1e-6, emu_end, cfg=cfg)
    if limits is not None:
        b.driver.limits = limits
    fw = Firmware(cfg, fw_end)
    t = 0
    while t <= DURATION_US:
        stalled = stall is not None and stall[0] <= t < stall[1]
        if not (stalled and who == "emulator"):
            b.emulator.step(t)
        if not (stalled and who == "firmware"):
            fw.tick(t)
        t += 1000
    b.emulator.step(t)
    return b, fw


def _poses(b):
    return [(rp["msg"].t_us, rp["msg"].status) for rp in b.recorder.poses]


@pytest.fixture(scope="module")
def clean():
    return _poses(_run()[0])


def test_no_stall_every_pose_valid(clean):
    assert len(clean) == 5 and all(st & POSE_VALID and not st & POSE_COIL_FAULT for _, st in clean)


@pytest.mark.parametrize("coil", [0, 1, 2])
def test_a_command_refused_as_late_drops_its_burst(coil, clean):
    cmd = BURST2 + coil * 100_000 - 50_000            # when the firmware sends that coil's command
    b, fw = _run((cmd - 10_000, cmd + 86_000), "emulator")
    ref = b.driver.refusals
    assert len(ref) == 1 and ref[0]["coil"] == coil
    assert ref[0]["faults"] == COIL_FAULT_REFUSED | COIL_FAULT_LATE and ref[0]["lead_us"] < 0
    # reported as an event (coil << 8 | faults) ...
    ev = [m.detail for _, m in b.recorder.events if m.code == EVT_COIL_FAULT]
    assert ev == [(coil << 8) | COIL_FAULT_REFUSED | COIL_FAULT_LATE]
    # ... and no pose from that burst: the others are the clean run's, every one valid
    got = _poses(b)
    t_burst = [t for t, _ in clean if BURST2 <= t < BURST2 + 600_000]
    assert len(t_burst) == 1
    assert [t for t, _ in got] == [t for t, _ in clean if t not in t_burst]
    assert all(st & POSE_VALID and not st & POSE_COIL_FAULT for _, st in got)
    act = fw.pipeline.actuate.__self__
    assert act.dropped == 1 and fw.schedule.late_refusals == 1
    # the pulses of the dropped burst after the refused one were not commanded
    assert fw.schedule.pulses == 3 * 5 - (2 - coil)


@pytest.mark.parametrize("coil", [0, 1, 2])
def test_a_firmware_stall_commands_no_pulse_after_its_start(coil, clean):
    cmd = BURST2 + coil * 100_000 - 50_000
    b, fw = _run((cmd - 10_000, cmd + 86_000), "firmware")
    assert b.driver.refusals == []
    got = _poses(b)
    assert all(st & POSE_VALID and not st & POSE_COIL_FAULT for _, st in got)
    # the cycle's first pulse: that cycle skipped before it opened; a later one: its burst dropped
    assert fw.pipeline.actuate.__self__.dropped == (0 if coil == 0 else 1)
    assert len(got) == len(clean) - 1
    for t, _ in got:
        assert not BURST2 <= t < BURST2 + 600_000


def test_another_refusal_still_marks_the_pose():
    """A driver whose current limit is below the coils' 1.5 A refuses every pulse with
    REFUSED | OVER_CURRENT: no burst is dropped, every pose carries POSE_COIL_FAULT."""
    b, fw = _run(limits=DriverLimits(max_current_a=1.0))
    got = _poses(b)
    assert got and all(st & POSE_COIL_FAULT and not st & POSE_VALID for _, st in got)
    assert fw.pipeline.actuate.__self__.dropped == 0 and fw.schedule.late_refusals == 0
