"""Hand-overs per tick (``[budget] handovers_per_tick``, track.magnetic).

``multi16`` (sixteen sensors solved ahead, one burst serves them all) on the virtual clock: at the
default budget of 27 field evaluations a hand-over is charged ``n`` = 3, so up to nine sensors'
POSEs and begins would land in the tick a burst completes. With the cap each tick begins at most
``handovers_per_tick`` sensors' solves and the rest wait for the next tick; the solutions are the
same bit for bit, only sent later.
"""
import numpy as np
import pytest

from coiltrack.firmware.config import ConfigError, FirmwareConfig
from coiltrack.firmware.loop import Firmware
from coiltrack.tools import scenarios
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup


def _run(cap: int, seconds: float = 3.0):
    """Per tick the hand-overs begun; per magnetic solution ``(tick, node, position, rotation)``."""
    sc = scenarios.get("multi16")
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, seconds + 1.0, emu_end)
    cfg = sc.firmware_config().with_(budget={"handovers_per_tick": cap}).validate()
    fw = Firmware(cfg, fw_end)
    tr = fw.tracker
    sols, per_tick, now = [], [], [0]
    real = tr._report

    def report(ch, solved):
        if solved:
            sols.append((now[0], ch.node, tr.solver.position.copy(), tr.solver.rotation.copy()))
        real(ch, solved)

    tr._report = report
    t = 0
    while t < seconds * 1e6:
        bench.emulator.step(t)
        now[0] = t
        fw.tick(t)
        per_tick.append(tr._handovers)
        t += cfg.timing.tick_us
    return cfg, np.array(per_tick), sols


def test_the_cap_delays_hand_overs_without_changing_the_solutions():
    """Catches the cap not applied (more than 4 begun in a tick), a cap that drops a sensor (fewer
    solutions) or changes a solve's inputs (not the same bit for bit), and a count not reset per
    tick (the capped run would stall: fewer solutions). Without the cap (16) the tick a burst
    completes begins 9 sensors here (27 / 3)."""
    cfg, capped, c_sols = _run(4)
    _, free, f_sols = _run(16)
    assert cfg.budget.track_budget_evals == 27
    assert capped.max() == 4 and free.max() >= 8
    assert len(c_sols) == len(f_sols) >= 64
    for (t, node, p, R), (t0, node0, p0, R0) in zip(c_sols, f_sols):
        assert node == node0 and t >= t0
        assert np.array_equal(p, p0) and np.array_equal(R, R0)
    assert any(t > t0 for (t, *_), (t0, *_) in zip(c_sols, f_sols))


@pytest.mark.parametrize("value", [0, -1, 1.5, True, "4"])
def test_bad_cap_is_refused_naming_the_key(value):
    with pytest.raises(ConfigError) as e:
        FirmwareConfig().with_(budget={"handovers_per_tick": value}).validate()
    assert "handovers_per_tick" in str(e.value)
