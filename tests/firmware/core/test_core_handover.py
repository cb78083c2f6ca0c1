"""The hand-over of bursts on the compiled core (firmware_py/core/src/begin.c ``ct_handover_status``,
``ct_handover_ahead``; py_begin.c ``HandOver``; ``MagneticTracker._begin_handover``) against the
Python references: ``MagneticTracker._begin`` (``SensorChannel.burst_flags``, ``PulseSchedule.any_faults``,
``input_status``, ``Supervisor.pose_status``) and ``MagneticTracker._start_solve`` (``fill_sigma``,
``warm_start``, ``_use_ahead``).

Two multi16 firmwares built alike are given the same seeded random state (test_core_ahead_start.py's):
every sensor's solve ahead of the burst finished on the same inputs, or on inputs one element apart,
or of another burst, or still running, tracked poses had or not, windows flagged (too few samples,
saturated, a drift), coil faults, a budget of 27 (up to nine hand-overs in one call). One begins the
first sensor's burst through ``HandOver``, the other through the references; the chain of hand-overs
that follows writes the same bits (the sigmas, warm starts, the solves ahead's records, the solver,
the quality's rows), the same counters (taken over, missed, vetoed, poses sent), the same status and
the same POSE frames. A channel's flags read for another's, a veto or an unusable burst let through,
a take-over of another burst's solve, a record not released or released when no warm start was made,
other inputs taken for the same, or a status bit dropped changes a frame or a counter here. Seeded;
skipped without the extension."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

from coiltrack.firmware.measure.pulse import PULSE_BASELINE_DRIFT, PULSE_SATURATED, PULSE_TOO_FEW  # noqa: E402
from coiltrack.firmware.track.magnetic import MagneticTracker  # noqa: E402
from coiltrack.firmware.loop import Firmware  # noqa: E402
from coiltrack.tools import scenarios  # noqa: E402

_spec = importlib.util.spec_from_file_location("_ahead_states", Path(__file__).with_name("test_core_ahead_start.py"))
_states = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_states)          # its seeded states and comparisons
_Port, _ahead_of, _arrays, _scalars, _state = (_states._Port, _states._ahead_of, _states._arrays, _states._scalars,
                                               _states._state)

BURST = 123_456


def _pair():
    cfg = scenarios.get("multi16").firmware_config().with_(core={"impl": "compiled"},
                                                         budget={"handovers_per_tick": 16}).validate()
    got, ref = Firmware(cfg, _Port()), Firmware(cfg, _Port())
    assert got.tracker._begin.__func__ is MagneticTracker._begin_handover
    assert got.tracker._ho_begin.__self__.__class__.__name__ == "HandOver"      # bound when composed
    del ref.tracker._begin                    # the references: _begin, the supervisor's pose_status,
    del ref.supervisor.pose_status            # _start_solve (through _take_ahead without AheadStart)
    ref.tracker._as_inputs = None
    return got, ref


def _setup(fw, seed: int) -> None:
    """Seeded: the state, each sensor's solve ahead and its windows' flags, the coils' faults."""
    _state(fw, seed)
    rng = np.random.default_rng(seed + 7)
    tr = fw.tracker
    tr.schedule.burst_start = BURST
    tr._ahead_k = -1
    tr.budget = 27
    running = int(rng.integers(0, 16)) if rng.random() < 0.3 else -1
    for k, ch in enumerate(tr.channels):
        u = rng.random()
        change = int(rng.integers(0, 6)) if u < 0.15 else -1
        _ahead_of(fw, k, BURST if u < 0.92 else BURST + 1, change, k == running)
        ch.flags[:] = 0
        f = rng.random()
        if f < 0.04:
            ch.flags[int(rng.integers(0, ch.flags.size))] = PULSE_SATURATED
        elif f < 0.08:
            ch.flags[int(rng.integers(0, ch.flags.size))] = PULSE_TOO_FEW
        elif f < 0.2:
            ch.flags[int(rng.integers(0, ch.flags.size))] = PULSE_BASELINE_DRIFT
    h = fw.supervisor.health
    for node in (ch.node for ch in tr.channels):    # some sensors' fields distorted, clocks suspect
        i = h._slot[node]
        h.distorted[i] = int(rng.random() < 0.1)
        h.suspect_open[i] = int(rng.random() < 0.05)
    seen = h.status_seen                             # the coils' status heard (else every pose vetoed)
    for j in range(tr.schedule.n):
        seen[j] = 1
    if rng.random() < 0.08:
        seen[int(rng.integers(0, tr.schedule.n))] = 0
    tr.schedule.faults[:] = 0
    if rng.random() < 0.1:
        tr.schedule.faults[int(rng.integers(0, tr.schedule.n))] = 1 << int(rng.integers(0, 4))
    tr._next, tr._units, tr._handover, tr._handovers = 0, 0, False, 0
    fw.port.out.clear()


def _counts(fw) -> tuple:
    sup, tx, q = fw.supervisor, fw.tx, fw.tracker.quality
    return (sup.veto, sup.poses_vetoed, tx.poses, tx.tx_errors, tx._seq, tuple(q.last.values())
            if isinstance(q.last, dict) else tuple(q.last), fw.tracker.solve_evals_max, fw.tracker.cycles)


def _same(got, ref) -> None:
    a, b = _arrays(got), _arrays(ref)
    bad = [k for k in a if a[k] != b[k]]
    assert not bad, bad
    assert _scalars(got) == _scalars(ref)
    assert _counts(got) == _counts(ref)
    assert got.port.out == ref.port.out


def test_the_hand_overs_equal_the_references():
    """120 random states, each a chain of up to nine hand-overs from the first sensor: the same
    bits, counters and frames after it, and after the solve it left running is stepped out."""
    got, ref = _pair()
    for seed in range(120):
        for fw in (got, ref):
            _setup(fw, 5000 + seed)
        _same(got, ref)
        got.tracker._begin(got.tracker.channels[0])
        ref.tracker._begin(ref.tracker.channels[0])
        _same(got, ref)
        for fw in (got, ref):
            while fw.tracker.solver.next_unit is not None:
                fw.tracker.solver.step(100)
        _same(got, ref)
    tr = got.tracker
    assert tr.ahead_used > 120 and tr.ahead_missed > 20 and got.supervisor.poses_vetoed > 40
    assert got.tx.poses > 120 and tr.out_of_range > 5


def test_a_model_with_a_distortion_map_takes_the_reference(monkeypatch):
    """With a distortion map the hand-over is _begin_compiled's (which gives it to the Python)."""
    got, _ = _pair()
    tr = got.tracker
    calls = []
    _setup(got, 1)
    monkeypatch.setattr(tr.solver.signal, "distortion", object(), raising=False)
    monkeypatch.setattr(tr, "_begin_compiled", lambda ch: calls.append(ch))
    tr._begin(tr.channels[0])
    assert calls == [tr.channels[0]]


def test_without_the_supervisors_kernel_the_hand_over_is_the_reference(monkeypatch):
    """A supervisor whose pose status is not compiled (no ``pose_kernel``) when the firmware is
    composed: no kernel is bound and every begin is ``_begin_compiled``'s, the same bits and frames."""
    from coiltrack.firmware.supervise.supervisor import Supervisor
    from coiltrack.firmware.track import magnetic
    cfg = scenarios.get("multi16").firmware_config().with_(core={"impl": "compiled"}).validate()
    ref = Firmware(cfg, _Port())
    monkeypatch.setattr(Supervisor, "pose_kernel", lambda self: None)
    got = Firmware(cfg, _Port())
    assert got.tracker._begin.__func__ is MagneticTracker._begin_handover
    assert got.tracker._ho_begin is magnetic._ho_reference
    ref.tracker._begin = ref.tracker._begin_compiled
    for seed in range(12):
        for fw in (got, ref):
            _setup(fw, 7000 + seed)
        got.tracker._begin(got.tracker.channels[0])
        ref.tracker._begin(ref.tracker.channels[0])
        _same(got, ref)
    assert got.tracker.ahead_used > 5
