"""The compiled strapdown and covariance step (firmware_py/core/src/strapdown.c: ct_exp_rotvec,
ct_strapdown_rotate, ct_to_nav, ct_integrate_pv, ct_transition_nav, ct_ins_propagate) against its
reference, InertialPrediction.step_python (estimate/magnetic_inertial.py, estimate/strapdown.py,
linalg.exp_rotvec). exp_rotvec is bit-identical (the same operations and libm); the attitude
product and the covariance sums go through BLAS in the reference, so the step is compared to
1e-12 relative. Seeded; skips where the extension is not built."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.estimate.magnetic_inertial import FusionFilter, FusionParams
from coiltrack.firmware.estimate.orientation import OrientationFilter, OrientationParams
from coiltrack.firmware.linalg import exp_rotvec

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")


def test_exp_rotvec_is_bit_identical():
    """ct_exp_rotvec against linalg.exp_rotvec: tiny angles (the series branch), angles near pi
    and 2 pi, ordinary ones; an infinite angle gives NaN in both."""
    rng = np.random.default_rng(21)
    ws = [(0.0, 0.0, 0.0), (1e-7, -2e-7, 3e-8), (math.pi - 1e-9, 0.0, 0.0), (0.0, 0.0, -math.pi),
          (2 * math.pi, 0.0, 0.0)]
    for _ in range(500):
        u = rng.normal(size=3)
        ws.append(tuple(u / np.linalg.norm(u) * 10 ** rng.uniform(-7, 0.6)))
    out = np.zeros((3, 3))
    for w in ws:
        exp_rotvec(*w, out)
        assert _core.exp_rotvec(*w) == tuple(out.reshape(9)), w
    assert all(math.isnan(v) for v in _core.exp_rotvec(math.inf, 0.0, 0.0))


def _filters(monkeypatch, model=3):
    prm = FusionParams.from_config(None, measurement_model=model)
    c = core.load("compiled")
    ref = FusionFilter(prm, OrientationFilter(OrientationParams.from_config(None), core.PYTHON), core=core.PYTHON)
    got = FusionFilter(prm, OrientationFilter(OrientationParams.from_config(None), c), core=c)
    assert ref.st.ck is None and got.st.ck is not None
    assert ref.prediction._ins_step == ref.prediction.step_python
    assert got.prediction._ins_step == got.prediction.step_compiled
    return ref, got


@pytest.mark.parametrize("model", [1, 3])
def test_ins_step_matches_the_reference(model, monkeypatch):
    """300 steps from the same random state (attitude near pi, offsets, a full covariance) with
    random inputs and a step that changes now and then (the static blocks rewritten): p, v,
    Theta, the offsets, A and P equal to 1e-12 relative. A dropped T^2 term of the position, the
    offset decay forgotten or R f where R^T f is due are off by far more."""
    rng = np.random.default_rng(22 + model)
    ref, got = _filters(monkeypatch, model)
    n = ref.st.P.shape[0]
    R0 = Rotation.from_rotvec([math.pi - 1e-6, 0.0, 0.0]).as_matrix()
    M = rng.normal(size=(n, n))
    for ff in (ref, got):
        st = ff.st
        st.p[:] = (0.1, -0.2, 0.3)
        st.v[:] = (0.5, 0.0, -0.1)
        st.Th[:] = R0
        st.ba[:] = (0.01, -0.02, 0.005)
        st.bg[:] = (0.001, 0.002, -0.003)
        st.P[:] = 1e-4 * (M @ M.T)
    for i in range(300):
        dt = (1.0 / 120.0) if i % 50 else rng.uniform(0.002, 0.02)
        f0 = rng.normal(size=3) + (0.0, 0.0, 9.81)
        f1 = f0 + 0.1 * rng.normal(size=3)
        w = rng.normal(size=3) * (1e-8 if i % 7 == 0 else 2.0)
        r0 = (0.0, 0.0, 9.81) + 0.01 * rng.normal(size=3)
        r1 = r0 + 0.01 * rng.normal(size=3)
        args = (dt, *f0, *f1, *w, *r0, *r1)
        ref.prediction.step_python(ref.st, *args)
        got.prediction.step_compiled(got.st, *args)
    for name in ("p", "v", "Th", "ba", "bg"):
        a, b = getattr(ref.st, name), getattr(got.st, name)
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * max(np.abs(a).max(), 1.0), err_msg=name)
    np.testing.assert_array_equal(got.st.pred.A != 0.0, ref.st.pred.A != 0.0)
    np.testing.assert_allclose(got.st.pred.A, ref.st.pred.A, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.st.P, ref.st.P, rtol=0, atol=1e-12 * np.abs(ref.st.P).max())
    assert got.steps == ref.steps == 300 and got.st.pred.count == ref.st.pred.count == 300


def test_both_live_and_shadow_states_are_bound(monkeypatch):
    """The live and shadow states each get their own compiled step (the snapshot, which is only
    copied, none): a step of one never writes the other's buffers."""
    _, got = _filters(monkeypatch)
    assert got.st.ck is not None and got.sh.ck is not None and got.sn.ck is None
    p_sh = got.sh.p.copy()
    P_sh = got.sh.P.copy()
    got.prediction.step_compiled(got.st, 0.01, 0, 0, 9.81, 0, 0, 9.81, 0.1, 0.2, 0.3, 0, 0, 9.81, 0, 0, 9.81)
    np.testing.assert_array_equal(got.sh.p, p_sh)
    np.testing.assert_array_equal(got.sh.P, P_sh)


def test_strapdown_rotate_matches_the_reference(monkeypatch):
    """Strapdown.rotate on the compiled core (ct_strapdown_rotate) against the reference (numpy's
    3x3 product) over 1000 chained steps with tiny and near-pi increments: equal to 1e-13 (the
    product's rounding, accumulated), and still a rotation."""
    from coiltrack.firmware.estimate.strapdown import Strapdown

    ref = Strapdown(core.PYTHON)
    got = Strapdown(core.load("compiled"))
    assert (ref.core, got.core) == ("python", "compiled")
    rng = np.random.default_rng(23)
    R1 = Rotation.from_rotvec([0.3, -2.0, 1.0]).as_matrix()
    R2 = R1.copy()
    for i in range(1000):
        u = rng.normal(size=3)
        u *= (1e-9 if i % 3 == 0 else (math.pi - 1e-6 if i % 3 == 1 else 0.01)) / np.linalg.norm(u)
        ref.rotate(R1, *u)
        got.rotate(R2, *u)
    np.testing.assert_allclose(R2, R1, rtol=0, atol=1e-13)
    np.testing.assert_allclose(R2 @ R2.T, np.eye(3), atol=1e-12)
    with pytest.raises(TypeError, match="R"):
        got.rotate(np.eye(3)[:, ::-1], 0.1, 0.0, 0.0)
