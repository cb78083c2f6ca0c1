"""The fused trackers' one IMU step on the compiled core (core/src/fusimu.c ct_fus_step with
ct_fus_set_dt), the one step of the forward path (ct_fus_propagate) and of the replay on the shadow
(core/src/fusion.c ct_fusion_replay), against its Python reference
(estimate/fusion_prediction.py InertialPrediction.propagate and set_dt) and the closed form of
sec 6.2.4's orientation noise (s_g dt)^2 (thesis seeds/002_cd7f1fdb7fc67471.txt).

The kernel squares s_g dt by a product, the correctly rounded square (a compiler turns
pow(x, 2.0) into that product too); the reference's ``** 2`` calls libm's pow, within 0.52 ulp,
which differs from it in the last bit for about one step length in a thousand. The tests pick such
step lengths: the compiled noise is the exact square rounded once (fractions.Fraction) on both
paths, and the reference within one ulp of it. Seeded; skips where the extension is not built."""
import math
from fractions import Fraction

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.estimate.layout import ORI
from coiltrack.firmware.estimate.magnetic_inertial import FusionFilter, FusionParams
from coiltrack.firmware.estimate.orientation import OrientationFilter, OrientationParams

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

G = np.array([0.0, 0.0, 9.81])


def _pair(fixed: bool):
    prm = FusionParams.from_config(None, measurement_model=1, acc_bias_tau_s=2.0, gyro_bias_tau_s=3.0,
                                   source_imu=not fixed)
    out = [FusionFilter(prm, OrientationFilter(OrientationParams.from_config(None), core.PYTHON),
                        fixed_source=fixed, core=c) for c in (core.PYTHON, core.load("compiled"))]
    assert out[0]._replay_ck is None and out[1]._replay_ck is not None
    return prm, out


def _sample(rng, fixed: bool):
    f = G + rng.normal(size=3)
    w = rng.normal(size=3)
    r = G + 0.05 * rng.normal(size=3)
    phi = np.eye(3) if fixed else Rotation.from_rotvec(0.3 * rng.normal(size=3)).as_matrix()
    return (*f, *w, *r, phi)


def _tie_steps(g: float, count: int, lo: int = 500) -> list[int]:
    """Step lengths (us) whose (g dt) ** 2 is not the product (g dt) (g dt)."""
    out = []
    for us in range(lo, 100_000):
        x = g * (us * 1e-6)
        if x ** 2 != x * x:
            out.append(us)
            if len(out) == count:
                break
    return out


def _square(x: float) -> float:
    """x^2 rounded once to the nearest double (an exact rational, then one rounding)."""
    return float(Fraction(x) ** 2)


def _ulp_apart(a: float, b: float) -> int:
    return abs(int(np.float64(a).view(np.int64)) - int(np.float64(b).view(np.int64)))


def _check_noise(prm, st, what: str) -> None:
    dt = st.ws[0]
    q = _square(prm.gyro_noise * dt)
    np.testing.assert_array_equal(np.diag(st.pred.Q)[ORI], [q, q, q], err_msg=what)


@pytest.mark.parametrize("fixed", [True, False])
def test_forward_step_noise_is_the_rounded_square(fixed):
    """Forward steps whose lengths tell pow and the product apart: Q's orientation diagonal is
    the correctly rounded (s_g dt)^2, the reference's one ulp away at most; the rest of Q, the
    step's scalars (dt_last, ka, kg) bit-identical to the reference, the state after each step
    to 1e-12 (the attitude product goes through BLAS in the reference)."""
    prm, (ref, got) = _pair(fixed)
    steps = _tie_steps(prm.gyro_noise, 6)
    rng = np.random.default_rng(11 + fixed)
    t = 1_000_000
    s = _sample(rng, fixed)
    for ff in (ref, got):
        ff.push_imu(t, *s)
        ff.st.t_us = t
        ff.initialized = True
    for us in steps:
        t += us
        s = _sample(rng, fixed)
        for ff in (ref, got):
            ff.push_imu(t, *s)
        dt = us * 1e-6
        x = prm.gyro_noise * dt
        assert x ** 2 != x * x == _square(x)               # the step tells the two apart
        _check_noise(prm, got.st, f"dt {us} us")
        Qr, Qg = ref.st.pred.Q.copy(), got.st.pred.Q.copy()
        assert all(_ulp_apart(a, b) == 1 for a, b in zip(np.diag(Qr)[ORI], np.diag(Qg)[ORI]))
        np.fill_diagonal(Qr[ORI, ORI], 0.0)
        np.fill_diagonal(Qg[ORI, ORI], 0.0)
        np.testing.assert_array_equal(Qg, Qr, err_msg=f"dt {us} us")
        np.testing.assert_array_equal(got.st.ws, ref.st.ws)
        assert tuple(got.st.ws) == (dt, math.exp(-dt / 2.0), math.exp(-dt / 3.0))
        for name in ("p", "v", "ba", "bg", "Th"):
            np.testing.assert_allclose(getattr(got.st, name), getattr(ref.st, name), rtol=1e-12, atol=1e-14,
                                       err_msg=name)
        np.testing.assert_allclose(got.st.P, ref.st.P, rtol=0, atol=1e-12 * np.abs(ref.st.P).max())


def test_replay_step_noise_is_the_forward_steps():
    """The replay on the shadow runs the forward path's step: a delayed solution over samples
    spaced by such step lengths is replayed one step per call, and after every call the
    shadow's orientation noise is the rounded square of its last step, as the live state's was
    (a replay with a step of its own, squaring by pow, is one ulp off)."""
    prm, (_, got) = _pair(True)
    steps = _tie_steps(prm.gyro_noise, 40, lo=2000)
    rng = np.random.default_rng(5)
    t = 1_000_000
    got.push_imu(t, *_sample(rng, True))
    got.st.t_us = t
    got.initialized = True
    t_ref = t + sum(steps[:10]) + 321                 # inside a step: the replay splits it
    got.schedule_snapshot(t_ref)
    for us in steps[:30]:
        t += us
        got.push_imu(t, *_sample(rng, True))
        _check_noise(prm, got.st, f"live at {t}")
    C = np.diag([4e-6, 3e-6, 5e-6, 1e-4, 1.2e-4, 0.8e-4])
    sn = got.snap.st                                  # the state at t_ref (a fixed source: Phi = I)
    flags = got.begin_magnetic_update(t_ref, sn.p + 1e-3, sn.Th.copy(), C)
    assert got.replaying, flags
    calls = 0
    while not got.step(1):
        calls += 1
        _check_noise(prm, got.sh, f"replay call {calls}")
    assert calls >= 15
