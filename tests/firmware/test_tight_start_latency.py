"""The solve's latency reaches the tight tracker's estimate through the EKF's start only
(``track.tight_fusion``: ``TightFusionTracker.on_solution``, ``_TightSensor.start``).

The tight tracker's window updates, quiet-field updates and IMU steps run in the ticks the
windows close and the samples arrive, whatever the burst solver does; the burst's solution is
used once, to start the EKF (and again after a lost track), in the tick it is reported: the pose
at the burst's middle carried to the EKF's time then, widened by the lag. ``roetenberg-flexion-back``
seed 1 reports its first solution in the tick its burst completes at a budget of 27 field
evaluations (505 ms, the EKF at 495.394 ms), two ticks later at 9 (507 ms, the EKF one IMU step
further, 503.726 ms): the two starts differ and so does everything after. Held to the same
tick, they do not.
"""
import numpy as np
import pytest

from coiltrack.firmware.loop import Firmware
from coiltrack.tools import scenarios
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup


def _firmware(name: str, seconds: float, budget: int, impl: str):
    sc = scenarios.get(name)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, seconds + 1.0, emu_end)
    cfg = sc.firmware_config().with_keys(track_budget_evals=budget).with_(core={"impl": impl}).validate()
    return bench, Firmware(cfg, fw_end), cfg


def _state(tr):
    out = []
    for s in tr._sens:
        e = s.ekf
        out.append((e.initialized, s.updates, s.gated, s.quiet_updates, s.starts,
                    (e.p.copy(), e.R.copy(), e.P.copy()) if e.initialized else None))
    return out


def _same(x, y) -> bool:
    return all(a[:5] == b[:5] and (a[5] is None or all(np.array_equal(u, v) for u, v in zip(a[5], b[5])))
               for a, b in zip(x, y))


@pytest.mark.parametrize("impl", ["compiled", "python"])
def test_a_start_held_to_the_same_tick_leaves_the_tight_estimate_independent_of_the_budget(impl):
    """``roetenberg-flexion-back`` seed 1, 2 s, budgets 9 and 27 side by side on the virtual
    clock, the 27 run's first solution held back from the tracker until the 9 run's EKF has
    started: every tick, both EKFs (position, orientation, covariance, the update counters) are
    bit-identical, and the 27 run did report its solution earlier (its start was held). Catches
    any other channel from the solve's timing into the fused state: a window update or an IMU
    step skipped or put off while a solve runs, a quiet-field update gated by the solver's
    state, the solution used beyond the start. On either core (the Python where the extension
    is not built runs twice)."""
    slow_bench, slow, cfg = _firmware("roetenberg-flexion-back", 2.0, 9, impl)
    fast_bench, fast, _ = _firmware("roetenberg-flexion-back", 2.0, 27, impl)
    tr_slow, tr_fast = slow.tracker, fast.tracker
    held = []
    reported = {}
    real = tr_fast.on_solution
    now = [0]

    def on_solution(ch, solved):
        reported.setdefault("fast", now[0])
        if solved and not tr_fast.sensors[ch.node].ekf.initialized \
                and not tr_slow.sensors[ch.node].ekf.initialized:
            held.append((ch, solved))
            return
        real(ch, solved)

    tr_fast.on_solution = on_solution
    compared = 0
    t = 0
    while t < 2e6:
        now[0] = t
        slow_bench.emulator.step(t)
        slow.tick(t)
        fast_bench.emulator.step(t)
        fast.tick(t)
        if held and all(s.ekf.initialized for s in tr_slow._sens):
            reported.setdefault("slow", t)
            for ch, solved in held:
                real(ch, solved)
            held.clear()
        a, b = _state(tr_slow), _state(tr_fast)
        assert _same(a, b), t
        compared += a[0][0]
        t += cfg.timing.tick_us
    assert reported["fast"] < reported["slow"]          # the budgets did report at different ticks
    assert compared > 1000                              # ticks with the EKFs running
