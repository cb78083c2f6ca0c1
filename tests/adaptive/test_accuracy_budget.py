"""The fixed cycle's accuracy held as a running mean (``reference_hold = "mean"``,
``firmware_py/actuate/accuracy_budget.py``): the hold factor's closed form, the filter's own
mean beside the reference's, the closed loop's fixed point, and the policy's use of it.

References: closed forms (``2 - own / target``; the exponential mean of a constant; the
fixed point of ``own <- own + a (f(own) T - own)``), independent of the code under test.
"""
import math

import numpy as np
import pytest

from coiltrack.firmware.actuate.accuracy import FixedCycleReference, fixed_cycle_bounds
from coiltrack.firmware.actuate.accuracy_budget import HOLD_MAX, HOLD_MIN, MeanBudgetReference, hold_factor
from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.config import ConfigError, config_from_dict
from coiltrack.firmware.estimate.layout import ORI, POS
from coiltrack.firmware.loop import Firmware
from coiltrack.firmware.model.field import Coil
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.scenarios import thesis as scenarios


class _Still:
    """A live filter that does not move: identity transition, no process noise, a given P."""

    def __init__(self, P):
        self.p = np.array([0.25, 0.0, 0.0])
        self.R = np.eye(3)
        self.P = P

    def core_transition(self, Fv, q, dt):
        np.asarray(Fv)[:] = np.eye(15)
        q[:] = 0.0


def _ref(avg_us=1e6):
    # no reference pulse in the run (first cycle at 1000 s): the reference's P stays its start
    return MeanBudgetReference((0.91,) * 3, 10 ** 9, 600_000, 140_000, 29_000, 1e-16, 0.0, 0.0, avg_us)


def _model():
    return SingleCoilModel([Coil((0, 0, 0), a, 0.055, 50) for a in np.eye(3)])


def test_hold_factor_closed_form_and_limits():
    """``2 - own / target``: on target 1, no variance spent 2, half again as much 0.5; clamped
    to [HOLD_MIN, HOLD_MAX]; a NaN mean or no target never loosens. Catches the sign of the
    correction (``2 + own / target`` loosens a filter in deficit) and a missing clamp."""
    assert hold_factor(1.0, 1.0) == 1.0
    assert hold_factor(0.0, 1.0) == min(2.0, HOLD_MAX)
    assert hold_factor(1.5e-6, 1e-6) == pytest.approx(0.5, rel=1e-12)
    assert hold_factor(3.0, 1.0) == HOLD_MIN
    assert hold_factor(float("nan"), 1.0) == HOLD_MIN
    assert hold_factor(1.0, 0.0) == 1.0


def test_own_mean_and_held_variances_closed_form():
    """A filter holding twice the reference's pose variances: its own mean is the trace of its
    P (the mean of a constant), and the held mean is the reference's times
    ``2 - 2 / ratio^2`` in both groups (0.347 at ratio 1.1). Catches the own mean taken over the
    reference's P instead of the filter's, a group's trace mixed with the other's, or the
    ratio left out of the target."""
    rng = np.random.default_rng(7)
    d = np.exp(rng.normal(size=15)) * 1e-6
    P0 = np.diag(d)
    live = np.diag(2.0 * d)
    ref = _ref()
    ref.start(P0, 0)
    ekf = _Still(live)
    model = _model()
    for k in range(1, 101):
        ref.step(ekf, k * 10_000, model)
    assert ref.own[0] == pytest.approx(2.0 * d[POS].sum(), rel=1e-12)
    assert ref.own[1] == pytest.approx(2.0 * d[ORI].sum(), rel=1e-12)
    np.testing.assert_allclose(ref.avg, np.r_[d[POS], d[ORI]], rtol=1e-12)
    held = ref.held_avg(1.1)
    f = 2.0 - 2.0 / 1.21
    np.testing.assert_allclose(held, f * np.r_[d[POS], d[ORI]], rtol=1e-12)
    np.testing.assert_allclose(ref.factor, [f, f], rtol=1e-12)
    # the plain reference holds its own mean whatever the filter does
    plain = FixedCycleReference((0.91,) * 3, 10 ** 9, 600_000, 140_000, 29_000, 1e-16, 0.0, 0.0, 1e6)
    plain.start(P0, 0)
    assert plain.held_avg(1.1) is plain.avg


def test_a_filter_following_its_held_mean_converges_to_the_target():
    """Closed loop: a filter whose variance is at every sample ``ratio^2`` times the held mean
    (``f T``, what ``fixed_cycle_bounds`` asks of it) has an
    own mean that converges to the target ``T = ratio^2 avg`` (fixed point of
    ``own <- own + a (2 T - own - own)``), from a deficit (own 3 T) and from a surplus
    (own T / 5), monotonically. Catches a correction that diverges or settles off target."""
    d = np.full(15, 1e-6)
    for start in (3.0, 0.2):
        ref = _ref(avg_us=2e5)
        ref.start(np.diag(d), 0)
        live = np.diag(start * 1.21 * d)
        ekf = _Still(live)
        model = _model()
        ref.step(ekf, 10_000, model)
        err = []
        for k in range(2, 600):
            held = ref.held_avg(1.1)
            live[POS, POS] = np.diag(1.21 * held[:3])       # the bounds hold ratio^2 x the held mean
            live[ORI, ORI] = np.diag(1.21 * held[3:])
            ref.step(ekf, k * 10_000, model)
            err.append(abs(ref.own[0] / (1.21 * 3e-6) - 1.0))
        assert err[-1] < 1e-6
        assert all(b <= a + 1e-15 for a, b in zip(err[100:], err[101:]))


def test_the_policy_bounds_hold_the_carried_mean():
    """``reference_hold = "mean"`` gives each sensor a :class:`MeanBudgetReference`, and the
    policy's bounds are ``fixed_cycle_bounds`` of its held mean: a filter in deficit (own mean
    1.5 times the target) is held to half the reference's mean variance. ``"bound"`` keeps the
    plain reference. A bad value is refused naming the key."""
    fw_end, _ = inproc_pair()
    cfg = scenarios.schepers_adaptive_config(reference_hold="mean", nis_feedback=False)
    pol = Firmware(cfg, fw_end).tracker.actuation
    v = pol.views[0]
    ref = v.sensor.ref
    assert isinstance(ref, MeanBudgetReference)
    ref.avg[:] = [4e-6, 2e-6, 1e-6, 3e-5, 2e-5, 1e-5]
    ref.law[:] = -1.0                      # no range law yet: law_now 1
    ref.active = True
    ref.own[0] = 1.5 * 7e-6
    ref.own[1] = 1.5 * 6e-5
    v.pp[:] = (0.25, 0.0, 0.0)
    pol._bounds(v)
    mx, mn = np.zeros(6), np.zeros(6)
    fixed_cycle_bounds(0.5 * ref.avg, 1.0, cfg.adaptive.adaptive_min_ratio, mx, mn)
    np.testing.assert_allclose(v.smax6, mx, rtol=1e-12)
    fw_end, _ = inproc_pair()
    plain = Firmware(scenarios.schepers_adaptive_config(), fw_end).tracker.actuation.views[0].sensor.ref
    assert type(plain) is FixedCycleReference
    with pytest.raises(ConfigError) as e:
        config_from_dict({"adaptive": {"reference_hold": "median"}})
    assert e.value.key == "adaptive.reference_hold"
    assert math.isfinite(float(v.smax6[0]))


def test_mean_hold_and_unreached_share_ticks_allocate_no_numpy_array():
    """The carried mean (``reference_hold = "mean"``) and the unreached goal
    (``unreached_share``) in a live 8 s run: no tick creates a numpy array, and the held
    factors moved off 1 (the own mean is being tracked)."""
    from coiltrack.tools.bench.runner import BenchSetup
    from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available
    from coiltrack.tools.scenarios import get

    if not available():
        pytest.skip("numpy memory handler API not reachable")
    sc = get("schepers-adaptive")
    cfg = sc.firmware_config().with_keys(reference_hold="mean", unreached_share=0.8, adaptive_current_step_a=0.001,
                                         baseline_sharing="ignore", reference_settle_drop=0.0, pulse_length="fixed")
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 3, 8.0, emu_end)
    fw = Firmware(cfg, fw_end)
    counter = NumpyAllocationCounter()
    allocating = 0
    for t in range(0, 8_000_001, cfg.timing.tick_us):
        bench.emulator.step(t)
        before = counter.count
        with counter:
            fw.tick(t)
        allocating += counter.count != before
    assert fw.status()["adaptive_updates"] > 40
    assert allocating == 0
    ref = fw.tracker.sensors[next(iter(fw.tracker.sensors))].ref
    assert isinstance(ref, MeanBudgetReference) and np.all(ref.own > 0.0) and np.any(ref.factor != 1.0)
