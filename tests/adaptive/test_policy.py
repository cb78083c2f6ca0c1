"""The adaptive policy's accuracy target: the fixed cycle's covariance predicted beside the
filter, bounds on the position and orientation traces, the NIS feedback, and the energy
figures the comparison rests on.

References are independent of the code under test: dense numpy in information form for the
Kalman covariance, closed-form sawtooth means, hand-computed energies, and seeded chi-square
samples with stated bands.
"""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from coiltrack.firmware.actuate.accuracy import FixedCycleReference, fixed_cycle_bounds, nis_bound_factor
from coiltrack.firmware.actuate.coil_choice import ActuationPolicy, CoilChooser, NisMonitor, SingleCoilModel
from coiltrack.firmware.config import ConfigError, config_from_dict
from coiltrack.firmware.estimate.layout import ORI, POS
from coiltrack.firmware.loop import Firmware
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.pose.reference import so3_exp
from coiltrack.tools.outputs import report
from coiltrack.tools.scenarios import thesis as scenarios
from coiltrack.tools.bench.links import inproc_pair


def _coils():
    return [Coil((0, 0, 0), a, 0.055, 50) for a in np.eye(3)]


def _pose(rng):
    d = np.array([1.0, 0.3, -0.2]) + 0.1 * rng.normal(size=3)
    return d / np.linalg.norm(d) * 0.25, so3_exp(rng.normal(size=3))


def _P6(rng):
    A = rng.normal(size=(6, 6)) * np.r_[[3e-3] * 3, [8e-3] * 3][:, None]
    return A @ A.T + np.diag([1e-6] * 3 + [1e-5] * 3)


def _brute_trace(P6, model, var_amp, rel, currents, i_limit, smax, smin):
    """Trace-mode choice by dense eq 4 (Schepers & Veltink 2010) for every coil and current:
    weights 1 / sum(smax^2) per group, the group furthest beyond its summed bound is the
    target, the smallest current that brings that group's summed variance to sum(smin^2)."""
    smax, smin = np.asarray(smax), np.asarray(smin)
    w = np.r_[[1.0 / np.sum(smax[:3] ** 2)] * 3, [1.0 / np.sum(smax[3:] ** 2)] * 3]
    d = np.diag(P6)
    target = 0 if d[:3].sum() * w[0] >= d[3:].sum() * w[3] else 3
    table = {}
    for c in range(model.n):
        for i in currents:
            if i > i_limit[c] * (1 + 1e-12):
                continue
            H = i * model.H[c]
            Rv = (var_amp + (rel * i) ** 2 * float(model.h[c] @ model.h[c])) * np.eye(3)
            Pp = P6 - P6 @ H.T @ np.linalg.inv(H @ P6 @ H.T + Rv) @ H @ P6
            table[(c, i)] = (float(np.sum(d * w) - np.sum(np.diag(Pp) * w)), np.diag(Pp).copy())
    ref_i = {c: max([i for (cc, i) in table if cc == c], default=None) for c in range(model.n)}
    red = {c: table[(c, ref_i[c])][0] for c in ref_i if ref_i[c] is not None}
    coil = max(red, key=red.get)
    goal = float(np.sum(smin[target:target + 3] ** 2))
    ok = sorted(i for (cc, i) in table if cc == coil and table[(cc, i)][1][target:target + 3].sum() <= goal)
    return coil, (ok[0] if ok else ref_i[coil]), target


def test_trace_chooser_matches_dense_eq4():
    """Trace bounds: the coil with the largest reduction of ``tr P_pos / B_pos + tr P_ori /
    B_ori``, the target group and the smallest current reaching its summed sigma_min, against
    dense eq 4. Catches the chooser picking a coil that reduces the uncertainty less, a
    target taken per axis instead of per group, or the current goal read from one axis."""
    rng = np.random.default_rng(11)
    currents = (0.05, 0.1, 0.2, 0.4, 0.91)
    smax = [2e-3, 3e-3, 2.5e-3, 5e-3, 4e-3, 6e-3]
    smin = [0.9 * s for s in smax]
    ch = CoilChooser(3, currents, smax, smin, rel_model=1e-3, trace=True)
    ch.set_bounds(smax, smin)
    model = SingleCoilModel(_coils())
    for _ in range(40):
        p, R = _pose(rng)
        P6 = _P6(rng)
        model.evaluate(p, R)
        lim = rng.uniform(0.3, 1.0, 3)
        coil = ch.choose(P6, model, (2e-8) ** 2, lim)
        bc, bi, bt = _brute_trace(P6, model, (2e-8) ** 2, 1e-3, currents, lim, smax, smin)
        assert (coil, ch.target) == (bc, bt)
        assert ch.current == pytest.approx(bi)


def test_trace_policy_fires_on_the_summed_bound_only():
    """Per axis, one variance over its bound fires; with trace bounds only the summed
    variance against the summed bounds counts (the RMS is the root of the trace). Catches a
    trace policy that still fires per axis, or one that compares a sum with one bound."""
    b = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0]) * 1e-3
    axis, trace = ActuationPolicy(b, 10 ** 9), ActuationPolicy(b, 10 ** 9, trace=True)
    trace.set_bounds(b)
    P = np.diag(np.r_[np.array([1.2, 0.5, 0.5]) * 1e-6, [1e-6] * 3])
    assert axis.due(P, 0, 0) and not trace.due(P, 0, 0)
    P = np.diag(np.r_[np.array([1.2, 0.9, 0.95]) * 1e-6, [1e-6] * 3])
    assert trace.due(P, 0, 0)
    P = np.diag(np.r_[[0.1e-6] * 3, np.array([4.5, 4.0, 3.6]) * 1e-6])   # orientation 12.1 > 12
    assert trace.due(P, 0, 0)
    assert trace.worst(P) == pytest.approx(math.sqrt(12.1 / 12.0))


class _FakeFilter:
    """The two things the reference reads of the live filter: its transition over dt
    (constant-velocity position, a gyro-offset coupling) and its pose."""

    def __init__(self, p, R):
        self.p, self.R = p, R

    @staticmethod
    def F_of(dt):
        F = np.eye(15)
        F[0:3, 3:6] = dt * np.eye(3)
        F[6:9, 12:15] = -dt * np.eye(3)
        F[3:6, 6:9] = dt * np.array([[0, -9.81, 0], [9.81, 0, 0], [0, 0, 0]])
        return F

    @staticmethod
    def q_of(dt):
        return np.r_[[1e-8 * dt] * 3, [4e-6 * dt] * 3, [4e-7 * dt] * 3, [1e-10 * dt] * 3, [1e-10 * dt] * 3]

    def core_transition(self, Fv, q, dt):
        np.asarray(Fv)[:] = self.F_of(dt)
        q[:] = self.q_of(dt)


def test_fixed_cycle_reference_matches_information_form_updates():
    """The fixed cycle's covariance carried beside the filter: propagation with the filter's
    F and Q at every IMU sample, and at each pulse's mid time the eq-4 update of that coil at
    its nominal current, against dense numpy (``P+ = (P^-1 + H^T R^-1 H)^-1``, information
    form, not the Joseph form under test) on the same timetable. Catches a dropped process
    noise, a pulse at the wrong time or of the wrong coil, the orientation columns of H left
    out, the current missing from H or R."""
    rng = np.random.default_rng(3)
    p, R = _pose(rng)
    ekf = _FakeFilter(p, R)
    model = SingleCoilModel(_coils())
    cur = (0.91, 0.6, 0.45)
    var_amp, rel, cs = (1.7e-8) ** 2, 1e-3, 1e-3
    ref = FixedCycleReference(cur, 200_000, 600_000, 140_000, 29_000, var_amp, rel, cs, 300_000)
    A = rng.normal(size=(15, 15)) * 1e-3
    P0 = A @ A.T + 1e-6 * np.eye(15)
    t0 = 150_000
    ref.start(P0, t0)
    # the reference, dense: same timetable, information-form updates
    model.evaluate(p, R)
    mids = sorted((200_000 + k * 600_000 + j * 140_000 + 29_000, j) for k in range(5) for j in range(3))
    P = P0.copy()
    t = t0
    avg = np.r_[np.diag(P0)[POS], np.diag(P0)[ORI]]
    elapsed = 0
    for t_imu in range(t0 + 10_000, 2_200_001, 10_000):
        events = [(m, j) for m, j in mids if t < m <= t_imu]
        for m, j in events + [(t_imu, None)]:
            if m > t:
                dt = (m - t) * 1e-6
                F = _FakeFilter.F_of(dt)
                P = F @ P @ F.T + np.diag(_FakeFilter.q_of(dt))
                # the mean since the start, then exponential over 300 ms
                elapsed += m - t
                a = 1.0 if elapsed <= m - t else (m - t) / min(elapsed, 300_000)
                avg += a * (np.r_[np.diag(P)[POS], np.diag(P)[ORI]] - avg)
                t = m
            if j is not None:
                H = np.zeros((3, 15))
                H[:, POS] = cur[j] * model.H[j][:, :3]
                H[:, ORI] = cur[j] * model.H[j][:, 3:]
                r = var_amp + ((rel * cur[j]) ** 2 + cs ** 2) * float(model.h[j] @ model.h[j])
                P = np.linalg.inv(np.linalg.inv(P) + H.T @ H / r)
        ref.step(ekf, t_imu, model)
    assert ref.pulses == sum(1 for m, _ in mids if t0 < m <= 2_200_000) == 11
    np.testing.assert_allclose(ref.P, P, rtol=1e-7, atol=1e-14)
    np.testing.assert_allclose(ref.avg, avg, rtol=1e-7, atol=1e-16)


def test_bounds_hold_the_fixed_cycles_mean_variance():
    """A variance climbing linearly from ``m^2 sigma_max^2`` to ``sigma_max^2`` between
    pulses has the time mean ``ratio^2 avg`` when sigma_max comes from
    ``fixed_cycle_bounds``: checked by integrating the sawtooth. Catches the (1 + m^2) / 2
    factor dropped or the ratio applied to the std instead of the variance."""
    avg = np.array([1e-6, 2e-6, 3e-6, 1e-5, 2e-5, 3e-5])
    mx, mn = np.zeros(6), np.zeros(6)
    for ratio, m in ((1.0, 0.9), (1.3, 0.5)):
        fixed_cycle_bounds(avg, ratio, m, mx, mn)
        s = np.linspace(0.0, 1.0, 100_001)
        for k in range(6):
            saw = (m * mx[k]) ** 2 + s * (mx[k] ** 2 - (m * mx[k]) ** 2)
            assert float(np.trapezoid(saw, s)) == pytest.approx(ratio ** 2 * avg[k], rel=1e-9)
        np.testing.assert_allclose(mn, m * mx)


def test_nis_excess_is_one_for_consistent_innovations_and_the_scale_otherwise():
    """``NisMonitor.excess``: the mean of NIS / dof. Seeded 3-dof chi-square NIS values give
    a time mean of 1 within 0.06 (4 standard errors of 3000 samples, sqrt(2/3/3000) = 0.015);
    innovations 2x larger than their covariance says (NIS x 4) give 4 within 0.25. Catches
    the dof left out, the nominal instead of the used NIS, or no averaging."""
    rng = np.random.default_rng(5)
    for scale, tol in ((1.0, 0.06), (4.0, 0.25)):
        mon = NisMonitor(window=8, dof=3, gate=math.inf, feedback_updates=30)
        vals = []
        for x in rng.chisquare(3, 3000) * scale:
            mon.add_used(float(x))
            vals.append(mon.excess)
        assert float(np.mean(vals[100:])) == pytest.approx(scale, abs=tol)
    assert nis_bound_factor(0.7, 4.0) == 1.0 and nis_bound_factor(2.5, 4.0) == 2.5
    assert nis_bound_factor(9.0, 4.0) == 4.0 and nis_bound_factor(float("nan"), 4.0) == 1.0


def _tracker(**kw):
    fw_end, _ = inproc_pair()
    fw = Firmware(scenarios.schepers_adaptive_config(**kw), fw_end)
    return fw.tracker.actuation, fw.tracker.actuation.views[0]


def test_the_policy_tightens_its_bounds_by_the_nis_excess():
    """With ``nis_feedback`` the bounds on the standard deviations are divided by the root
    of the NIS excess (errors twice the covariance: a covariance four times smaller is
    held); without it the NIS does not move them. Catches a policy ignoring the NIS."""
    for fb in (True, False):
        pol, s = _tracker(nis_feedback=fb, accuracy_target="stated", sigma_range_ref_m=0.0)
        s.pp[:] = (0.25, 0.0, 0.0)
        s.sensor.monitor.excess = 1.0
        pol._bounds(s)
        base = s.smax6.copy()
        np.testing.assert_allclose(base, [0.002] * 3 + [math.radians(0.3)] * 3)
        s.sensor.monitor.excess = 4.0
        pol._bounds(s)
        np.testing.assert_allclose(s.smax6, base / 2.0 if fb else base, rtol=1e-12)


def test_energy_counts_the_winding_and_the_supply():
    """``report.energy``: coil energy ``sum I^2 R t`` (each coil's own R), charge
    ``sum I t``, supply ``V sum I t``, run time from the battery, the median pulse length.
    Hand numbers; catches a dropped R, t or V, or squares where the charge is linear."""
    world = SimpleNamespace(coils=[SimpleNamespace(resistance=2.0), SimpleNamespace(resistance=3.0)], supply_v=6.0)
    ex = [{"coil": 0, "current_a": 0.5, "start_us": 0, "end_us": 60_000},
          {"coil": 1, "current_a": -0.2, "start_us": 100_000, "end_us": 160_000},
          {"coil": 0, "current_a": 0.91, "start_us": 300_000, "end_us": 400_000}]
    e = report.energy(ex, world, 10.0, battery_wh=14.4)
    coil = 0.25 * 2 * 0.06 + 0.04 * 3 * 0.06 + 0.91 ** 2 * 2 * 0.1
    charge = 0.5 * 0.06 + 0.2 * 0.06 + 0.91 * 0.1
    assert e["coil_energy_j"] == pytest.approx(coil, abs=1e-4)
    assert e["coil_charge_c"] == pytest.approx(charge, abs=1e-4)
    assert e["supply_energy_j"] == pytest.approx(6.0 * charge, abs=1e-4)
    assert e["projected_runtime_h"] == pytest.approx(14.4 / (6.0 * charge / 10.0), abs=0.01)
    assert e["pulse_ms"] == 60.0 and e["pulses_per_s"] == 0.3


@pytest.mark.parametrize("key, value", [("accuracy_target", "best"), ("fixed_accuracy_ratio", 0.0),
                                        ("adaptive_min_ratio", 1.5), ("bound_on", "norm"),
                                        ("nis_feedback_max", 0.5), ("flip_every_us", 0),
                                        ("reference_settle_drop", 1.0), ("reference_settle_drop", -0.1),
                                        ("reference_settle_drop", float("nan")), ("adaptive_current_step_a", -1e-3),
                                        ("adaptive_current_step_a", 0.5)])
def test_bad_policy_values_are_refused_naming_the_key(key, value):
    """A bad value of the new section is refused with its qualified name."""
    with pytest.raises(ConfigError) as e:
        config_from_dict({"adaptive": {key: value}})
    assert e.value.key == f"adaptive.{key}"


def test_range_law_is_normalised_by_its_own_mean():
    """The bound's range law ``r^(2e) / mean(r^(2e))`` (e = 4/3 position, 1 orientation): a
    sensor spending equal time at 0.2 and 0.4 m gets 2 / (1 + 2^(2e)) of the mean bound at 0.2 m
    (closed form). Catches the exponent applied to the std instead of the variance, or a law
    not divided by its mean (the run's mean variance would then not be the fixed cycle's)."""
    ekf = _FakeFilter(np.array([0.2, 0.0, 0.0]), np.eye(3))
    model = SingleCoilModel(_coils())
    ref = FixedCycleReference((0.91,) * 3, 10 ** 9, 600_000, 140_000, 29_000, 1e-16, 0.0, 0.0, 1e12,
                              4.0 / 3.0, 1.0)
    ref.start(np.eye(15) * 1e-6, 0)
    for k in range(1, 201):
        ekf.p[0] = 0.2 if (k - 1) // 10 % 2 == 0 else 0.4
        ref.step(ekf, k * 10_000, model)
    for g, e in ((0, 4.0 / 3.0), (1, 1.0)):
        assert ref.law_now(0.2, g) == pytest.approx(2.0 / (1.0 + 2.0 ** (2 * e)), rel=1e-9)
        assert ref.law_now(0.4, g) == pytest.approx(2.0 * 2.0 ** (2 * e) / (1.0 + 2.0 ** (2 * e)), rel=1e-9)


def test_duty_check_is_the_overlap_of_the_remembered_pulses():
    """PulseBook.duty_ok against the on-time summed directly: the last DUTY_HIST pulses of the coil
    (start, end), each clipped to the window ``[end - coil_duty_window_us, end]`` of the pulse asked
    about, plus that pulse's length, against ``duty_margin coil_max_duty coil_duty_window_us``.
    Random pulse trains, more pulses than remembered, some overlapping the window's start; the other
    coils' pulses do not count. Catches a pulse of another coil counted, a start read for an end, or
    a pulse straddling the window's start counted whole."""
    from coiltrack.firmware.actuate.single_coil_pulses import DUTY_HIST, PulseBook
    from coiltrack.firmware.config import FirmwareConfig

    cfg = FirmwareConfig()
    sched = SimpleNamespace(command=lambda coil, current, start, length: (1, current))
    rng = np.random.default_rng(4)
    lim = cfg.adaptive.duty_margin * cfg.limits.coil_max_duty * cfg.limits.coil_duty_window_us
    seen = set()
    for trial in range(40):
        book = PulseBook(cfg, 3, sched, (), 30_000, 20_000, 0)
        hist = [[], [], []]
        t = 0
        for _ in range(int(rng.integers(1, 3 * DUTY_HIST))):
            c = int(rng.integers(3))
            length = int(rng.integers(20_000, 90_000))
            t += int(rng.integers(0, 60_000))
            sl = book.command(c, 0.5, t, length, True)
            book.release(book.slots[sl])
            hist[c].append((t, t + length))
            t += length
        for _ in range(10):
            c = int(rng.integers(3))
            start = t + int(rng.integers(0, 400_000))
            length = int(rng.integers(20_000, 90_000))
            end = start + length
            w0 = end - cfg.limits.coil_duty_window_us
            on = length + sum(min(e, end) - max(s, w0) for s, e in hist[c][-DUTY_HIST:] if e > w0)
            assert book.duty_ok(c, start, length) == (on <= lim)
            seen.add(on <= lim)
    assert seen == {True, False}


@pytest.mark.parametrize("impl", ["python", "compiled"])
def test_a_lost_track_is_judged_on_each_position_variance_and_the_silence(impl):
    """The decision's first test, every tick (``_decide``, its constants and covariance views bound
    at composition): a sensor whose position variance on any axis is above ``acquire_sigma_m^2``,
    or with no update for more than four ``adaptive_max_interval_us``, is reacquired; an orientation
    variance or an off-diagonal term that large, the variance at the bound or the silence at four
    intervals, is not. Catches a diagonal read with the wrong stride or block, an axis dropped,
    ``>`` for ``>=``, the silence's factor or bound lost."""
    if impl == "compiled":
        pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
    fw_end, _ = inproc_pair()
    cfg = scenarios.schepers_adaptive_config().with_(core={"impl": impl})
    fw = Firmware(cfg, fw_end)
    act = fw.tracker.actuation
    calls = []
    fw.tracker.reacquire = lambda s: calls.append("lost")
    act._decide_own = lambda now_us, held: calls.append("decide")
    now = 50_000_000
    quiet = 4 * cfg.adaptive.adaptive_max_interval_us
    big = cfg.adaptive.acquire_sigma_m * cfg.adaptive.acquire_sigma_m
    for s in act._sens:
        s.ekf.initialized = True
        s.last_update_us = now
    s = act._sens[-1]
    P = s.ekf.P

    def judged(i=None, j=None, x=0.0, last=now):
        P.fill(0.0)
        if i is not None:
            P[i, j] = x
        s.last_update_us = last
        calls.clear()
        act._decide(now)
        return calls[0]

    assert judged() == "decide"
    for k in range(3):
        assert judged(POS.start + k, POS.start + k, big * 1.0001) == "lost", k
        assert judged(POS.start + k, POS.start + k, big) == "decide", k
        assert judged(ORI.start + k, ORI.start + k, 10.0 * big) == "decide", k
    assert judged(POS.start, POS.start + 1, 10.0 * big) == "decide"
    assert judged(POS.start + 2, POS.start + 1, 10.0 * big) == "decide"
    assert judged(last=now - quiet - 1) == "lost"
    assert judged(last=now - quiet) == "decide"
