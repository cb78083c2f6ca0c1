"""The fixed cycle's actual error beside its filter's belief (``reference_error = "actual"``,
``firmware_py/actuate/accuracy_actual.py``): equal to the belief when the model error is as
assumed; the sensitivity update against a Monte Carlo of the errors it describes; the model-error
estimate from NIS draws of known expectation; the means following the actual covariance; the key
refused out of its values.

References: a seeded Monte Carlo of ``(I - K H) x - K v`` (independent of the code's products), the
expectation ``E[nis / 3] = 1 - x + q x`` drawn from a scaled chi-square, and the plain reference
(``accuracy.FixedCycleReference``) run beside it.
"""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.actuate.accuracy import FixedCycleReference
from coiltrack.firmware.actuate.accuracy_actual import (MIN_WEIGHT, ActualBudgetReference, ActualCycleReference,
                                                        ModelErrorEstimate)
from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.estimate.layout import ORI, POS
from coiltrack.firmware.model.field import Coil

REL = 3e-3
VAR = 2e-16


class _Drifting:
    """A live filter at a fixed pose whose error state grows with white process noise."""

    def __init__(self):
        self.p = np.array([0.12, 0.05, 0.03])
        self.R = np.eye(3)
        self.P = np.eye(15) * 1e-6

    def core_transition(self, Fv, q, dt):
        F = np.asarray(Fv)
        F[:] = np.eye(15)
        F[0:3, 3:6] = dt * np.eye(3)                      # position from velocity
        q[:] = 1e-7 * dt


def _model():
    return SingleCoilModel([Coil((0, 0, 0), a, 0.055, 50) for a in np.eye(3)], core=core.PYTHON)


def _refs(kind=ActualCycleReference):
    args = ((0.91,) * 3, 0, 600_000, 140_000, 29_000, VAR, REL, 1e-3, 30e6)
    return kind(*args, core=core.PYTHON), FixedCycleReference(*args, core=core.PYTHON)


def _run(refs, seconds=3.0):
    ekf, model = _Drifting(), _model()
    P0 = np.diag(np.exp(np.random.default_rng(3).normal(size=15))) * 1e-6
    for r in refs:
        r.start(P0, 0)
    for k in range(1, int(seconds * 100) + 1):
        for r in refs:
            r.step(ekf, k * 10_000, model)
    return ekf, model


def test_actual_is_the_belief_when_the_model_error_is_as_assumed():
    """Before the estimate has its weight (q = 1) the sensitivity update with the optimal gain is
    the Joseph update itself: ``Pa = P`` and the means are the plain reference's (a wrong sign
    in ``I - K H`` or a dropped ``K R K^T`` breaks it)."""
    act, plain = _refs()
    _run((act, plain))
    assert act.pulses == plain.pulses >= 14
    np.testing.assert_allclose(act.Pa, act.P, rtol=1e-9, atol=1e-22)
    np.testing.assert_allclose(act.P, plain.P, rtol=1e-12, atol=1e-24)
    np.testing.assert_allclose(act.avg, plain.avg, rtol=1e-9)


def test_sensitivity_update_against_a_monte_carlo():
    """One reference pulse with ``q = 0.25``: ``Pa`` after it is the covariance of
    ``(I - K H) x - K v`` with ``x ~ N(0, Pa_before)``, ``v ~ N(0, R_a)``, ``R_a = R_f - 0.75
    rho^2 I^2 |h|^2`` (400k seeded draws, the pose diagonal within 1.5 %)."""
    act, _ = _refs()
    act.est.sxx, act.est.sxy = 100.0, 25.0                 # q = 0.25
    assert act.est.q() == pytest.approx(0.25)
    ekf, model = _Drifting(), _model()
    rng = np.random.default_rng(11)
    A = rng.normal(size=(15, 15)) * 1e-3
    P0 = A @ A.T + np.eye(15) * 1e-7
    act.start(P0, 0)
    act.Pa[:] = 0.5 * P0                                   # the actual errors smaller than the belief
    Pa0 = act.Pa.copy()
    P_before = act.P.copy()
    act._pulse(ekf, model, 1)
    K, H = act.upd.K.copy(), act.upd.H.copy()
    model.evaluate(ekf.p, ekf.R)
    hn2 = float(model.h[1] @ model.h[1])
    ra = act.upd.R[0, 0] - 0.75 * REL * REL * 0.91 ** 2 * hn2
    assert ra > 0 and ra < act.upd.R[0, 0]
    # K is the filter's own (optimal for P and R_f)
    S = H @ P_before @ H.T + act.upd.R
    np.testing.assert_allclose(K, P_before @ H.T @ np.linalg.inv(S), rtol=1e-8)
    n = 400_000
    x = rng.multivariate_normal(np.zeros(15), Pa0, size=n, method="cholesky")
    v = rng.normal(size=(n, 3)) * np.sqrt(ra)
    e = x - (x @ H.T) @ K.T - v @ K.T
    mc = np.einsum("ni,ni->i", e, e) / n
    for blk in (POS, ORI):
        np.testing.assert_allclose(np.diag(act.Pa)[blk], mc[blk], rtol=0.015)


def test_model_error_estimate_recovers_q_from_nis_draws():
    """NIS drawn as ``3 (1 - x + q x) chi2_3 / 3`` for amplitudes of various model shares ``x``:
    the least squares finds ``q`` (0.4) within 0.05; 1 until the weight ``MIN_WEIGHT``; clamped
    at 1 above (a filter understating its errors is not made to look honest)."""
    rng = np.random.default_rng(5)
    est = ModelErrorEstimate()
    assert est.q() == 1.0
    q, a = 0.4, 1e-16
    for _ in range(3000):
        y = rng.normal(size=3) * 10 ** rng.uniform(-5.5, -4.5)
        b = REL * REL * float(y @ y)
        x = b / (a + b)
        nis = (1.0 - x + q * x) * rng.chisquare(3)
        est.add(nis, *y, a, REL)
    assert est.sxx > MIN_WEIGHT
    assert est.q() == pytest.approx(q, abs=0.05)
    hi = ModelErrorEstimate()
    hi.sxx, hi.sxy = 10.0, 30.0
    assert hi.q() == 1.0


def test_means_follow_the_actual_covariance_and_hold_mean_composes():
    """With q < 1 the actual covariance falls below the belief, and so do the means the bounds hold,
    in both reference kinds (``reference_hold`` "bound" and "mean")."""
    for kind in (ActualCycleReference, ActualBudgetReference):
        act, plain = _refs(kind)
        act.est.sxx, act.est.sxy = 100.0, 20.0              # q = 0.2
        _run((act, plain))
        assert np.all(np.diag(act.Pa)[POS] < np.diag(act.P)[POS])
        assert np.all(act.avg < plain.avg)
        np.testing.assert_allclose(act.P, plain.P, rtol=1e-12, atol=1e-24)   # the belief unchanged


def test_the_key_is_refused_out_of_its_values():
    from coiltrack.firmware.config import FirmwareConfig

    with pytest.raises(Exception, match="reference_error"):
        FirmwareConfig().with_keys(reference_error="truth").validate()
