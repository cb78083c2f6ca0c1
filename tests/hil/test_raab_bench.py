"""Raab's tracker in the firmware pipelines on the emulated pulsed-DC bench
(magpylib physics): selection by ``[pose] pose_solver``, the scenarios
``raab-acquire`` and ``helix-hemisphere``, and the allocation-free tick."""
import dataclasses

import numpy as np
import pytest

from coiltrack.firmware.config import ConfigError, FirmwareConfig, config_from_dict
from coiltrack.firmware.loop import Firmware
from coiltrack.firmware.pose.raab import RaabTracker
from coiltrack.firmware.pose.solver import PoseSolver
from coiltrack.tools import scenarios
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup, run_inproc


def test_pose_solver_key_selects_and_bad_values_are_refused():
    """The one factory builds the solver of ``pose.pose_solver`` for both the
    burst's solve and the fusion's re-solve; a bad value names its key.
    Catches a tracker that ignores the key or a validation that lets a typo
    through."""
    for name, kind in (("lm", PoseSolver), ("raab", RaabTracker)):
        cfg = config_from_dict({"pose": {"pose_solver": name}})
        fw = Firmware(cfg, inproc_pair()[0])
        assert isinstance(fw.tracker.solver, kind) and isinstance(fw.tracker.comp_solver, kind)
    for bad, key in (({"pose_solver": "kalman"}, "pose.pose_solver"), ({"raab_iterations": 0}, "pose.raab_iterations"),
                     ({"raab_refresh": 2.0}, "pose.raab_refresh"), ({"raab_correction": 1}, "pose.raab_correction"),
                     ({"raab_start_position": [0.1, 0.2]}, "pose.raab_start_position")):
        with pytest.raises(ConfigError) as ei:
            config_from_dict({"pose": bad})
        assert ei.value.key == key


def test_raab_acquire_converges_within_20_updates():
    """raab-acquire, seed 1, 15 s (25 bursts): from 90 deg and 50 % range
    error the estimate stays within 3 sigma of the truth (the bench's
    magpylib CRB) after at most 20 updates, on the right side, and after that
    its position RMS is within 1.3 times the bound. Catches an acquisition
    that stalls or ends on the mirror solution in the firmware's pipeline."""
    rep = run_inproc(scenarios.get("raab-acquire"), 1, 15.0)
    assert rep["pose_solver"] == "raab"
    assert rep["acquisition_updates"] is not None and rep["acquisition_updates"] <= 20
    assert rep["hemisphere_flips"] == 0
    assert rep["after_acquisition_position_rms_mm"] <= 1.3 * rep["after_acquisition_crlb_position_rms_mm"]


def test_helix_hemisphere_crosses_the_plane_without_a_flip():
    """helix-hemisphere, seed 1, 30 s: the sensor crosses x = 0 twice (at
    7.9 and 23.6 s); no magnetic estimate goes over to the mirror solution.
    Catches a tracker that applies the configured hemisphere after
    acquisition instead of continuity."""
    sc = scenarios.get("helix-hemisphere")
    world = sc.build_world(1, 30.0)
    xs = world.trajectory.position(np.arange(0, 30_000_001, 500_000))[:, 0]
    assert (xs < 0).any() and (xs > 0).any()
    rep = run_inproc(sc, 1, 30.0)
    assert rep["poses"] >= 45 and rep["hemisphere_flips"] == 0 and rep["mirrored_poses"] == 0


@pytest.mark.skipif(not available(), reason="numpy memory handler API not reachable")
def test_steady_tick_with_raab_allocates_nothing():
    """roetenberg-fusion with Raab's tracker for the burst solve and the
    motion-compensated re-solve: after a 5 s warm-up, 15 s of ticks allocate
    no numpy array (the counting allocator of tools.bench.alloc around every tick).
    Catches an array created per update or per correction."""
    sc = scenarios.get("roetenberg-fusion")
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 2, 21.0, emu_end)
    cfg = sc.firmware_config().with_(pose={"pose_solver": "raab"})
    fw = Firmware(cfg, fw_end)
    counter = NumpyAllocationCounter()
    counts = 0
    for t in range(0, 20_000_001, cfg.timing.tick_us):
        bench.emulator.step(t)
        before = counter.count
        with counter:
            fw.tick(t)
        if t >= 5_000_000:
            counts += counter.count - before
    assert counts == 0
    assert fw.status()["cycles"] >= 30 and fw.status().get("fusion_updates", 0) >= 20
