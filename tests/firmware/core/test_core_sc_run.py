"""The single-coil update in one compiled call (``SingleCoilUpdateCore.run``, py_single_coil.c, through
``estimate.single_coil_update.SingleCoilUpdate._run_fused``) against the same update made one kernel a
call (``_run_compiled``: the model's evaluation, ``begin``, the shared ``KalmanUpdate``, ``after`` and
``again``), which test_core_single_coil.py compares with the Python reference and filterpy. The fused
call runs the same kernels in the same order, so everything is compared with ``==``: the covariance,
the error estimate, the flags, both NISs, the shared update's counts (its symmetrisation every
``SYMMETRIZE_EVERY``-th update included) and the model's evaluation count. Seeded; skips where the
extension is not built."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.estimate.ekf import EKF_GATED, SYMMETRIZE_EVERY
from coiltrack.firmware.estimate.single_coil import CoilGainEKF, SchepersEKF
from coiltrack.firmware.estimate.single_coil_update import CoilMeasurement
from coiltrack.firmware.model.field import Coil

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
COILS = [Coil((0.02, -0.01, 0.0), (1.0, 0.2, 0.1), 0.055, 50),
         Coil((-0.015, 0.03, 0.01), (0.3, 1.0, -0.2), 0.045, 60),
         Coil((0.0, 0.0, -0.025), (0.2, 0.4, 1.0), 0.06, 40)]


def _filters(kind, iterations):
    cfg = FirmwareConfig()
    kw = dict(iterations=iterations, core=COMPILED)
    if kind is CoilGainEKF:
        kw.update(coil_gains=3, gain_sigma=0.01)
    fused, unfused = kind.from_config(cfg, **kw), kind.from_config(cfg, **kw)
    u = unfused._coil_update
    u.run = u._run_compiled                      # the same update, one kernel a call
    for e in (fused, unfused):
        e.initialize(np.array([0.22, -0.08, 0.14]), np.eye(3), np.diag([4e-4] * 3 + [1e-3] * 3), 0, 0.05, 0.02,
                     0.003)
    return fused, unfused


def _same(a, b):
    ua, ub = a._coil_update, b._coil_update
    for name in ("P", "p", "v", "R", "ba", "bg", "clone_p", "clone_R"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(ua.dx, ub.dx) and np.array_equal(ua.upd.dx, ub.upd.dx)
    assert (a.nis, a.nis_nominal, a.updates, a.rejected) == (b.nis, b.nis_nominal, b.updates, b.rejected)
    assert (ua.upd.count, ua.upd.rejected, ua.upd.nis) == (ub.upd.count, ub.upd.rejected, ub.upd.nis)


@pytest.mark.parametrize("kind, iterations", [(SchepersEKF, 1), (SchepersEKF, 3), (CoilGainEKF, 3)])
def test_a_fused_run_is_the_kernel_by_kernel_run(kind, iterations):
    """Pulses of each coil, through a clone and the current state, priors off by up to 4 cm (second and
    third passes), the gate stepped aside and an amplitude far off (gated), 40 updates: more than
    ``SYMMETRIZE_EVERY``, so the symmetrisation falls inside runs. Catches a count kept apart from the
    shared update's, a pass's model with the first pass's noise terms, or an evaluation not counted."""
    rng = np.random.default_rng(3 + iterations)
    fused, unfused = _filters(kind, iterations)
    mf, mu = SingleCoilModel(COILS, "exact", COMPILED), SingleCoilModel(COILS, "exact", COMPILED)
    truth = SingleCoilModel(COILS, "exact", core.PYTHON)
    t, flags_seen = 0, set()
    for j in range(40):
        t += 10_000
        acc, gyr = np.array([0.1, -0.2, 9.8]) + rng.normal(0, 0.05, 3), rng.normal(0, 0.3, 3)
        for e in (fused, unfused):
            e.schedule_clone(0, t - 4_000)
            e.propagate(t, acc, gyr)
        coil = j % 3
        off = (0.04 if j % 5 == 0 else 0.002) * rng.normal(size=3)
        truth.evaluate(fused.clone_p[0] + off, fused.clone_R[0])
        y = truth.h[coil] * 0.9 + rng.normal(0, 3e-9, 3)
        if j % 11 == 7:
            y = y + 1e-4                                   # far off: gated
        k = 0 if j % 2 == 0 else -1
        gate = j % 7 != 3
        fl = [e.update_pulse(k, CoilMeasurement().set(y, np.full(3, 1e-17), coil, 0.9, 3e-3, 1.0 + (j % 3), gate), m)
              for e, m in ((fused, mf), (unfused, mu))]
        assert fl[0] == fl[1]
        flags_seen.add(fl[0] & EKF_GATED)
        _same(fused, unfused)
        assert mf.signal.evals == mu.signal.evals
        for e in (fused, unfused):
            e.release_clone(0)
    assert fused._coil_update._run_model is mf
    assert fused._coil_update.upd.count > SYMMETRIZE_EVERY and flags_seen == {0, EKF_GATED}
    assert mf.signal.evals > 3 * 40 if iterations > 1 else mf.signal.evals == 3 * 40


def test_a_model_with_a_distortion_map_or_another_model_takes_the_call_by_call_path():
    """The fused call evaluates the plain signal model of the first model it is handed: a model
    with a distortion map, or a second model, goes through ``_run_compiled`` (the map's field
    added between the kernels), and the bound buffers are not bound twice."""
    fused, _ = _filters(SchepersEKF, 1)
    u = fused._coil_update
    m1, m2 = SingleCoilModel(COILS, "exact", COMPILED), SingleCoilModel(COILS, "exact", COMPILED)
    m1.signal.distortion = object()
    calls = []
    u._run_compiled = lambda *a, **k: calls.append(1) or 0
    y = np.full(3, 1e-7)
    fused.update_pulse(-1, CoilMeasurement().set(y, np.full(3, 1e-17), 0, 0.9, 3e-3, 1.0, True), m1)
    assert calls == [1] and u._run_model is None
    m1.signal.distortion = None
    fused.update_pulse(-1, CoilMeasurement().set(y, np.full(3, 1e-17), 0, 0.9, 3e-3, 1.0, False), m1)
    assert u._run_model is m1 and calls == [1]
    fused.update_pulse(-1, CoilMeasurement().set(y, np.full(3, 1e-17), 0, 0.9, 3e-3, 1.0, False), m2)
    assert calls == [1, 1] and u._run_model is m1
    with pytest.raises(RuntimeError):
        u._ck.bind_run((), (), u._rs, SYMMETRIZE_EVERY)
