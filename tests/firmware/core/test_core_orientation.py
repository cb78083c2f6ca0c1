"""The orientation filter (thesis ch. 2, estimate/orientation.py) on the compiled core (its
covariance propagation ct_orientation_propagate, Kalman updates ct_kalman_update and attitude
steps ct_strapdown_rotate) against the same filter on the Python core: the same seeded samples
through initialize / predict / update_acc / update_mag give the same flags and the same
orientation, covariance, gyroscope offset and disturbance to 1e-9 relative (each kernel agrees
to rounding, ~1e-15; over a closed loop of 2000 samples the differences grow to ~1e-12, the
1e-9 of the bench reports' contract is the bound). Skips where the extension is not built."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.estimate.orientation import OrientationFilter, OrientationParams

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

G = np.array([0.0, 0.0, 9.81])
H = np.array([0.2e-4, 0.0, -0.45e-4])       # earth field, global frame (north, west, up), T


def _pair(monkeypatch, **kw):
    prm = OrientationParams.from_config(None, mag_learn_samples=20, **kw)
    ref = OrientationFilter(prm, core.PYTHON)
    got = OrientationFilter(prm, core.load("compiled"))
    assert ref._ck is None and got._ck is not None
    return ref, got


@pytest.mark.parametrize("heading_only", [False, True])
def test_filter_runs_the_same_on_both_cores(heading_only, monkeypatch):
    """20 s at 100 Hz of a turning sensor (one turn passes an angle near pi), with a magnetic
    disturbance switched on halfway and a free-fall sample: flags equal at every sample, the
    states equal to 1e-9 relative at every 50th and at the end. A propagation that forgot to
    compose the transition (Gamma) or the offset block's -T/2 (I + Gamma) is off by far more."""
    rng = np.random.default_rng(31)
    ref, got = _pair(monkeypatch, compass_heading_only=heading_only)
    dt_us = 10_000
    R = Rotation.from_rotvec([0.1, -0.2, 0.3])
    w_true = np.array([0.05, -0.1, 1.2])
    for i in range(2000):
        t = i * dt_us
        R = R * Rotation.from_rotvec(w_true * dt_us * 1e-6)
        Rm = R.as_matrix()
        acc = Rm.T @ G + 0.05 * rng.normal(size=3)
        if i == 1200:
            acc = acc * 0.1                              # free fall: no inclination information
        mag = Rm.T @ (H + (0.1e-4 * np.array([1.0, 0.5, 0.0]) if i > 1000 else 0.0)) + 5e-8 * rng.normal(size=3)
        gyr = w_true + 0.01 * rng.normal(size=3) + 0.02
        out = []
        for f in (ref, got):
            if not f.initialized:
                out.append(f.initialize(t, *acc, *mag))
                continue
            f.predict(t, *gyr)
            out.append((f.update_acc(*acc), f.update_mag(*mag)))
        assert out[0] == out[1], i
        if i % 50 == 0 or i == 1999:
            for name in ("R", "P", "bias", "dist"):
                a, b = getattr(ref, name), getattr(got, name)
                np.testing.assert_allclose(b, a, rtol=0, atol=1e-9 * max(np.abs(a).max(), 1e-30),
                                           err_msg=f"{name} at sample {i}")
    assert got.pred.count == ref.pred.count > 1000
    assert got.upd_acc.count == ref.upd_acc.count and got.upd_mag.count == ref.upd_mag.count
    assert math.degrees(np.linalg.norm(Rotation.from_matrix(got.R.T @ R.as_matrix()).as_rotvec())) < 5.0
