"""The compiled pulse-window extraction and the pose solve's compiled bookkeeping
(firmware_py/core/src/window.c, py_window.c) against their Python references
(measure/pulse.py PulseExtractor.extract; pose/solver.py PoseSolver's _load, _load_x0, _publish
and staged.run_units over the LM's steps).

The C does the same floating-point operations in the same order, compiled with -ffp-contract=off,
so every comparison with the reference is bit for bit: amplitude, variance, flags, counts, the
used sample times and the empirical variance of each window; position, rotation, covariance,
iterations, status and the field evaluations of every budgeted step of a solve. The extraction
is also checked against an independent reference (numpy's least-squares line through the
baseline samples, the textbook prediction variance). Seeded; skips without the extension."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.measure.pulse import (PULSE_BASELINE_DRIFT, PULSE_FLIP, PULSE_INCOMPLETE,
                                              PULSE_SATURATED, PULSE_TOO_FEW, PulseExtractor, SampleRing)
from coiltrack.firmware.model.field import Coil, orthogonal_source
from coiltrack.firmware.pose.solver import SOLVE_BAD_INPUT, SOLVE_RUNNING, PoseSolver
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
ORTHO = orthogonal_source(0.055, 50)
SKEWED = [Coil([0.01, 0, 0], [1, 0.2, 0], 0.05, 40), Coil([0, 0.012, 0], [0, 1, 0.3], 0.06, 50),
          Coil([0, 0, 0.01], [0.1, 0, 1], 0.055, 45), Coil([-0.01, 0, 0], [1, 1, 1], 0.04, 30)]


# ---------------------------------------------------------------- windows
def _pair(ring, **kw):
    ref = PulseExtractor(ring, core=core.PYTHON, **kw)
    got = PulseExtractor(ring, core=COMPILED, **kw)
    assert ref.core == "python" and got.core == "compiled"
    return ref, got


def _same_window(ref, got, start, end, case):
    """Both extractors on one window: every output equal to the bit."""
    a0, v0, a1, v1 = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    r0 = ref.extract(start, end, a0, v0)
    r1 = got.extract(start, end, a1, v1)
    assert r1 == r0, case
    np.testing.assert_array_equal(a1, a0, err_msg=str(case))
    np.testing.assert_array_equal(v1, v0, err_msg=str(case))
    u0, u1 = np.zeros(ref.max_samples, np.int64), np.zeros(got.max_samples, np.int64)
    assert got.last_used_times(u1) == ref.last_used_times(u0), case
    np.testing.assert_array_equal(u1, u0, err_msg=str(case))
    assert got.last_used_span() == ref.last_used_span(), case
    e0, e1 = np.zeros(3), np.zeros(3)
    assert got.last_empirical_var(e1) == ref.last_empirical_var(e0), case
    np.testing.assert_array_equal(e1, e0, err_msg=str(case))
    return r0


def _random_ring(rng, cap, n):
    """A ring of ``n`` samples (wrapped when n > cap): jittered 1 ms spacing, now and then a gap,
    a saturated sample or a flip of the set/reset state."""
    ring = SampleRing(cap)
    t = int(rng.integers(-5000, 5000))
    flip = 0
    for _ in range(n):
        t += int(rng.integers(1500, 4000)) if rng.random() < 0.05 else int(rng.integers(900, 1100))
        if rng.random() < 0.02:
            flip ^= 1
        ring.push(t, *(rng.normal(size=3) * 1e-5), bool(rng.random() < 0.02), flip)
    return ring, t


def test_random_windows_bit_identical():
    """3000 random rings (wrapped or not, gaps, flips, saturation) and windows anywhere (before
    the oldest sample, across it, after the newest), random settings (automatic and fixed gap
    limit, a used-time buffer smaller than the window): every output the same to the bit; the
    flags the windows raised cover every PULSE_* bit."""
    rng = np.random.default_rng(30)
    seen = 0
    for trial in range(3000):
        ring, t_last = _random_ring(rng, int(rng.integers(4, 90)), int(rng.integers(0, 150)))
        kw = dict(settle_us=int(rng.integers(0, 3000)), fall_us=int(rng.integers(0, 3000)),
                  baseline_us=int(rng.integers(500, 8000)), guard_us=int(rng.integers(0, 1500)),
                  min_pulse_samples=int(rng.integers(1, 4)), min_baseline_samples=int(rng.integers(1, 3)),
                  max_samples=int(rng.integers(1, 40)), max_gap_us=int(rng.choice([0, 1500])),
                  drift_limit_t=float(rng.choice([0.0, 2e-6])), sigma_t=float(10.0 ** rng.uniform(-9, -6)))
        ref, got = _pair(ring, **kw)
        lo = ring.oldest_t_us if len(ring) else 0
        start = int(rng.integers(lo - 8000, t_last + 3000))
        end = start + int(rng.integers(0, 25000))
        flags, _, _ = _same_window(ref, got, start, end, trial)
        seen |= flags
    assert seen == PULSE_TOO_FEW | PULSE_SATURATED | PULSE_BASELINE_DRIFT | PULSE_FLIP | PULSE_INCOMPLETE


def _clean_window(rng, drift, n_tail=2):
    """A 1 kHz stream: earth field with a linear drift, a 3 ms-settled 20 ms pulse; returns the
    ring, the window and the samples as arrays."""
    ring = SampleRing(256)
    earth = rng.normal(size=3) * 2e-5
    pulse = rng.normal(size=3) * 1e-6
    t = np.arange(0, 60_000, 1000) + 7
    B = earth + np.outer(t, drift) + rng.normal(size=(len(t), 3)) * 3e-9
    start, end = 20_000, 40_000
    on = (t > start) & (t < end)
    B[on] += pulse
    for k in range(len(t) - 10 + n_tail):
        ring.push(int(t[k]), *B[k], False, 0)
    return ring, start, end, t, B


def test_amplitude_and_variance_match_numpy_least_squares():
    """Independent reference: the baseline as numpy's least-squares line (np.polyfit, degree 1)
    through the samples of both quiet sides, evaluated at the mean time of the used in-pulse
    samples (all in [start + settle, end - guard] but the first and last inside the pulse);
    amp = mean(used) - line(t_m), var = sigma^2 / n_p + sigma^2 (1 / n_b + (t_m - t_bar)^2 / Sxx).
    Both cores within 1e-9 of the amplitude's scale (the reference sums in another order)."""
    rng = np.random.default_rng(4)
    kw = dict(settle_us=3000, fall_us=2000, baseline_us=10_000, guard_us=1000, sigma_t=3e-9)
    for drift in ([0.0, 0.0, 0.0], [2e-10, -1e-10, 5e-11]):
        ring, start, end, t, B = _clean_window(rng, np.array(drift))
        ref, got = _pair(ring, **kw)
        a_ref, v_ref = np.zeros(3), np.zeros(3)
        flags, n_p, n_b = _same_window(ref, got, start, end, drift)
        ref.extract(start, end, a_ref, v_ref)
        inside = np.flatnonzero((t >= start) & (t <= end))
        used = np.flatnonzero((t >= start + 3000) & (t <= end - 1000))
        used = used[(used != inside[0]) & (used != inside[-1])]
        quiet = np.flatnonzero(((t >= start - 10_000) & (t < start - 1000 + 1))
                               | ((t >= end + 2000) & (t <= end + 12_000)))
        assert (n_p, n_b) == (len(used), len(quiet))
        tm = t[used].mean()
        for ax in range(3):
            slope, icpt = np.polyfit(t[quiet].astype(float), B[quiet, ax], 1)
            amp = B[used, ax].mean() - (slope * tm + icpt)
            assert abs(a_ref[ax] - amp) <= 1e-9 * 1e-6, (drift, ax)
        tq = t[quiet].astype(float)
        var = 9e-18 / len(used) + 9e-18 * (1 / len(quiet) + (tm - tq.mean()) ** 2 / ((tq - tq.mean()) ** 2).sum())
        np.testing.assert_allclose(v_ref, var, rtol=1e-9)


def test_edge_cases_bit_identical():
    """The reference's edge cases, on both cores: an empty ring; a window not yet closed (no
    sample after its span: PULSE_INCOMPLETE); one before every sample (nothing in the span);
    no in-pulse sample (a pulse shorter than the sample spacing); times beyond int64 and a
    time that is no integer (the compiled extractor hands them to the reference)."""
    rng = np.random.default_rng(8)
    kw = dict(settle_us=0, fall_us=0, baseline_us=5000, guard_us=0)
    empty = SampleRing(8)
    ref, got = _pair(empty, **kw)
    assert _same_window(ref, got, 0, 10, "empty")[0] == PULSE_INCOMPLETE | PULSE_TOO_FEW
    ring, start, end, _, _ = _clean_window(rng, np.zeros(3), n_tail=-8)
    ref, got = _pair(ring, **kw)
    assert _same_window(ref, got, start, end, "open")[0] & PULSE_INCOMPLETE
    ring, start, end, _, _ = _clean_window(rng, np.zeros(3))
    ref, got = _pair(ring, **kw)
    _same_window(ref, got, start, end, "closed")
    assert _same_window(ref, got, -90_000, -80_000, "before")[0] & PULSE_TOO_FEW
    assert _same_window(ref, got, 30_100, 30_500, "short")[1] == 0
    assert _same_window(ref, got, 1 << 62, (1 << 62) + 5, "far")[0] & PULSE_TOO_FEW
    assert _same_window(ref, got, 1 << 70, 1 << 71, "beyond int64")[0] & PULSE_TOO_FEW
    assert _same_window(ref, got, 20_000.5, 40_000, "float")[0] == PULSE_INCOMPLETE | PULSE_TOO_FEW


def test_extraction_follows_the_ring_as_it_wraps():
    """One extractor pair on a ring that wraps many times: the kernel reads the ring's head and
    count at each call (bound to its arrays once), so every window as the ring refills is the
    reference's."""
    rng = np.random.default_rng(12)
    ring = SampleRing(40)
    ref, got = _pair(ring, settle_us=2000, fall_us=1000, baseline_us=6000, guard_us=500)
    t = 0
    for k in range(400):
        t += 1000
        ring.push(t, *(rng.normal(size=3) * 1e-5), False, 0)
        if k % 7 == 0:
            _same_window(ref, got, t - 30_000, t - 15_000, k)


def test_a_subclass_with_its_own_extract_keeps_it():
    """The gyroscope-turned extractor overrides extract: built on the compiled core it still
    runs its own (the compiled kernel binds only where extract is the plain one)."""
    from coiltrack.firmware.measure.gyro_baseline import GyroBaselineExtractor, GyroRing

    ex = GyroBaselineExtractor(SampleRing(16), GyroRing(16), 64, settle_us=0, fall_us=0, baseline_us=1000,
                               guard_us=0)
    assert not hasattr(ex, "core") and ex.extract.__func__ is GyroBaselineExtractor.extract


@pytest.mark.skipif(not available(), reason="needs numpy's allocation hooks")
def test_compiled_extraction_allocates_no_array():
    rng = np.random.default_rng(3)
    ring, start, end, _, _ = _clean_window(rng, np.zeros(3))
    _, got = _pair(ring, settle_us=3000, fall_us=2000, baseline_us=10_000, guard_us=1000)
    amp, var = np.zeros(3), np.zeros(3)
    got.extract(start, end, amp, var)
    with NumpyAllocationCounter() as c:
        for _ in range(20):
            got.extract(start, end, amp, var)
            got.last_used_span()
    assert c.count == 0


# ------------------------------------------------------------------ solves
def _signals(coils, p, R, cur, rng, noise):
    gen = PoseSolver(coils, "exact", core=core.PYTHON)
    h = memoryview(np.zeros(3 * len(coils)))
    gen.signal.predict(p[0], p[1], p[2], R, cur, h)
    return np.array(h).reshape(len(coils), 3).T + rng.normal(0.0, noise, (3, len(coils)))


def _run_budgeted(s, args, budgets):
    """begin, then step with the budgets in turn (cycled) until done: the status and each
    step's (status, evaluations, units charged)."""
    st = s.begin(*args)
    trace = []
    k = 0
    while st == SOLVE_RUNNING:
        st = s.step(budgets[k % len(budgets)])
        trace.append((st, s.evals_last_step, s.units_last))
        k += 1
    return st, trace


@pytest.mark.parametrize("coils", [ORTHO, SKEWED])
def test_budgeted_solves_bit_identical(coils):
    """Warm solves (near, far enough to climb the damping or fall back to acquisition, with a
    hemisphere to check) and cold ones, stepped a budget at a time (3, 9, 18, 1 evaluations and
    a mix): the compiled run of LM steps charges, evaluates and ends each step where the
    reference's units do, and the results are the same to the bit."""
    rng = np.random.default_rng(17)
    n = len(coils)
    ref = PoseSolver(coils, "exact", core=core.PYTHON)
    got = PoseSolver(coils, "exact", core=COMPILED)
    assert got._run.__func__ is PoseSolver._run_compiled
    sigma = np.full((3, n), 2e-9)
    for k in range(24):
        u = rng.normal(size=3)
        p = u / np.linalg.norm(u) * rng.uniform(0.15, 0.6)
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        cur = rng.uniform(0.5, 2.0, n)
        S = _signals(coils, p, R, cur, rng, 2e-9)
        off = (0.01, 0.05) if k % 3 else (0.3, 1.0)
        x0p = p + rng.normal(0.0, off[0], 3)
        x0R = R @ Rotation.from_rotvec(rng.normal(0.0, off[1], 3)).as_matrix()
        hemi = p / np.linalg.norm(p) if k % 2 else None
        budgets = ((3,), (9,), (18,), (1,), (9, 3, 18))[k % 5]
        for args in ((S, cur, sigma, hemi, x0p, x0R), (S, cur, sigma, hemi)):
            st_ref, tr_ref = _run_budgeted(ref, args, budgets)
            st_got, tr_got = _run_budgeted(got, args, budgets)
            case = (k, len(args), budgets)
            assert (st_got, tr_got) == (st_ref, tr_ref), case
            np.testing.assert_array_equal(got.position, ref.position, err_msg=str(case))
            np.testing.assert_array_equal(got.rotation, ref.rotation, err_msg=str(case))
            np.testing.assert_array_equal(got.covariance, ref.covariance, err_msg=str(case))
            assert (got.iterations, got.cost, got.converged, got.solve_evals) == \
                (ref.iterations, ref.cost, ref.converged, ref.solve_evals), case
            assert got.signal.evals == ref.signal.evals, case


def test_inputs_the_kernels_do_not_take_go_to_the_reference():
    """A warm rotation that is no rotation (scaled: projected by nearest_rotation's
    eigen-decomposition), currents as a list, a transposed (non-contiguous) S and sigma,
    integer arrays, wrong shapes, a non-finite signal, sigma, current or x0, a zero sigma: the
    same status and results as the reference."""
    rng = np.random.default_rng(21)
    ref = PoseSolver(ORTHO, "exact", core=core.PYTHON)
    got = PoseSolver(ORTHO, "exact", core=COMPILED)
    p, R = np.array([0.2, -0.1, 0.15]), Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix()
    cur = np.array([1.0, 1.2, 0.8])
    S = _signals(ORTHO, p, R, cur, rng, 1e-9)
    sigma = np.full((3, 3), 1e-9)
    x0p = p + 0.01
    nan = S.copy()
    nan[2, 1] = math.nan
    zero = sigma.copy()
    zero[0, 0] = 0.0
    cases = [(S, cur, sigma, None, x0p, R * 1.3), (S, list(cur), sigma, None, x0p, R),
             (np.ascontiguousarray(S.T).T, cur, np.ascontiguousarray(sigma.T).T, None, x0p, R),
             (S, cur.astype(int), sigma, None, x0p, R), (S[:, :2], cur, sigma, None, x0p, R),
             (nan, cur, sigma, None, x0p, R), (S, cur, zero, None, x0p, R),
             (S, np.array([1.0, math.inf, 1.0]), sigma, None, x0p, R),
             (S, cur, sigma, None, x0p + math.nan, R), (S, cur, sigma, None, x0p, R + math.nan),
             (S, cur, sigma, None, x0p, None), (S, cur, sigma, None, x0p.astype(np.float32), R)]
    statuses = set()
    for k, args in enumerate(cases):
        st_ref, st_got = ref.solve(*args), got.solve(*args)
        assert st_got == st_ref, k
        statuses.add(st_ref)
        if st_ref != SOLVE_BAD_INPUT:
            np.testing.assert_array_equal(got.position, ref.position, err_msg=str(k))
            np.testing.assert_array_equal(got.rotation, ref.rotation, err_msg=str(k))
            np.testing.assert_array_equal(got.covariance, ref.covariance, err_msg=str(k))
            assert got.signal.evals == ref.signal.evals, k
    assert SOLVE_BAD_INPUT in statuses and len(statuses) > 1


@pytest.mark.skipif(not available(), reason="needs numpy's allocation hooks")
def test_compiled_budgeted_warm_solve_allocates_no_array():
    rng = np.random.default_rng(6)
    s = PoseSolver(ORTHO, "exact", core=COMPILED)
    p, R = np.array([0.25, 0.05, -0.1]), Rotation.from_rotvec([0.1, 0.5, -0.3]).as_matrix()
    cur = np.ones(3)
    S = _signals(ORTHO, p, R, cur, rng, 1e-9)
    sigma = np.full((3, 3), 1e-9)
    x0p = p + 0.005
    _run_budgeted(s, (S, cur, sigma, None, x0p, R), (9,))
    with NumpyAllocationCounter() as c:
        for _ in range(5):
            _run_budgeted(s, (S, cur, sigma, None, x0p, R), (9,))
    assert c.count == 0
