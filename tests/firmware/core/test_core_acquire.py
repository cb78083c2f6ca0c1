"""The compiled acquisition (firmware_py/core/src/acquire.c, py_acquire.c; run inside solve.c's
ct_solve_run) against its Python reference (pose/acquire.py Acquisition with _Kuipers, run by
pose/solver.py PoseSolver._start_acquisition and _unit_acquire).

The C does the same floating-point operations in the same order (-ffp-contract=off; the Cholesky
inverse through ekf.c's ct_spd_inverse, whose only difference from linalg.chol_inverse, -(x)
for 0.0 - x, can change no more than the sign of a zero that the next sum takes away), so the
comparisons are bit for bit: the units run one by one and their sequence, the field evaluations
each unit does, ok, p and R, on seeded random poses near the source (the exact model: the
invariant fit and the grid run), far from it (Kuipers' start is final), with no hemisphere
(h = 0), with moments that do not span 3-D (no start), on a coil's axis; and whole solves on
either core with the acquisition in the compiled run. Seeded; skips without the extension."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.pose.solver import SOLVE_NO_START, SOLVE_REACQUIRED, SOLVE_RUNNING, PoseSolver

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

from .test_core_solve import ORTHO, SKEWED, _signals  # noqa: E402  (the solve's tests' sources and signals)

COMPILED = core.load("compiled")
EXT = COMPILED.ext
#: three coils whose axes lie in one plane: M M^T is singular, no start
FLAT = [Coil([0, 0, 0], [1, 0, 0], 0.05, 40), Coil([0, 0, 0], [0, 1, 0], 0.05, 40),
        Coil([0, 0, 0], [1, 1, 0], 0.05, 40)]
#: Acquisition's units and the compiled unit codes (include/ct_acquire.h CT_AQ_*)
UNITS = {None: 0, "_unit_moments": 1, "_unit_kuipers_position": 2, "_unit_kuipers_rotation": 3,
         "_unit_refine_start": 4, "_unit_refine_step": 5, "_unit_radius": 6, "_unit_misfit": 7, "_unit_orient": 8}


def _pair(coils, model="exact"):
    return PoseSolver(coils, model, core=core.PYTHON), PoseSolver(coils, model, core=COMPILED)


def _units(ref, got, S, cur, sigma, h):
    """Both acquisitions run unit by unit on the same inputs: the Python's units (as codes) with
    the evaluations of each, and the compiled ones; the compiled start and ok."""
    assert ref._load(S, cur, sigma) and got._load(S, cur, sigma)
    acq, run, st, n = ref._acq, got._aqrun, got._aqst, ref.n
    acq.begin(h[0], h[1], h[2], ref._sigma_rms)
    run.begin(h[0], h[1], h[2], got._sigma_rms)
    seq_ref, seq_got = [], []
    while not acq.finished:
        e0 = ref.signal.evals
        acq.next_unit()
        seq_ref.append((UNITS[getattr(acq.next_unit, "__name__", None)], (ref.signal.evals - e0) // n))
        assert acq.next_unit is None or acq.next_cost == n
    while True:
        e0 = st[EXT.ACQUIRE_EVALS]
        u = run.unit()
        seq_got.append((u, int(st[EXT.ACQUIRE_EVALS] - e0)))
        if u == 0:
            break
        assert len(seq_got) < 5000
    return seq_ref, seq_got, acq.ok, st[EXT.ACQUIRE_OK] != 0.0


def _check(ref, got, S, cur, sigma, h, case):
    seq_ref, seq_got, ok_ref, ok_got = _units(ref, got, S, cur, sigma, h)
    assert seq_got == seq_ref, case
    assert ok_got == ok_ref, case
    if ok_ref:
        np.testing.assert_array_equal(got._aqp, ref._acq.p, err_msg=str(case))
        np.testing.assert_array_equal(got._aqR, ref._acq.R.reshape(-1), err_msg=str(case))
    return {u for u, _ in seq_ref}


@pytest.mark.parametrize("coils", [ORTHO, SKEWED])
def test_near_and_far_starts_unit_by_unit(coils):
    """Seeded poses near the source (exact model: the invariant fit runs, and where it misses its
    noise level the grid, its candidates refined) and far from it (Kuipers' start is final), with a
    hemisphere on the pose's side, on the other side and none (h = 0: every direction of the
    grid); a dipole model (no refinement): every unit and its evaluations, ok, p and R the
    reference's to the bit, and the grid reached by some near case."""
    rng = np.random.default_rng(40)
    n = len(coils)
    ref, got = _pair(coils)
    seen = set()
    for k in range(10):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        p = u * (rng.uniform(0.07, 0.16) if k < 7 else rng.uniform(0.5, 0.9))
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        cur = rng.uniform(0.5, 2.0, n)
        noise = 1e-9 if k % 2 else 3e-8
        S = _signals(coils, p, R, cur, rng, noise)
        sigma = np.full((3, n), noise)
        h = (u, -u, np.zeros(3))[k % 3]
        seen |= _check(ref, got, S, cur, sigma, h, (k, "exact"))
    assert {4, 5, 6, 7, 8} <= seen           # the invariant fit, the grid and the orientation ran
    dref, dgot = _pair(coils, "dipole")
    p = np.array([0.3, -0.2, 0.25])
    S = _signals(coils, p, np.eye(3), np.ones(n), rng, 1e-9, "dipole")
    assert _check(dref, dgot, S, np.ones(n), np.full((3, n), 1e-9), p, "dipole") == {0, 2, 3}


def test_no_start_and_a_sensor_on_a_coil_axis():
    """Moments in one plane (and a two-coil source): no start (ok False after the first unit); a
    sensor on the x coil's axis near and far (U's eigenvectors degenerate, the hemisphere's sign
    decides): the reference's units, ok, p and R."""
    rng = np.random.default_rng(41)
    for coils in (FLAT, ORTHO[:2]):
        ref, got = _pair(coils)
        n = len(coils)
        S = _signals(coils, np.array([0.2, 0.1, 0.1]), np.eye(3), np.ones(n), rng, 1e-9)
        seq_ref, seq_got, ok_ref, ok_got = _units(ref, got, S, np.ones(n), np.full((3, n), 1e-9), (1.0, 0.0, 0.0))
        assert seq_got == seq_ref == [(0, 0)] and not ok_ref and not ok_got
    ref, got = _pair(ORTHO)
    for r in (0.08, 0.12, 0.7):
        p = np.array([r, 0.0, 0.0])
        S = _signals(ORTHO, p, Rotation.from_rotvec([0.3, 0.2, -0.4]).as_matrix(), np.ones(3), rng, 0.0)
        for h in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 0.0)):
            _check(ref, got, S, np.ones(3), np.full((3, 3), 1e-10), h, (r, h))


def _trace(s, args, budget):
    st = s.begin(*args)
    out = [st]
    while st == SOLVE_RUNNING:
        st = s.step(budget)
        out.append((st, s.evals_last_step, s.units_last, s.signal.evals))
    return out


def test_solves_run_the_acquisition_in_the_compiled_run(monkeypatch):
    """Cold solves near the source, warm ones that fail their checks (the acquisition begun inside
    the run) and no start (the status alone, the last solve's iterations kept): every step's
    status, evaluations and charges and the results the reference's at budgets of 3, 9 and 27,
    and the Python's acquisition never run on the compiled core."""
    rng = np.random.default_rng(42)
    ref, got = _pair(SKEWED)
    monkeypatch.setattr(got._acq, "begin", None)             # the compiled run must not call it
    n = len(SKEWED)
    sigma = np.full((3, n), 2e-9)
    statuses = set()
    for k in range(6):
        u = rng.normal(size=3)
        p = u / np.linalg.norm(u) * rng.uniform(0.08, 0.3)
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        cur = rng.uniform(0.5, 2.0, n)
        S = _signals(SKEWED, p, R, cur, rng, 2e-9)
        hemi = p / np.linalg.norm(p)
        far = (p + rng.normal(0.0, 0.2, 3), R @ Rotation.from_rotvec(rng.normal(0.0, 1.0, 3)).as_matrix())
        for args in ((S, cur, sigma, hemi), (S, cur, sigma, None), (S, cur, sigma, -hemi, *far)):
            budget = (3, 9, 27)[k % 3]
            assert _trace(got, args, budget) == _trace(ref, args, budget), (k, len(args))
            np.testing.assert_array_equal(got.position, ref.position)
            np.testing.assert_array_equal(got.rotation, ref.rotation)
            np.testing.assert_array_equal(got.covariance, ref.covariance)
            assert (got.iterations, got.cost, got.converged, got.status, got.solve_evals) == \
                (ref.iterations, ref.cost, ref.converged, ref.status, ref.solve_evals)
            statuses.add(ref.status)
    assert any(s & SOLVE_REACQUIRED for s in statuses)
    fref, fgot = _pair(FLAT)
    S = _signals(FLAT, np.array([0.2, 0.1, 0.1]), np.eye(3), np.ones(3), rng, 1e-9)
    for s in (fref, fgot):
        s.iterations, s.cost = 7, 1.5                     # a previous solve's, kept by no start
    for args in ((S, np.ones(3), np.full((3, 3), 1e-9)),
                 (S, np.ones(3), np.full((3, 3), 1e-9), None, np.array([0.3, 0.0, 0.0]), np.eye(3))):
        assert _trace(fgot, args, 9) == _trace(fref, args, 9)
        assert fgot.status == fref.status and fgot.status & SOLVE_NO_START
        assert (fgot.iterations, fgot.cost, fgot.converged) == (fref.iterations, fref.cost, fref.converged)
