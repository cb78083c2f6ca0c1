"""The compiled parts of the adaptive single-coil policy (firmware_py/core/src/sc_policy.c, the glue in
py_single_coil.c) against their Python references: the fixed cycle's reference covariance
(actuate.accuracy.FixedCycleReference._propagate, accuracy_budget.MeanBudgetReference's running
mean), the eq-4 update of a pulse in flight (coil_choice.PoseCovUpdate.apply) and the
magnetometer-range current limits (single_coil_policy.AdaptiveActuation._range_limits).

The reference propagation's F P F^T and the update's products go through BLAS in the reference
and are summed in index order in C: compared to 1e-12 relative (observed ~1e-16), with the
discrete outcomes (settled, the pulses taken) the same. The scalar parts (the running means, the
limits) are the same operations in the same order: bit for bit. Independent references: the
explicit ``F P F^T + diag(q)`` and ``P - P H^T S^-1 H P`` through numpy.linalg, and the closed form
of the saturation limit. Seeded; skips where the extension is not built."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.actuate.accuracy import FixedCycleReference
from coiltrack.firmware.actuate.accuracy_budget import MeanBudgetReference
from coiltrack.firmware.actuate.coil_choice import PoseCovUpdate, SingleCoilModel
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.estimate.layout import SCHEPERS_CORE as CORE
from coiltrack.firmware.estimate.single_coil import SchepersEKF
from coiltrack.firmware.model.field import Coil
from coiltrack.tools.bench.alloc import NumpyAllocationCounter

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
COILS = [Coil((0.02, -0.01, 0.0), (1.0, 0.2, 0.1), 0.055, 50),
         Coil((-0.015, 0.03, 0.01), (0.3, 1.0, -0.2), 0.045, 60),
         Coil((0.0, 0.0, -0.025), (0.2, 0.4, 1.0), 0.06, 40)]


def _close(a, b, what, rtol=1e-12):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = max(float(np.abs(a).max()), 1e-300)
    np.testing.assert_allclose(b, a, rtol=0, atol=rtol * scale, err_msg=what)


def _filter(rng):
    """A compiled single-coil EKF started at a random pose (both references step with it, so only
    the reference's own kernels differ)."""
    ekf = SchepersEKF.from_config(FirmwareConfig(), core=COMPILED)
    assert ekf.kernels == "compiled"
    R0 = Rotation.from_rotvec(rng.normal(0, 0.5, 3)).as_matrix()
    A = rng.normal(size=(6, 6))
    P6 = np.diag([3e-3 ** 2] * 3 + [0.02 ** 2] * 3) + 1e-7 * (A @ A.T)
    ekf.initialize(np.array([0.25, -0.1, 0.15]), R0, P6, 0, 0.05, 0.02, 0.003)
    ekf.propagate(0, np.array([0.0, 0.0, 9.81]), np.zeros(3))
    return ekf


def _refs(kind, settle_drop, exp_pos, exp_ori):
    args = ((0.91, 0.8, 0.7), 150_000, 600_000, 140_000, 29_000, (1.7e-8) ** 2, 3e-3, 1e-3, 2e6)
    kw = dict(exp_pos=exp_pos, exp_ori=exp_ori, warmup_us=400_000, settle_drop=settle_drop)
    ref = kind(*args, core=core.PYTHON, **kw)
    got = kind(*args, core=COMPILED, **kw)
    assert (ref.kernels, got.kernels) == ("python", "compiled")
    return ref, got


@pytest.mark.parametrize("kind,settle_drop,exp_pos,exp_ori", [
    (FixedCycleReference, 0.0, 0.0, 0.0),
    (FixedCycleReference, 0.05, 1.5, 0.5),
    (MeanBudgetReference, 0.05, 1.0, 0.0),
    (MeanBudgetReference, 0.0, 2.0, 1.0),
])
def test_the_reference_propagation_matches_the_python_one(kind, settle_drop, exp_pos, exp_ori):
    """Four seconds of IMU samples (100 Hz, jittered) with the fixed cycle's reference pulses:
    the covariance, the means, the range law and the filter's own means to 1e-12, the scalars
    (elapsed, mean time, settled, pulses) the same. Catches a dropped q, a law updated with the
    wrong weight, the settle rule inverted, the own means read from the wrong block."""
    rng = np.random.default_rng(7)
    ekf = _filter(rng)
    ref, got = _refs(kind, settle_drop, exp_pos, exp_ori)
    for r in (ref, got):
        r.start(ekf.P[CORE, CORE], ekf.t_us)
    model = SingleCoilModel(COILS, "exact", COMPILED)
    t = 0
    for i in range(400):
        t += 10_000 + int(rng.integers(-400, 400))
        s = t * 1e-6
        f = np.array([0.3 * math.sin(2.1 * s), -0.2 * math.cos(1.3 * s), 9.81]) + rng.normal(0, 0.02, 3)
        w = np.array([0.8 * math.sin(1.7 * s), 0.5, -0.6 * math.cos(0.9 * s)]) + rng.normal(0, 0.01, 3)
        ekf.propagate(t, f, w)
        for r in (ref, got):
            r.step(ekf, t, model)
        assert (got.elapsed_us, got.mean_us, got.settled, got.pulses) == (ref.elapsed_us, ref.mean_us, ref.settled,
                                                                         ref.pulses), i
        assert got._a == ref._a
    assert ref.pulses >= 15 and (ref.settled or settle_drop > 0.0)
    _close(ref.P, got.P, "P")
    _close(ref.avg, got.avg, "avg")
    np.testing.assert_array_equal(got.law, ref.law)       # from the filter's position alone
    if kind is MeanBudgetReference:
        np.testing.assert_array_equal(got.own, ref.own)   # from the filter's covariance alone
        _close(ref.held_avg(1.2), got.held_avg(1.2), "held_avg")


def test_one_compiled_propagation_is_f_p_ft_plus_q():
    """Independent reference: one interval is ``F P F^T + diag(q)`` with the filter's own
    transition (numpy's products), and the first interval's mean is the present variance."""
    rng = np.random.default_rng(3)
    ekf = _filter(rng)
    ekf.propagate(10_000, np.array([0.2, -0.1, 9.7]), np.array([0.3, -0.2, 0.5]))
    _, got = _refs(FixedCycleReference, 0.0, 0.0, 0.0)
    got.start(ekf.P[CORE, CORE], ekf.t_us)
    A = rng.normal(size=(15, 15))
    got.P[:] = A @ A.T * 1e-5
    P0 = got.P.copy()
    F, q = np.eye(15), np.zeros(15)
    ekf.core_transition(F, q, 0.004)
    got._propagate(ekf, 0.004, 4_000)
    _close(F @ P0 @ F.T + np.diag(q), got.P, "F P F^T + q")
    assert got._a == 1.0
    # avg + 1 (P_kk - avg): the present variances, to rounding
    np.testing.assert_allclose(got.avg, np.concatenate([np.diag(got.P)[0:3], np.diag(got.P)[6:9]]), rtol=1e-15)


def _pose_problem(rng):
    model = SingleCoilModel(COILS, "exact", COMPILED)
    R = Rotation.from_rotvec(rng.normal(0, 0.7, 3)).as_matrix()
    model.evaluate(np.array([0.22, 0.08, -0.12]) + rng.normal(0, 0.03, 3), R)
    A = rng.normal(size=(6, 6))
    P6 = np.diag([2e-3 ** 2] * 3 + [0.01 ** 2] * 3) + 1e-7 * (A @ A.T)
    return model, P6


def test_the_update_of_a_pulse_in_flight_matches_poscovupdate_and_the_closed_form():
    """``pose_cov_update`` against ``PoseCovUpdate.apply`` (1e-12, both symmetric) and against
    ``P - P H^T (H P H^T + R_v)^-1 H P`` through numpy.linalg.solve; a covariance that is not
    positive definite leaves P6 alone and says so. Catches a missing current factor, a dropped
    field-model term in R_v, a transposed Jacobian."""
    from coiltrack.firmware import _core

    rng = np.random.default_rng(11)
    for trial in range(12):
        model, P6 = _pose_problem(rng)
        lim = np.zeros(3)
        pk = _core.PolicyCore(3, model.h, model.H, lim)
        c = trial % 3
        cur, var, rel, cs = 0.2 + 0.7 * rng.random(), (1e-8 * (1 + trial)) ** 2, 3e-3, 1e-3
        ref, got = P6.copy(), P6.copy()
        assert PoseCovUpdate().apply(ref, model.H[c], model.h[c], cur, var, rel, cs)
        assert pk.pose_cov_update(got, c, cur, var, rel, cs) is True
        _close(ref, got, "P6")
        np.testing.assert_array_equal(got, got.T)
        H = cur * model.H[c]
        hn2 = float(model.h[c] @ model.h[c])
        S = H @ P6 @ H.T + np.eye(3) * (var + (rel * rel * cur * cur + cs * cs) * hn2)
        _close(P6 - P6 @ H.T @ np.linalg.solve(S, H @ P6), got, "closed form", 1e-9)
    bad = P6.copy()
    assert pk.pose_cov_update(bad, 0, 0.5, -1.0, 0.0, 0.0) is False
    np.testing.assert_array_equal(bad, P6)
    with pytest.raises(ValueError, match="coil"):
        pk.pose_cov_update(bad, 3, 0.5, 1e-16, 0.0, 0.0)


def _actuations():
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.scenarios import thesis as scenarios

    out = []
    for impl in ("python", "compiled"):
        fw_end, _ = inproc_pair()
        fw = Firmware(scenarios.schepers_adaptive_config().with_(core={"impl": impl}), fw_end)
        out.append(fw.tracker.actuation)
    assert (out[0].kernels, out[1].kernels) == ("python", "compiled")
    return out


@pytest.mark.parametrize("have_quiet,quiet,pp,sp", [
    (True, (2e-5, -3e-5, 4e-5), (0.2, 0.05, -0.1), 2e-3),
    (False, (0.0, 0.0, 0.0), (0.12, -0.02, 0.04), 2e-2),      # r - 3 sp < r / 2: gain 8
    (True, (2e-5, 5e-3, 0.0), (0.3, 0.1, 0.1), 1e-3),        # the quiet field beyond the range: 0
    (True, (1e-5, 1e-5, 1e-5), (0.0, 0.0, 0.0), 1e-3),        # at the origin: gain 8
])
def test_the_range_limits_are_the_python_ones_bit_for_bit(have_quiet, quiet, pp, sp):
    """``_range_limits`` compiled and in Python give the same limits to the bit, with and without
    a quiet sample, with the position uncertainty's gain at its floor and at a sensor placed at the
    origin; and each finite limit is the closed form ``min_k (margin range - |quiet_k|) / (gain
    |hu_k|)``."""
    acts = _actuations()
    lims = []
    for act in acts:
        v = act.views[0]
        v.pp[:] = pp
        v.P6[:] = np.diag([sp * sp] * 3 + [1e-4] * 3)
        v.quiet[:] = quiet
        v.have_quiet = have_quiet
        v.Rd[:] = Rotation.from_rotvec((0.3, -0.2, 0.5)).as_matrix()
        act.pmodel.evaluate(v.pp if np.any(v.pp) else np.array([0.0, 0.0, 1e-3]), v.Rd)
        act._lim.fill(7.0)
        act._range_limits(v)
        lims.append(act._lim.copy())
    np.testing.assert_array_equal(lims[1], lims[0])
    act = acts[0]
    p = act.cfg.pulse
    r = float(np.linalg.norm(pp))
    sd = math.sqrt(3.0) * sp            # the position's total std
    gain = (r / max(r - act.cfg.adaptive.saturation_sigmas * sd, 0.5 * r)) ** 3 if r > 0.0 else 8.0
    rng_t = p.mag_range_t if have_quiet else p.mag_range_t - p.earth_field_max_t / p.saturation_margin
    for c in range(act.n):
        room = p.saturation_margin * rng_t - np.abs(np.array(quiet))
        want = 0.0 if np.any(room <= 0.0) else float(np.min(room / (gain * np.abs(act.pmodel.h[c]))))
        assert lims[0][c] == pytest.approx(min(want, 7.0), rel=1e-12)


def test_the_compiled_decision_parts_allocate_no_array():
    """The reference's step and the policy's compiled parts create no numpy array."""
    rng = np.random.default_rng(5)
    ekf = _filter(rng)
    _, got = _refs(MeanBudgetReference, 0.05, 1.0, 0.5)
    got.start(ekf.P[CORE, CORE], ekf.t_us)
    model = SingleCoilModel(COILS, "exact", COMPILED)
    act = _actuations()[1]
    v = act.views[0]
    v.pp[:] = (0.2, 0.05, -0.1)
    v.P6[:] = np.diag([4e-6] * 3 + [1e-4] * 3)
    act.pmodel.evaluate(v.pp, v.Rd)
    acc, gyr = np.array([0.1, 0.2, 9.8]), np.array([0.3, -0.1, 0.2])
    ekf.propagate(10_000, acc, gyr)
    got.step(ekf, 10_000, model)
    sl = type("Slot", (), {"coil": 1, "current": 0.5})()
    with NumpyAllocationCounter() as c:
        for t in range(20_000, 1_500_000, 10_000):
            ekf.propagate(t, acc, gyr)
            got.step(ekf, t, model)
            act._range_limits(v)
            act._in_flight(v, sl, 1e-16)
    assert got.pulses > 0
    assert c.count == 0


def test_bad_bindings_are_refused_with_their_names():
    from coiltrack.firmware import _core

    rng = np.random.default_rng(2)
    _, got = _refs(FixedCycleReference, 0.0, 0.0, 0.0)
    with pytest.raises(TypeError, match="ekf_core"):
        got._ck.propagate(object(), 0.01, 10_000, 0.0, 0.0, False, 0.0)
    with pytest.raises(TypeError, match="avg"):
        _core.FixedRefCore((got.P, got.F, got.q, got._T, np.zeros(5), got.law, got._st), None, 0.0, 1.0, 0.0, 0.0)
    with pytest.raises(TypeError, match="lim"):
        _core.PolicyCore(3, np.zeros((3, 3)), np.zeros((3, 3, 6)), np.zeros(2))
    del rng


@pytest.mark.parametrize("kw", [{}, {"reference_hold": "mean"}, {"accuracy_target": "stated"},
                                {"accuracy_target": "stated", "sigma_range_ref_m": 0.3}])
def test_the_bounds_are_the_python_ones_bit_for_bit(kw):
    """``_bounds`` compiled and in Python, over random predicted positions, reference means, range
    laws (a negative mean: no law yet), reference covariances (the warm-up's), NIS excesses
    (below 1, between, beyond the cap) and a reference active or not: the same bounds to the
    bit, and the mean budget's held means and factors too. Catches a law applied to the wrong
    group, the NIS factor not rooted, the warm-up's catch-up read from the wrong diagonal."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.scenarios import thesis as scenarios

    acts = []
    for impl in ("python", "compiled"):
        fw_end, _ = inproc_pair()
        fw = Firmware(scenarios.schepers_adaptive_config(**kw).with_(core={"impl": impl}), fw_end)
        acts.append(fw.tracker.actuation)
    assert acts[1]._bounds.__name__ == "_bounds_compiled"
    for trial in range(120):
        outs = []
        for act in acts:
            rng = np.random.default_rng(trial)
            v = act.views[0]
            s, ref = v.sensor, v.sensor.ref
            v.pp[:] = rng.normal(0, 0.2, 3)
            if ref is not None:
                ref.active = bool(trial % 3)
                ref.avg[:] = rng.random(6) * 1e-5
                ref.law[:] = rng.random(2) - 0.2
                A = rng.normal(size=(15, 15))
                ref.P[:] = A @ A.T * 1e-6
                if isinstance(ref, MeanBudgetReference):
                    ref.own[:] = rng.random(2) * 1e-5
            act._warming = bool(trial % 2)
            s.monitor.excess = float(rng.random() * 6.0)
            act._bounds(v)
            extra = [ref.factor, ref._held] if isinstance(ref, MeanBudgetReference) else []
            outs.append(np.concatenate([v.smax6, v.smin6] + extra))
        np.testing.assert_array_equal(outs[1], outs[0], err_msg=f"trial {trial}")
    assert np.all(outs[0][:6] > 0.0)
