"""The start of a burst's fusion update on the compiled core (firmware_py/core/src/fuse.c:
ct_fuse_compensate, ct_fuse_predict, ct_fuse_solution; glue py_fuse.c ``FuseComp``) against its
Python reference (track/burst_fusion.py ``SensorInertial.fuse`` with ``_measure_step``,
``compensate_begin``, ``compensate_step``, ``on_solution``; the reference run on the Python core),
and the predicted signals against an independent reference (``pose.reference.measurement_model``).

Every stage, pulse index, charge, the ``waiting`` flag, the compensated signals, the re-solve's
begin and the burst's kept solution are compared with ``==`` (the same operations in the same order
on both cores). Seeded; skips where the extension is not built."""
import dataclasses

import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.estimate.magnetic_inertial import FS_INIT, FS_N
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.pose.solver import PoseSolver
from coiltrack.firmware.track.burst_fusion import _SOLVE, _UPDATE_MAG, FixedSource, PulseGate, SensorInertial

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
COMPILED = core.load("compiled")
STAGES = (SensorInertial.fuse, SensorInertial._measure_step, SensorInertial.on_solution,
          SensorInertial.compensate_begin, SensorInertial.compensate_step, SensorInertial._begin_solve)


def _spd(rng, n, scale):
    M = rng.normal(size=(n, n))
    return scale * (M @ M.T + n * np.eye(n))


class _Side:
    """One core's sensor, re-solving solver, burst solver and channel-like inputs."""

    def __init__(self, cfg, c, motion_compensation=True):
        if not motion_compensation:
            cfg = dataclasses.replace(cfg, fusion=dataclasses.replace(cfg.fusion, motion_compensation=False))
        coils = [Coil(k.center, k.axis, k.radius, k.turns) for k in cfg.source.coils]
        gate = PulseGate(np.zeros(3, dtype=np.int64), np.zeros(3, dtype=np.int64), 0, 0)
        self.ins = SensorInertial(1, cfg, gate, FixedSource(cfg), core=c)
        self.comp = PoseSolver(coils, gate_probability=1.0, core=c)
        self.solver = PoseSolver(coils, core=c)
        n = len(coils)
        self.n = n
        self.S = np.zeros((3, n))
        self.sigma = np.zeros((3, n))
        self.pulse_t = np.zeros(n, dtype=np.int64)
        self.currents = np.zeros(n)
        self.ins.bind_fuse(c, self.comp, self.solver, self.S, self.pulse_t, self.currents, (FS_INIT, FS_N), STAGES,
                           (_SOLVE, _UPDATE_MAG))
        self.filter_steps = 0

        def filter_step(replay_budget):        # (the update's own tests are test_core_fusion_update.py's)
            self.filter_steps += 1
            return False
        self.ins._filter_step = filter_step

    def state(self):
        ins = self.ins
        return (ins.stage, ins._comp_j, ins.comp_ok, ins.compensated, ins.waiting, ins.pending,
                self.comp.signal.evals, self.comp.status, self.filter_steps, ins.S_comp.tobytes(),
                ins.mag_position.tobytes(), ins.mag_rotation.tobytes(), ins.mag_cov.tobytes(),
                self.comp._fit.p.tobytes(), self.comp._fit.R.tobytes())


def _pair(motion_compensation=True):
    ref = _Side(FirmwareConfig(), core.PYTHON, motion_compensation)
    got = _Side(FirmwareConfig(), COMPILED, motion_compensation)
    assert ref.ins.fuse.__func__ is SensorInertial.fuse
    assert got.ins.fuse.__func__ is not SensorInertial.fuse and got.ins.on_solution.__func__ is not SensorInertial.on_solution
    return ref, got


def _burst(sides, rng, trial):
    """One random burst and history (the same on both sides): its magnetic-only solution, the
    live history the compensation reads, the signals, currents and pulse times."""
    ref = sides[0]
    n = ref.n
    p = np.array([0.25, -0.1, 0.2]) + rng.normal(size=3) * 0.05
    ang = rng.normal(size=3) * 0.5
    Rm = _rot(ang)
    P = _spd(rng, ref.ins.fusion.n, 1e-5 if trial % 7 else 1e-1)      # every 7th: a velocity too uncertain
    t = np.cumsum(rng.integers(900, 1100, size=40)) + 10_000
    rows = rng.normal(size=(40, 12)) * (0.0 if trial == 5 else 0.01)
    rows[:, 0:3] += p
    rows[:, 3:12] += Rm.reshape(9)
    cov = _spd(rng, 6, 1e-6)
    currents = rng.uniform(0.5, 2.0, size=n) * np.sign(rng.normal(size=n))
    sigma = rng.uniform(1e-9, 3e-9, size=(3, n))
    t_ref = int(t[20]) + 17 if trial % 13 != 4 else int(t[-1]) + 5      # every 13th: beyond the history
    pulse_t = [int(t[5]) + 3, int(t[20]), int(t[33]) + 400 if trial % 9 != 2 else int(t[0]) - 50]
    for s in sides:
        ins = s.ins
        np.copyto(ins.fusion.st.P, P)
        ins.fusion.initialized = trial % 11 != 3
        live = ins.fusion.history.live
        live.clear()
        for k in range(40):
            live.d[live.push(int(t[k]))] = rows[k]
        ins.t_ref = t_ref
        s.pulse_t[:] = pulse_t[:n]
        s.currents[:] = currents
        s.sigma[:] = sigma
        # the burst's solve: its results, then the signals as the model gives them there
        np.copyto(s.solver.position, p)
        np.copyto(s.solver.rotation, Rm)
        np.copyto(s.solver.covariance, cov)
    from coiltrack.firmware.pose import reference
    coils = [Coil(k.center, k.axis, k.radius, k.turns) for k in FirmwareConfig().source.coils]
    ref.S[:] = reference.measurement_model(p, Rm, coils, currents) + rng.normal(size=ref.S.shape) * 2e-9
    for s in sides[1:]:
        np.copyto(s.S, ref.S)


def _rot(v):
    from coiltrack.firmware.linalg import exp_rotvec
    R = np.zeros((3, 3))
    exp_rotvec(v[0], v[1], v[2], R)
    return R


@pytest.mark.parametrize("motion_compensation", [True, False])
def test_fuse_start_matches_the_reference(motion_compensation):
    """``fuse`` called tick after tick at random budgets (below ``n``: no room, the ``waiting``
    flag; between ``n`` and two bursts' pulses) from the burst's solution to the filter's stage:
    after every call the same stage, next pulse, charges, flags, compensated signals and re-solve
    start on both cores; over the trials every outcome of the compensation occurs (done, the history
    missing a pulse's time, not initialised, too uncertain a velocity, t_ref beyond the history)."""
    sides = _pair(motion_compensation)
    ref, got = sides
    rng = np.random.default_rng(30)
    n = ref.n
    outcomes = set()
    for trial in range(60):
        _burst(sides, rng, trial)
        solved = trial % 17 != 6                      # every 17th: the burst was not solved
        for s in sides:
            s.ins.on_solution(s.solver, solved)
            s.ins.pending = True                      # (the tracker offers a pending sensor only)
        assert ref.state() == got.state(), trial
        if not solved:
            continue
        seen_pulses = False
        for tick in range(12):
            budget = int(rng.integers(0, 4 * n + 2))
            fresh = bool(rng.integers(0, 2))
            r = [s.ins.fuse(s.comp, s.S, s.currents, s.sigma, memoryview(s.pulse_t), budget, 8, fresh)
                 for s in sides]
            assert r[0] == r[1], (trial, tick)
            assert ref.state() == got.state(), (trial, tick, budget)
            seen_pulses |= ref.ins.stage == 1
            if ref.ins.stage not in (0, 1, 2):
                break
        outcomes.add((ref.ins.stage, ref.ins._comp_j == n, seen_pulses))
    if motion_compensation:
        assert (2, True, True) in outcomes or (3, True, True) in outcomes        # compensated and re-solved
        assert any(o[0] == 5 and o[2] for o in outcomes)                         # a pulse outside the history
        assert any(o[0] == 5 and not o[2] for o in outcomes)                     # no compensation at all
    else:
        assert {o[0] for o in outcomes} == {5}


def test_predicted_signals_match_the_independent_model():
    """``ct_fuse_predict`` (the compensation's predictions, through the re-solving solver's model)
    against ``pose.reference.measurement_model`` at random poses and currents, to 1e-12 relative."""
    from coiltrack.firmware.pose import reference
    cfg = FirmwareConfig()
    ref, got = _pair()
    rng = np.random.default_rng(8)
    coils = [Coil(k.center, k.axis, k.radius, k.turns) for k in cfg.source.coils]
    for trial in range(30):
        _burst((ref, got), rng, 1)
        p = np.array([0.2, 0.1, 0.15]) + rng.normal(size=3) * 0.1
        R = _rot(rng.normal(size=3))
        cur = got.currents
        out = np.zeros((3, got.n))
        got.comp.predict_signals(p, R, cur, out)
        want = reference.measurement_model(p, R, coils, cur)
        scale = np.abs(want).max()
        assert np.abs(out - want).max() <= 1e-12 * scale, trial


def test_the_solution_copies_and_a_solver_of_another_kind():
    """``on_solution`` (compiled: ``ct_fuse_solution``) keeps the solver's results and resets the
    stage as the reference does; a solver it is not bound to takes the reference's copies; and
    ``fuse`` with another solver runs the reference."""
    ref, got = _pair()
    rng = np.random.default_rng(3)
    _burst((ref, got), rng, 1)
    for s in (ref, got):
        s.ins.stage = 4
        s.ins.on_solution(s.solver, True)
    assert ref.state() == got.state()
    other = PoseSolver([Coil(k.center, k.axis, k.radius, k.turns) for k in FirmwareConfig().source.coils],
                       core=COMPILED)
    np.copyto(other.position, [0.3, 0.0, 0.1])
    got.ins.on_solution(other, True)
    assert np.array_equal(got.ins.mag_position, other.position) and got.ins.pending
    got.ins.on_solution(other, False)
    assert not got.ins.pending
    e = got.comp.signal.evals
    got.ins.on_solution(got.solver, True)
    got.ins.fuse(other, got.S, got.currents, got.sigma, memoryview(got.pulse_t), 9, 8, False)
    assert other.signal.evals > 0 and got.comp.signal.evals == e
