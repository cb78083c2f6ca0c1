"""The compiled coil choice (firmware_py/core/src/sc_choose.c, glue py_sc_choose.c) against its Python
reference, actuate.coil_choice.CoilChooser (``choose``, ``choose_length``) and
``posterior_pose_variances``.

The choice is a discrete decision, so the two must agree to the bit: the products ``Hu P6`` and
``A Hu^T`` are summed in the same order in both (``CoilChooser._products``), the 3 x 3 inverse is
``linalg.inv3_sym`` in both, and every score, comparison and bisection step is the same operation
in the same order; the coil, the target, the current, the length, the reductions, the products
and the posterior variances are compared with ``==``. Random states on an orthogonal and on a
skewed source, with and without the trace bound, the current refinement and the unreached
share; the edge cases the reference handles: two coils in an exact tie (the first wins), a
target no allowed current brings to ``sigma_min``, coils limited by the driver's current, by the
magnetometer's range (``saturation_current_limit``) and to nothing at all, an innovation
covariance that is not positive definite. Independent reference: the dense eq 4 of Schepers &
Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``) through numpy.linalg. Then a replayed
schepers-adaptive run: every decision of the compiled firmware taken again by the reference on the
same inputs, and the pulses both cores command. The bounds (``set_bounds``) bit for bit too. Seeded; skips where the extension is not built."""
import math

import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.actuate.coil_choice import (CoilChooser, CompiledCoilChooser, SingleCoilModel, coil_chooser,
                                                    current_ladder, posterior_pose_variances,
                                                    saturation_current_limit)
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.pose.reference import so3_exp
from coiltrack.tools.bench.alloc import NumpyAllocationCounter

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
ORTHO = [Coil((0, 0, 0), a, 0.055, 50) for a in np.eye(3)]
SKEWED = [Coil((0.02, -0.01, 0.0), (1.0, 0.2, 0.1), 0.055, 50),
          Coil((-0.015, 0.03, 0.01), (0.3, 1.0, -0.2), 0.045, 60),
          Coil((0.0, 0.0, -0.025), (0.2, 0.4, 1.0), 0.06, 40)]
SMAX = [2e-3] * 3 + [math.radians(0.3)] * 3
SMIN = [1.8e-3] * 3 + [math.radians(0.27)] * 3
# the amplitude variances of four pulse lengths, shortest first (T^2), and the lengths (us)
VARS = [(3e-8) ** 2 * f for f in (0.75, 0.58, 0.5, 0.45)]
LENGTHS = (45_000, 55_000, 65_000, 75_000)


def _pose(rng):
    d = rng.normal(size=3)
    d[0] = abs(d[0]) + 0.3
    return d / np.linalg.norm(d) * rng.uniform(0.15, 0.45), so3_exp(rng.normal(size=3))


def _P6(rng, scale=1.0):
    A = rng.normal(size=(6, 6)) * np.r_[[2.5e-3] * 3, [6e-3] * 3][:, None]
    return scale * (A @ A.T + np.diag([4e-7] * 3 + [4e-6] * 3))


def _pair(trace, step, share, n=3, currents=None, rel=3e-3, cs=1e-3):
    currents = current_ladder(0.05, 0.91, 16) if currents is None else currents
    args = (n, currents, SMAX, SMIN, rel, cs, trace, step, share)
    ref, got = CoilChooser(*args), coil_chooser(COMPILED, *args)
    assert type(got) is CompiledCoilChooser
    return ref, got


def _same(ref, got, what):
    """Every output of the choice bit for bit."""
    assert (got.coil, got.current, got.length, got.target, got.reached) == \
        (ref.coil, ref.current, ref.length, ref.target, ref.reached), what
    for name in ("reduction", "i_ref", "var_after", "_A", "_M", "_hn2"):
        assert np.array_equal(getattr(got, name), getattr(ref, name)), f"{what}: {name}"


def _dense_eq4(P6, Hu, hu, current, var_amp, rel, cs):
    """diag(P - P H^T (H P H^T + R_v)^-1 H P), H = I Hu: Schepers eq 4, dense."""
    H = current * Hu
    Rv = (var_amp + (rel * current) ** 2 * (hu @ hu) + cs ** 2 * (hu @ hu)) * np.eye(3)
    S = H @ P6 @ H.T + Rv
    return np.diag(P6 - P6 @ H.T @ np.linalg.inv(S) @ H @ P6)


@pytest.mark.parametrize("coils", [ORTHO, SKEWED], ids=["orthogonal", "skewed"])
@pytest.mark.parametrize("trace,step,share", [(False, 0.0, 0.0), (True, 0.0, 0.0), (True, 1e-3, 0.0),
                                              (True, 1e-3, 0.8), (False, 1e-3, 0.8)])
def test_choose_is_the_reference_bit_for_bit(coils, trace, step, share):
    """200 random decisions; the limits now the driver's, now a magnetometer's range (a sensor near
    a coil, a large quiet field), now nothing for one coil or for all. Catches a product summed in
    another order (a last-bit score), a wrong rung, a bisection step off, a target group read wrong."""
    rng = np.random.default_rng(11)
    model = SingleCoilModel(coils, "exact", core.PYTHON)
    ref, got = _pair(trace, step, share)
    kinds = {"reached": 0, "unreached": 0, "range": 0, "none": 0}
    for trial in range(200):
        p, R = _pose(rng)
        if trial % 9 == 4:
            p *= 0.12 / np.linalg.norm(p)                # close to the source: the range limit bites
        model.evaluate(p, R)
        P6 = _P6(rng, 10.0 ** rng.uniform(-1.5, 1.5))
        if trial % 3 == 1:                               # the decision's bounds (set_bounds), some invalid
            smax = np.array(SMAX) * rng.uniform(0.5, 2.0, 6)
            smin = smax * rng.uniform(0.5, 1.2, 6)
            if trial % 4 == 1:
                smax[rng.integers(6)] = 0.0
                smin[rng.integers(6)] = -1.0
            ref.set_bounds(smax, smin)
            got.set_bounds(smax, smin)
            for name in ("sigma_max", "sigma_min", "weight"):
                assert np.array_equal(getattr(got, name), getattr(ref, name)), name
        lim = np.full(3, 0.91)
        if trial % 9 == 4:
            quiet = rng.normal(0, 3e-5, 3)
            for c in range(3):
                lim[c] = min(lim[c], saturation_current_limit(model.h[c], quiet, 8e-5, 0.9, 1.3))
            kinds["range"] += bool(np.any(lim < 0.91))
        if trial % 7 == 0:
            lim[rng.integers(3)] = 0.01                  # below every candidate current
        if trial % 31 == 0:
            lim[:] = 0.0                                 # no coil may carry any current
        var = (3e-8) ** 2 * rng.uniform(0.3, 30.0)
        c = ref.choose(P6, model, var, lim)
        assert got.choose(P6, model, var, lim) == c
        _same(ref, got, f"trial {trial}")
        if c < 0:
            kinds["none"] += 1
            continue
        kinds["reached" if ref.reached else "unreached"] += 1
        # the independent reference: eq 4, dense, at the chosen current
        want = _dense_eq4(P6, model.H[c], model.h[c], got.current, var, 3e-3, 1e-3)
        np.testing.assert_allclose(got.var_after, want, rtol=1e-9, atol=1e-12 * float(np.abs(want).max()))
    assert kinds["reached"] > 10 and kinds["unreached"] > 10 and kinds["range"] > 5 and kinds["none"] > 0


@pytest.mark.parametrize("trace,step,share", [(True, 1e-3, 0.8), (True, 1e-3, 0.0), (False, 0.0, 0.0)])
def test_choose_length_is_the_reference_bit_for_bit(trace, step, share):
    """choose_length over four lengths: the same coil, current and length, bit for bit. Catches an
    energy compared in another order or the last length's variance used for another."""
    rng = np.random.default_rng(5)
    model = SingleCoilModel(SKEWED, "exact", core.PYTHON)
    ref, got = _pair(trace, step, share)
    lengths = set()
    for trial in range(120):
        p, R = _pose(rng)
        model.evaluate(p, R)
        P6 = _P6(rng, 10.0 ** rng.uniform(-1.5, 1.0))
        lim = np.full(3, 0.91) if trial % 5 else np.array([0.91, 0.3, 0.01])
        c = ref.choose_length(P6, model, VARS, LENGTHS, lim)
        assert got.choose_length(P6, model, VARS, LENGTHS, lim) == c
        _same(ref, got, f"trial {trial}")
        lengths.add(got.length)
    assert len(lengths) >= 2


def test_a_tie_between_coils_picks_the_first_in_both():
    """Two identical coils give the same reduction to the bit: the first (strict >) in both, the
    other never; a third coil that may carry nothing is left out."""
    coils = [ORTHO[0], ORTHO[0], ORTHO[1]]
    model = SingleCoilModel(coils, "exact", core.PYTHON)
    ref, got = _pair(True, 1e-3, 0.8)
    rng = np.random.default_rng(3)
    for _ in range(20):
        p, R = _pose(rng)
        model.evaluate(p, R)
        P6 = _P6(rng)
        lim = np.array([0.91, 0.91, 0.0])
        assert ref.choose(P6, model, (3e-8) ** 2, lim) == got.choose(P6, model, (3e-8) ** 2, lim) == 0
        assert got.reduction[0] == got.reduction[1] and got.reduction[2] == -1.0 and got.i_ref[2] == 0.0
        _same(ref, got, "tie")


def test_posterior_pose_variances_kernel():
    """The kernel alone: the reference's values to the bit, the dense eq 4 to 1e-9; an innovation
    covariance that is not positive definite (a negative amplitude variance) gives False and
    diag(P6) in both."""
    from coiltrack.firmware import _core

    rng = np.random.default_rng(8)
    model = SingleCoilModel(SKEWED, "exact", core.PYTHON)
    ch = CoilChooser(3, [0.5], SMAX, SMIN)
    for trial in range(50):
        p, R = _pose(rng)
        model.evaluate(p, R)
        P6 = _P6(rng)
        ch._products(0, memoryview(model.H.reshape(-1)), memoryview(P6))
        A, M = ch._A[0], ch._M[0]
        hn2 = float(model.h[0] @ model.h[0])
        cur = rng.uniform(0.05, 1.5)
        var = (3e-8) ** 2 if trial % 10 else -1.0
        a, b = np.zeros(6), np.zeros(6)
        ok = posterior_pose_variances(P6, A, M, hn2, cur, var, 3e-3, a, 1e-3)
        assert _core.posterior_pose_variances(P6, A, M, hn2, cur, var, 3e-3, b, 1e-3) is ok
        assert np.array_equal(a, b)
        if ok:
            np.testing.assert_allclose(b, _dense_eq4(P6, model.H[0], model.h[0], cur, var, 3e-3, 1e-3), rtol=1e-9)
        else:
            assert trial % 10 == 0 and np.array_equal(b, np.diag(P6))
        # the products against numpy's (BLAS: to rounding only)
        np.testing.assert_allclose(A, model.H[0] @ P6, rtol=1e-12, atol=1e-24)
        np.testing.assert_allclose(M, model.H[0] @ P6 @ model.H[0].T, rtol=1e-12, atol=1e-30)


def test_compiled_choice_allocates_no_array_and_per_coil_variances_take_the_reference():
    rng = np.random.default_rng(2)
    model = SingleCoilModel(SKEWED, "exact", core.PYTHON)
    ref, got = _pair(True, 1e-3, 0.8)
    p, R = _pose(rng)
    model.evaluate(p, R)
    P6, lim = _P6(rng), np.full(3, 0.91)
    got.choose(P6, model, (3e-8) ** 2, lim)
    counter = NumpyAllocationCounter()
    with counter:
        got.choose(P6, model, (3e-8) ** 2, lim)
        got.choose_length(P6, model, VARS, LENGTHS, lim)
    assert counter.count == 0
    assert ref.choose_length(P6, model, VARS, LENGTHS, lim) == got.coil
    _same(ref, got, "after choose_length")
    var = (3e-8) ** 2 * np.array([1.0, 4.0, 9.0])        # per coil: the reference's path, the same state
    assert got.choose(P6, model, var, lim) == ref.choose(P6, model, var, lim)
    _same(ref, got, "per-coil variances")


def test_a_replayed_adaptive_run_decides_the_same_on_either_core():
    """schepers-adaptive, seed 1, 8 s recorded once and replayed through a firmware on each core:
    every decision of the compiled firmware is taken again by a reference chooser on the same inputs
    (the same coil, current and state to the bit), and both firmwares command the same pulses (coil,
    current, start, length)."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools.bench.framelog import replay
    from coiltrack.tools.bench.runner import record_log
    from coiltrack.tools.commands.perf import _with_core
    from coiltrack.tools.scenarios import get

    sc = get("schepers-adaptive")
    # the scenario's policy (pulse lengths chosen) with the 2 s warm-up: its reference's settle would
    # hold the fixed cycle for about 10 s, past the recording
    cfg = _with_core(sc.firmware_config().with_keys(reference_settle_drop=0.0), "python")
    header, reads = record_log(sc, 1, 8.0, cfg)
    pulses, checked = {}, []
    for impl in ("python", "compiled"):
        cmds = pulses[impl] = []

        def factory(cfg, port, impl=impl, cmds=cmds):
            fw = Firmware(cfg.with_(core={"impl": impl}), port)
            act = fw.tracker.actuation
            book_command = act.book.command

            def command(coil, current, start, length, *rest):
                cmds.append((coil, current, start, length))
                return book_command(coil, current, start, length, *rest)
            act.book.command = command
            if impl == "compiled":
                ch = act.chooser
                assert isinstance(ch, CompiledCoilChooser)
                twin = CoilChooser(ch.n, ch.currents, ch.sigma_max, ch.sigma_min, ch.rel_model, ch.current_sigma,
                                   ch.trace, ch.step_a, ch.unreached_share)
                choose, set_bounds = ch.choose, ch.set_bounds

                def bounds(smax, smin):
                    twin.set_bounds(smax, smin)
                    set_bounds(smax, smin)

                def chosen(P6, model, var, lim):
                    twin.target = ch.target
                    c = twin.choose(P6.copy(), model, var, lim.copy())
                    assert choose(P6, model, var, lim) == c
                    _same(twin, ch, f"decision {len(checked)}")
                    checked.append((c, ch.current))
                    return c
                choose_length = ch.choose_length
                def chosen_length(P6, model, var_amps, lengths_us, lim):
                    twin.target = ch.target
                    c = twin.choose_length(P6.copy(), model, list(var_amps), tuple(lengths_us), lim.copy())
                    assert choose_length(P6, model, var_amps, lengths_us, lim) == c
                    _same(twin, ch, f"decision {len(checked)}")
                    checked.append((c, ch.current))
                    return c
                # the scenario chooses the pulse length (choose_length); a policy of one length, choose
                ch.set_bounds, ch.choose, ch.choose_length = bounds, chosen, chosen_length
            return fw
        replay(factory, header, reads)
    assert len(checked) >= 10 and len({c for c, _ in checked}) >= 2
    assert pulses["python"] == pulses["compiled"] and len(pulses["python"]) > len(checked)


def test_more_pulse_lengths_than_the_kernel_takes_run_the_reference():
    """70 lengths (over CH_MAXLEN): the reference's path, the same choice."""
    from coiltrack.firmware import _core

    rng = np.random.default_rng(6)
    model = SingleCoilModel(SKEWED, "exact", core.PYTHON)
    ref, got = _pair(True, 1e-3, 0.8)
    n = _core.CH_MAXLEN + 6
    lengths = tuple(40_000 + 500 * k for k in range(n))
    var = [(3e-8) ** 2 * 40_000 / x for x in lengths]
    p, R = _pose(rng)
    model.evaluate(p, R)
    P6, lim = _P6(rng), np.full(3, 0.91)
    assert ref.choose_length(P6, model, var, lengths, lim) == got.choose_length(P6, model, var, lengths, lim) >= 0
    _same(ref, got, "70 lengths")


def _dense_eq4_with_gain(P6, Hu, hu, current, var_amp, rel, cs, gain_var):
    """The pose's diag of eq 4 for the state (pose, g_c) with prior blockdiag(P6, gain_var) and
    H = I [Hu, hu]: the measurement y = (1 + g_c) I h(pose), linearised (the closed form the
    rank-one term stands for)."""
    P = np.zeros((7, 7))
    P[:6, :6] = P6
    P[6, 6] = gain_var
    H = current * np.column_stack([Hu, hu])
    Rv = (var_amp + (rel * current) ** 2 * (hu @ hu) + cs ** 2 * (hu @ hu)) * np.eye(3)
    S = H @ P @ H.T + Rv
    return np.diag(P - P @ H.T @ np.linalg.inv(S) @ H @ P)[:6]


@pytest.mark.parametrize("trace,step,share", [(True, 1e-3, 0.8), (False, 0.0, 0.0)])
def test_the_gain_term_is_the_reference_bit_for_bit_and_the_augmented_eq4(trace, step, share):
    """Each coil's gain variance (``gain_var``, some 0) folded into its eq-4 ``S`` as
    ``s_g^2 (I hu)(I hu)^T``: the compiled choice equals the reference to the bit (choose and
    choose_length), and the chosen posterior equals the dense eq 4 of the state augmented by the
    gain (pose and gain uncorrelated) to 1e-9. Catches the term dropped on one side, added as
    ``s_g^2 |hu|^2 I3`` (isotropic) or without the current's square, or read from another coil."""
    rng = np.random.default_rng(21)
    model = SingleCoilModel(SKEWED, "exact", core.PYTHON)
    ref, got = _pair(trace, step, share)
    moved = 0
    for trial in range(80):
        p, R = _pose(rng)
        model.evaluate(p, R)
        P6 = _P6(rng, 10.0 ** rng.uniform(-1.5, 1.0))
        gv = (3e-3 * rng.uniform(0.2, 1.0, 3)) ** 2
        if trial % 4 == 0:
            gv[rng.integers(3)] = 0.0
        Pbig = np.diag(np.r_[np.ones(5), gv, np.ones(2)])     # the gains' rows from 5, as a filter's P
        ref.set_gain_var(Pbig, 5)
        got.set_gain_var(Pbig, 5)
        assert np.array_equal(got.gain_var, gv)
        lim = np.full(3, 0.91)
        var = (3e-8) ** 2 * rng.uniform(0.3, 30.0)
        c = ref.choose(P6, model, var, lim)
        assert got.choose(P6, model, var, lim) == c >= 0
        _same(ref, got, f"trial {trial}")
        want = _dense_eq4_with_gain(P6, model.H[c], model.h[c], got.current, var, 3e-3, 1e-3, gv[c])
        np.testing.assert_allclose(got.var_after, want, rtol=1e-9, atol=1e-12 * float(np.abs(want).max()))
        without = _dense_eq4(P6, model.H[c], model.h[c], got.current, var, 3e-3, 1e-3)
        moved += gv[c] > 0.0 and not np.allclose(want, without, rtol=1e-6)
        c2 = ref.choose_length(P6, model, VARS, LENGTHS, lim)
        assert got.choose_length(P6, model, VARS, LENGTHS, lim) == c2
        _same(ref, got, f"trial {trial}, lengths")
    assert moved > 20
    counter = NumpyAllocationCounter()                       # the decision's path with the gains
    with counter:
        got.set_gain_var(Pbig, 5)
        got.choose(P6, model, (3e-8) ** 2, lim)
        got.choose_length(P6, model, VARS, LENGTHS, lim)
    assert counter.count == 0
    ref.set_gain_var(np.zeros((8, 8)), 5)                   # back to none: the choice of before, bit for bit
    plain = CoilChooser(3, current_ladder(0.05, 0.91, 16), SMAX, SMIN, 3e-3, 1e-3, trace, step, share)
    p, R = _pose(rng)
    model.evaluate(p, R)
    P6 = _P6(rng)
    assert ref.choose(P6, model, (3e-8) ** 2, np.full(3, 0.91)) == plain.choose(P6, model, (3e-8) ** 2, np.full(3, 0.91))
    _same(plain, ref, "no gain term")
