"""The fixed-cycle reference's settling, and the current refined between the ladder's rungs.

Settling (``accuracy.FixedCycleReference``, ``settle_drop``): until the Riccati recursion of the
fixed schedule is near its fixed point the reference's mean follows the present covariance, so
a start's convergence does not inflate the bound the policy holds for the rest of a run.
Refinement (``coil_choice.CoilChooser``, ``step_a``): the smallest current that brings the
target to ``sigma_min``, to the driver's resolution, checked against the closed form of eq 4
for a measurement that observes the position axes one by one.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from coiltrack.firmware.actuate.accuracy import FixedCycleReference
from coiltrack.firmware.actuate.coil_choice import CoilChooser, current_ladder
from coiltrack.firmware.estimate.layout import GYR, ORI, POS
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.actuate.coil_choice import SingleCoilModel


class _Filter:
    """Constant-velocity position, orientation driven by the gyro offset (``d ori/dt = -gyr``),
    tilt coupled to velocity through gravity: the offsets are seen only through the orientation
    they build up, as in the single-coil EKF (its eq 6.17 structure)."""

    def __init__(self, p):
        self.p = p
        self.R = np.eye(3)

    def core_transition(self, Fv, q, dt):
        F = np.asarray(Fv)
        F[:] = np.eye(15)
        F[0:3, 3:6] = dt * np.eye(3)
        F[6:9, 12:15] = -dt * np.eye(3)
        F[3:6, 6:9] = dt * np.array([[0, -9.81, 0], [9.81, 0, 0], [0, 0, 0]])
        q[:] = np.r_[[1e-8 * dt] * 3, [4e-6 * dt] * 3, [4e-7 * dt] * 3, [1e-10 * dt] * 3, [1e-12 * dt] * 3]


def _reference(settle_drop, warmup_us=0):
    coils = [Coil((0, 0, 0), a, 0.055, 50) for a in np.eye(3)]
    model = SingleCoilModel(coils)
    ref = FixedCycleReference((0.91,) * 3, 0, 600_000, 140_000, 29_000, (1.7e-8) ** 2, 3e-3, 1e-3, 30e6,
                              warmup_us=warmup_us, settle_drop=settle_drop)
    P0 = np.eye(15) * 1e-6
    P0[POS, POS] = np.eye(3) * 1e-4
    P0[ORI, ORI] = np.eye(3) * (0.17 ** 2)
    P0[GYR, GYR] = np.eye(3) * (0.02 ** 2)         # the filter's start: offsets unknown to 0.02 rad/s
    ref.start(P0, 0)
    return ref, _Filter(np.array([0.25, 0.05, -0.03])), model


def _gyr(P):
    return float(np.trace(P[GYR, GYR]))


def test_reference_follows_the_present_covariance_until_the_offsets_settle():
    """Cycle by cycle: while the gyroscope-offset variance still falls by more than
    ``settle_drop`` per cycle the means equal the present pose variances exactly; the cycle it
    falls by less is the one the reference settles at, and from then on the means are the time
    means since that instant (checked against the variances integrated here at each sample).
    Catches the mean taken from the start (the old behaviour: a bound several times the
    steady state), a settling tested on the pose variance (which moves with the range), or the
    drop compared the wrong way round."""
    drop = 0.05
    ref, ekf, model = _reference(drop)
    prev = _gyr(ref.P)
    settled_at = None
    acc = np.zeros(6)
    t_mean = 0
    for k in range(1, 60 * 100 + 1):                 # 60 s of IMU samples at 100 Hz
        t = k * 10_000
        was, n0 = ref.settled, ref.pulses
        ref.step(ekf, t, model)
        pres = np.r_[np.diag(ref.P)[POS], np.diag(ref.P)[ORI]]
        if ref.pulses != n0 and ref.coil == 0:       # a cycle's last pulse (the offsets' rows move by q dt only since)
            g = _gyr(ref.P)
            if not was and ref.settled:
                settled_at = t
                assert g > (1.0 - drop) * prev * (1 - 1e-9)
            elif not ref.settled:
                assert g <= (1.0 - drop) * prev * (1 + 1e-9)
            prev = g
        if not ref.settled:
            np.testing.assert_allclose(ref.avg, pres, rtol=1e-12)
        elif settled_at is not None and t > settled_at:
            acc += pres * 10_000
            t_mean += 10_000
    assert settled_at is not None and 3e6 < settled_at < 50e6
    # the time mean since settling; sampled here after each step (after its pulse's update), by
    # the reference before each pulse: the sawtooth's two samplings differ by a few per cent
    np.testing.assert_allclose(ref.avg, acc / t_mean, rtol=0.08)
    # and well below a mean taken from the start, whose first seconds are the start's
    ref0, _, _ = _reference(0.0)
    for k in range(1, 60 * 100 + 1):
        ref0.step(ekf, k * 10_000, model)
    assert ref0.avg[3:].sum() > 1.5 * ref.avg[3:].sum()


def test_settle_drop_zero_is_the_mean_after_the_warmup():
    """``settle_drop = 0``: settled as soon as ``warmup_us`` has passed, whatever the offsets do."""
    ref, ekf, model = _reference(0.0, warmup_us=1_000_000)
    for k in range(1, 101):
        ref.step(ekf, k * 10_000, model)
        assert ref.settled == (k * 10_000 > 1_000_000)
    for k in range(101, 131):
        ref.step(ekf, k * 10_000, model)
    assert ref.settled


def _chooser(step, trace, ladder):
    smax = (2e-3,) * 3 + (5e-3,) * 3
    smin = (1.5e-3,) * 3 + (4e-3,) * 3
    return CoilChooser(1, ladder, smax, smin, rel_model=3e-3, current_sigma=1e-3, trace=trace, step_a=step)


class _Model:
    """One coil that observes the position axes one by one: ``Hu = g [I3 0]``, ``|hu|^2 = h2``."""

    def __init__(self, g, h2):
        self.H = np.zeros((1, 3, 6))
        self.H[0, :, :3] = g * np.eye(3)
        self.h = np.zeros((1, 3))
        self.h[0, 0] = math.sqrt(h2)


@pytest.mark.parametrize("trace", [False, True])
def test_refined_current_is_the_closed_form_rounded_up(trace):
    """Eq 4 for a position axis observed alone, prior ``p``, measurement variance
    ``r(I) = a + b I^2`` (``a = var_amp + (current_sigma |hu|)^2``, ``b = (rel |hu|)^2``) and gain
    ``g I``: the posterior ``p r / (g^2 I^2 p + r)`` reaches ``v`` at
    ``I^2 = a (p - v) / (v g^2 p - b (p - v))``. The chooser's current is that value rounded up
    to the 1 mA resolution, not the ladder's next rung; without a resolution it is the rung.
    Catches a bisection on the wrong side, the rounding down (the goal then missed), or the
    model error's saturation left out of the search."""
    g, h2, va = 2e-5, (4e-6) ** 2, (2e-8) ** 2
    a, b = va + (1e-3) ** 2 * h2, (3e-3) ** 2 * h2
    p = (2.2e-3) ** 2
    P6 = np.diag([p, (1e-3) ** 2, (1e-3) ** 2, 1e-6, 1e-6, 1e-6])
    if trace:                                        # the group's trace: the other two axes observed too
        P6[1, 1] = P6[2, 2] = p
    v = (1.5e-3) ** 2
    i_star = math.sqrt(a * (p - v) / (v * g * g * p - b * (p - v)))
    ladder = current_ladder(0.05, 0.91, 16)
    model = _Model(g, h2)
    ch = _chooser(1e-3, trace, ladder)
    assert ch.choose(P6, model, va, np.array([0.91])) == 0 and ch.reached
    assert ch.current == pytest.approx(math.ceil(i_star / 1e-3) * 1e-3, abs=1e-12)
    assert ch.var_after[0] <= v * (1 + 1e-12)
    rung = min(c for c in ladder if c >= i_star)
    assert rung - ch.current > 0.005                  # the ladder would have overshot
    ch0 = _chooser(0.0, trace, ladder)
    ch0.choose(P6, model, va, np.array([0.91]))
    assert ch0.current == pytest.approx(rung)
