"""The compiled part of the single-coil tracker's window bookkeeping: the fixed cycle's reference
pulse (actuate.accuracy.FixedCycleReference._pulse, its measurement filled by sc_policy.c's
ct_scp_ref_pulse_fill through FixedRefCore.pulse) against the Python reference method on the same
KalmanUpdate: the measurement (H, R, y) and the posterior covariance bit for bit (the same scalar
operations in the same order, the same update). Independent references: the closed form of the
measurement (``H = I Hu`` in the position and orientation blocks, ``R = (var_amp + (rel I |hu|)^2 +
(sigma_I |hu|)^2) I3``, Schepers & Veltink 2010, seeds/000_e46ec0e8bf7ea271.txt eq 4) and the
update ``P - P H^T (H P H^T + R)^-1 H P`` through numpy.linalg. Seeded; skips where the extension
is not built."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.actuate.accuracy import FixedCycleReference
from coiltrack.firmware.actuate.accuracy_budget import MeanBudgetReference
from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.estimate.layout import ORI, POS, SCHEPERS_CORE as CORE
from coiltrack.firmware.estimate.single_coil import SchepersEKF
from coiltrack.firmware.model.field import Coil
from coiltrack.tools.bench.alloc import NumpyAllocationCounter

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
COILS = [Coil((0.02, -0.01, 0.0), (1.0, 0.2, 0.1), 0.055, 50),
         Coil((-0.015, 0.03, 0.01), (0.3, 1.0, -0.2), 0.045, 60),
         Coil((0.0, 0.0, -0.025), (0.2, 0.4, 1.0), 0.06, 40)]
CURRENTS = (0.91, 0.8, 0.7)
VAR_AMP, REL, SIGMA_I = (1.7e-8) ** 2, 3e-3, 1e-3


def _ref(kind):
    return kind(CURRENTS, 150_000, 600_000, 140_000, 29_000, VAR_AMP, REL, SIGMA_I, 2e6,
                exp_pos=1.0, exp_ori=0.5, warmup_us=400_000, core=COMPILED)


def _filter(rng):
    ekf = SchepersEKF.from_config(FirmwareConfig(), core=COMPILED)
    R0 = Rotation.from_rotvec(rng.normal(0, 0.5, 3)).as_matrix()
    A = rng.normal(size=(6, 6))
    P6 = np.diag([3e-3 ** 2] * 3 + [0.02 ** 2] * 3) + 1e-7 * (A @ A.T)
    ekf.initialize(rng.normal(0, 0.1, 3) + np.array([0.25, -0.1, 0.15]), R0, P6, 0, 0.05, 0.02, 0.003)
    ekf.propagate(0, np.array([0.0, 0.0, 9.81]), np.zeros(3))
    return ekf


@pytest.mark.parametrize("kind", [FixedCycleReference, MeanBudgetReference])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_compiled_reference_pulse_is_the_python_one_bit_for_bit(kind, seed):
    """Each coil's pulse, one after the other on two references from the same covariance: the
    measurement and the posterior the same bits as the Python method's. Catches a coil's Jacobian
    taken from the wrong row, the orientation block shifted, |hu|^2 or the current's variance
    dropped from R, a stale y."""
    rng = np.random.default_rng(seed)
    ekf = _filter(rng)
    model = SingleCoilModel(COILS, "exact", COMPILED)
    py, got = _ref(kind), _ref(kind)
    assert got._pulse.__func__ is FixedCycleReference._pulse_compiled
    A = rng.normal(size=(15, 15))
    P0 = ekf.P[CORE, CORE] + 1e-8 * (A @ A.T)
    for r in (py, got):
        r.start(P0, ekf.t_us)
        r.upd.y[:] = 1.0                        # a stale innovation: the pulse's is zero
    for coil in (0, 2, 1, 0):
        FixedCycleReference._pulse(py, ekf, model, coil)
        got._pulse(ekf, model, coil)
        for name in ("H", "R", "y"):
            np.testing.assert_array_equal(getattr(got.upd, name), getattr(py.upd, name), err_msg=name)
        np.testing.assert_array_equal(got.P, py.P)
    assert got.pulses == py.pulses == 4


def test_the_reference_pulse_is_the_closed_form_eq4_update():
    """Independent reference: the pulse's measurement in closed form and the posterior through
    numpy.linalg (1e-10 of the largest element: the update's own rounding)."""
    rng = np.random.default_rng(11)
    ekf = _filter(rng)
    model = SingleCoilModel(COILS, "exact", COMPILED)
    got = _ref(FixedCycleReference)
    got.start(ekf.P[CORE, CORE], ekf.t_us)
    coil = 1
    P0 = got.P.copy()
    got._pulse(ekf, model, coil)
    model.evaluate(ekf.p, ekf.R)
    c, Hu, hu = CURRENTS[coil], model.H[coil], model.h[coil]
    H = np.zeros((3, 15))
    H[:, POS] = c * Hu[:, :3]
    H[:, ORI] = c * Hu[:, 3:]
    r = VAR_AMP + ((REL * c) ** 2 + SIGMA_I ** 2) * float(hu @ hu)
    np.testing.assert_allclose(got.upd.H, H, rtol=1e-15, atol=0)
    np.testing.assert_allclose(got.upd.R, r * np.eye(3), rtol=1e-15, atol=0)
    assert not got.upd.y.any()
    S = H @ P0 @ H.T + r * np.eye(3)
    want = P0 - P0 @ H.T @ np.linalg.solve(S, H @ P0)
    np.testing.assert_allclose(got.P, want, rtol=0, atol=1e-10 * float(np.abs(P0).max()))
    assert np.trace(got.P[POS, POS]) < np.trace(P0[POS, POS])


def test_the_compiled_reference_step_allocates_no_array():
    """Four seconds of samples with the reference pulses, through the compiled pulse: no numpy
    array created."""
    rng = np.random.default_rng(5)
    ekf = _filter(rng)
    got = _ref(MeanBudgetReference)
    model = SingleCoilModel(COILS, "exact", COMPILED)
    got.start(ekf.P[CORE, CORE], ekf.t_us)
    acc, gyr = np.array([0.1, 0.2, 9.8]), np.array([0.3, -0.1, 0.2])
    ekf.propagate(10_000, acc, gyr)
    got.step(ekf, 10_000, model)
    with NumpyAllocationCounter() as n:
        for t in range(20_000, 4_000_000, 10_000):
            ekf.propagate(t, acc, gyr)
            got.step(ekf, t, model)
    assert got.pulses >= 15
    assert n.count == 0


def test_bad_pulse_bindings_are_refused_with_their_names():
    got = _ref(FixedCycleReference)
    from coiltrack.firmware import _core

    ck = _core.FixedRefCore((got.P, got.F, got.q, got._T, got.avg, got.law, got._st), None, 0.0, 1.0, 0.0, 0.0)
    model = SingleCoilModel(COILS, "exact", COMPILED)
    with pytest.raises(RuntimeError, match="not bound"):
        ck.pulse(model.h, model.H, 0, 1.0)
    with pytest.raises(TypeError, match="H"):
        ck.bind_pulse(np.zeros((3, 14)), got.upd.R, got.upd.y, 15, 0, 6, 1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="ori"):
        ck.bind_pulse(got.upd.H, got.upd.R, got.upd.y, 15, 0, 13, 1.0, 0.0, 0.0)
    with pytest.raises(RuntimeError, match="already"):
        got._ck.bind_pulse(got.upd.H, got.upd.R, got.upd.y, 15, 0, 6, 1.0, 0.0, 0.0)
    with pytest.raises(TypeError, match="H"):
        got._ck.pulse(model.h, np.zeros((2, 3, 6)), 2, 1.0)


_MON_STATE = ("count", "_head", "mean", "inconsistent", "r_scale", "total", "flagged", "excess", "gated")


def _monitors(**kw):
    from coiltrack.firmware.actuate.coil_choice import NisMonitor
    from coiltrack.firmware.track.single_coil_nis import CompiledNisMonitor, nis_monitor

    got = nis_monitor(COMPILED, **kw)
    assert isinstance(got, CompiledNisMonitor) and got.kernels == "compiled"
    assert type(nis_monitor(core.PYTHON, **kw)) is NisMonitor
    return NisMonitor(**kw), got


@pytest.mark.parametrize("kw", [dict(window=8, dof=3, gate=16.27, z=2.326, min_count=3, min_excess=1.5,
                                     max_scale=50.0, feedback_updates=30),
                                dict(window=1, dof=2, gate=9.0, min_count=1, max_scale=1e4, feedback_updates=1),
                                dict(window=5, dof=3, min_count=5, min_excess=0.0, max_scale=3.0)])
def test_the_compiled_nis_monitor_is_the_reference_bit_for_bit(kw):
    """A seeded run of chi-square NIS values, a disturbance (scaled ones), NaN, inf and resets:
    after every step each attribute of the twin is the reference's, bit for bit. Independent
    check: the mean is the last ``window`` values' (numpy), the excess the exponential mean of the
    gated NIS / dof. Catches the ring's head wrapped wrongly, the hysteresis dropped, the scale not
    capped, NaN or inf taken as a value."""
    ref, got = _monitors(**kw)
    rng = np.random.default_rng(17)
    vals, excess = [], 1.0
    alpha = 1.0 / max(1, kw["feedback_updates"]) if "feedback_updates" in kw else 1.0 / 30
    gate = kw.get("gate", 16.27)
    for i in range(400):
        x = float(rng.chisquare(kw["dof"]))
        if 120 <= i < 200:
            x *= 12.0                                   # a ferromagnetic disturbance
        if i in (50, 51, 260):
            x = (math.nan, math.inf, -math.inf)[(i - 50) % 3 if i < 260 else 2]
        if i in (300, 301):
            x = 1e300
        for m in (ref, got):
            m.add(x)
            m.add_used(x * 0.5)
            if i % 7 == 0:
                m.note_gated()
        u = x * 0.5 if x * 0.5 < gate else gate
        u = gate if not u >= 0.0 else u
        excess += alpha * (u / kw["dof"] - excess)
        vals.append(x if math.isfinite(x) else 1e9)
        if i == 330:
            ref.reset()
            got.reset()
            vals, excess = [], 1.0
        for name in _MON_STATE:
            a, b = getattr(ref, name), getattr(got, name)
            assert type(a) is type(b) and (a == b or (a != a and b != b)), (i, name, a, b)
        assert got.bound() == ref.bound()
        if vals:
            w = vals[-kw["window"]:] if len(vals) >= kw["window"] else vals
            assert got.mean == pytest.approx(float(np.mean(w)), rel=1e-12)
        assert got.excess == pytest.approx(excess, rel=1e-12)
    np.testing.assert_array_equal(got._buf, ref._buf)
    assert ref.flagged > 0 and ref.total == 400


def test_the_compiled_nis_monitor_allocates_nothing_and_refuses_bad_bindings():
    from coiltrack.firmware import _core

    _, got = _monitors(window=8, dof=3, min_count=3)
    with NumpyAllocationCounter() as n:
        for i in range(200):
            got.add(float(i % 13))
            got.add_used(float(i % 5))
    assert n.count == 0 and got.total == 200
    with pytest.raises(TypeError, match="bound"):
        _core.NisCore(got._buf, np.zeros(8), got._st, 8, 3, 3.0, 3.0, 10.0, 16.0, 0.1)
    with pytest.raises(ValueError, match="min_count"):
        _core.NisCore(got._buf, got._bound, got._st, 8, 9, 3.0, 3.0, 10.0, 16.0, 0.1)
