"""The fusing trackers' solve ticks in fewer Python frames (``track/solve_tick.py`` ``SolveTick``,
``track/ac.py`` ``ACFusionTracker._bind_ac_tick``): on the compiled core, a tracker with its
bound forms against one whose bound forms are taken away again (the reference's methods on the
same kernels), driven in lockstep by two benches of the same seed: after every tick the same
bytes sent, the same warm starts, the same solver state and evaluation counts, the same charges.
"""
import numpy as np
import pytest

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

#: the tracker's attributes the compiled binding puts on the instance (the twins, bound at composition)
_BOUND = ("step", "_charges", "_step_solving", "_start_solve")


def _firmware(name: str, seconds: float, budget: dict):
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools import scenarios
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.bench.runner import BenchSetup

    sc = scenarios.get(name)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, seconds + 1.0, emu_end)
    cfg = sc.firmware_config().with_(budget=budget).validate()
    fw = Firmware(cfg, fw_end)
    sent = []
    write = fw_end.write

    def record(data):
        sent.append(bytes(data))
        write(data)

    fw_end.write = record
    return bench, fw, sent, cfg.timing.tick_us


def _reference(fw) -> None:
    """Take the tracker's bound forms away: the class's (reference) methods run again (the loop's
    track stage too, which holds the tracker's ``step`` as composed)."""
    tr = fw.tracker
    track = fw.pipeline.track
    for k in _BOUND:
        tr.__dict__.pop(k, None)
    fw.stages = tuple(tr.step if s == track else s for s in fw.stages)


def _lockstep(name: str, seconds: float, bound: dict) -> tuple[int, int]:
    """Run ``name`` twice in lockstep, the second tracker on the reference's methods, the tick's other
    work charged (``[budget] window_evals``, ``imu_sample_evals``: 0 by default); compare after
    every tick. ``bound``: attribute -> the function the first tracker must have bound. Returns the
    ticks that solved (or re-solved, compensated) and the frames sent."""
    budget = {"window_evals": 4, "imu_sample_evals": 5}
    a, b = _firmware(name, seconds, budget), _firmware(name, seconds, budget)
    ta, tb = a[1].tracker, b[1].tracker
    for k, fn in bound.items():
        assert getattr(getattr(ta, k), "__func__", None) is fn, k
    _reference(b[1])
    solved = 0
    t = 0
    while t < seconds * 1e6:
        for bench, fw, _, _ in (a, b):
            bench.emulator.step(t)
        e = ta.solver.signal.evals + ta.comp_solver.signal.evals
        for _, fw, _, _ in (a, b):
            fw.tick(t)
        assert a[2] == b[2], t
        assert ta.solver.signal.evals == tb.solver.signal.evals and ta.comp_solver.signal.evals == \
            tb.comp_solver.signal.evals, t
        assert (ta._units, ta._charged, ta._waited, ta._next, ta._n_pending, ta._imu_last) == \
            (tb._units, tb._charged, tb._waited, tb._next, tb._n_pending, tb._imu_last), t
        assert ta.solver.status == tb.solver.status and ta.solver.next_cost == tb.solver.next_cost, t
        assert np.array_equal(ta.solver.position, tb.solver.position), t
        for node, tp in ta.poses.items():
            assert np.array_equal(tp.warm_p, tb.poses[node].warm_p), t
            assert np.array_equal(tp.warm_R, tb.poses[node].warm_R), t
        solved += ta.solver.signal.evals + ta.comp_solver.signal.evals != e
        t += a[3]
    return solved, len(a[2])


def test_fused_solve_ticks_match_the_reference_methods():
    """roetenberg-fusion, 2 s (bursts solved, fused, compensated): the bound solve tick
    (``SolveTick._step_solve_compiled``, the charges in one frame, the fused sensor's poses sent
    through its kernel) against ``BurstFusionTracker``'s methods. Catches a part of the tick's charges
    left out of the bound ones (the windows closed: the solve steps and hand-overs then take other
    ticks), and any other step of the tick that changes what is sent, solved or charged."""
    from coiltrack.firmware.track.burst_fusion import BurstFusionTracker
    from coiltrack.firmware.track.solve_tick import SolveTick

    solved, frames = _lockstep("roetenberg-fusion", 2.0, {"step": BurstFusionTracker._step_fast,
                                                          "_charges": SolveTick._charges_fused,
                                                          "_step_solving": SolveTick._step_solve_compiled})
    assert solved >= 3 and frames > 200


def test_ac_solve_ticks_match_the_reference_methods():
    """raab-ac, 0.8 s (an AC block solved every 9 ms, fused): the bound AC tick
    (``ACFusionTracker._step_compiled``: the sensors' samples in one ``FusedTick`` call, the charges
    in one frame) and the solve's start in one call (``SolveStart`` with the AC tracker's warm start,
    ``warm_ac``) against the reference's ``step``, ``_start_solve`` (``SensorChannel.fill_sigma``,
    ``ACFusionTracker.warm_start``, ``PoseSolver.begin``). Catches the filter's pose taken at the
    sensor's own burst instant (``tr``) instead of the block's ``t_ref``, and the IMU samples left
    out of the charges (the solve then runs in other ticks)."""
    from coiltrack.firmware.track.ac import ACFusionTracker
    from coiltrack.firmware.track.magnetic import MagneticTracker
    from coiltrack.firmware.track.solve_tick import SolveTick

    solved, frames = _lockstep("raab-ac", 0.8, {"step": ACFusionTracker._step_compiled,
                                                "_charges": SolveTick._charges_imu,
                                                "_start_solve": MagneticTracker._start_solve_compiled})
    assert solved > 40 and frames > 400
