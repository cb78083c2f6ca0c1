"""Single-coil measurement model and the adaptive coil/current choice.

The chooser is checked against a brute-force evaluation of Schepers &
Veltink 2010 eq 4 for every coil and every candidate current (plain numpy,
``np.linalg.inv``), on an orthogonal co-centred source and on a source whose
coils are tilted, offset and of different sizes.
"""
import math

import numpy as np
import pytest

from coiltrack.firmware.actuate.coil_choice import (ActuationPolicy, CoilChooser, NisMonitor, SingleCoilModel, chi2_upper,
                                  current_ladder, posterior_pose_variances, saturation_current_limit)
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.pose.reference import so3_exp
from coiltrack.hil import physics


def orthogonal():
    return [Coil((0, 0, 0), a, 0.055, 50) for a in np.eye(3)]


def skewed():
    """Three coils, none orthogonal to another, none at the origin, unequal."""
    return [Coil((0.02, -0.01, 0.0), (1.0, 0.2, 0.1), 0.055, 50),
            Coil((-0.015, 0.03, 0.01), (0.3, 1.0, -0.2), 0.045, 60),
            Coil((0.0, 0.0, -0.025), (0.2, 0.4, 1.0), 0.06, 40)]


def random_pose(rng, r=(0.15, 0.45)):
    d = rng.normal(size=3)
    d[0] = abs(d[0]) + 0.3
    p = d / np.linalg.norm(d) * rng.uniform(*r)
    R = so3_exp(rng.normal(size=3))
    return p, R


def random_P6(rng):
    A = rng.normal(size=(6, 6)) * np.r_[[3e-3] * 3, [8e-3] * 3][:, None]
    return A @ A.T + np.diag([1e-6] * 3 + [1e-5] * 3)


@pytest.mark.parametrize("coils", [orthogonal(), skewed()], ids=["orthogonal", "skewed-offset"])
@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_single_coil_jacobian_matches_finite_differences(coils, model):
    """H_c = [R^T dB_c/dp, [h_c]x] (eqs 9-11) against central differences of
    h = R^T B_c(p) with R_true = R exp([dtheta]x)."""
    rng = np.random.default_rng(4)
    m = SingleCoilModel(coils, model)
    m2 = SingleCoilModel(coils, model)
    for _ in range(5):
        p, R = random_pose(rng)
        m.evaluate(p, R)
        for j in range(6):
            e = np.zeros(6)
            e[j] = 1e-6
            hp = np.empty((3, 3))
            hm = np.empty((3, 3))
            m2.evaluate(p + e[:3], R @ so3_exp(e[3:]))
            hp[:] = m2.h
            m2.evaluate(p - e[:3], R @ so3_exp(-e[3:]))
            hm[:] = m2.h
            fd = (hp - hm) / 2e-6
            for c in range(3):
                np.testing.assert_allclose(m.H[c, :, j], fd[c], rtol=2e-5, atol=1e-9 * np.abs(m.h[c]).max())


def test_single_coil_field_matches_magpylib_for_an_offset_tilted_coil():
    """The exact model (eqs 6-7) of a coil that is neither at the origin nor
    on an axis agrees with an independent magpylib loop."""
    coils = skewed()
    m = SingleCoilModel(coils, "exact")
    ref = physics.Source([physics.SourceCoil(center=c.center, axis=c.axis, radius=c.radius, turns=c.turns)
                          for c in coils])
    rng = np.random.default_rng(1)
    for _ in range(5):
        p, R = random_pose(rng, (0.1, 0.5))
        m.evaluate(p, R)
        B = ref.unit_fields(p[None, :])[:, 0, :]          # (coils, 3), source frame, per ampere
        np.testing.assert_allclose(m.h, B @ R, rtol=1e-9, atol=1e-15)


def brute_force(P6, model, var_amp, rel, currents, i_limit, sigma_max, sigma_min, cur_sigma=0.0):
    """Every coil at every current: posterior by eq 4 with a dense inverse."""
    var_amp = np.broadcast_to(np.asarray(var_amp, dtype=float), (model.n,))
    w = 1.0 / np.asarray(sigma_max) ** 2
    j0 = float(np.sum(np.diag(P6) * w))
    target = int(np.argmax(np.diag(P6) * w))
    table = {}
    for c in range(model.n):
        for i in currents:
            if i > i_limit[c] * (1 + 1e-12):
                continue
            H = i * model.H[c]
            Rv = (var_amp[c] + ((rel * i) ** 2 + cur_sigma ** 2) * float(model.h[c] @ model.h[c])) * np.eye(3)
            K = P6 @ H.T @ np.linalg.inv(H @ P6 @ H.T + Rv)
            Pp = P6 - K @ H @ P6
            table[(c, i)] = (j0 - float(np.sum(np.diag(Pp) * w)), np.diag(Pp).copy())
    ref_i = {c: max([i for (cc, i) in table if cc == c], default=None) for c in range(model.n)}
    red = {c: table[(c, ref_i[c])][0] for c in ref_i if ref_i[c] is not None}
    coil = max(red, key=red.get)
    ok = sorted(i for (cc, i) in table if cc == coil and table[(cc, i)][1][target] <= sigma_min[target] ** 2)
    current = ok[0] if ok else ref_i[coil]
    return coil, current, target, red, table[(coil, current)][1]


@pytest.mark.parametrize("coils", [orthogonal(), skewed()], ids=["orthogonal", "skewed-offset"])
def test_coil_and_current_choice_matches_brute_force(coils):
    rng = np.random.default_rng(7)
    currents = current_ladder(0.05, 1.5, 12)
    smax = [4e-3] * 3 + [0.01] * 3
    smin = [2e-3] * 3 + [0.005] * 3
    ch = CoilChooser(3, currents, smax, smin, rel_model=1e-3, current_sigma=1e-3)
    model = SingleCoilModel(coils)
    checked_reached = checked_limited = 0
    for trial in range(60):
        p, R = random_pose(rng)
        P6 = random_P6(rng)
        model.evaluate(p, R)
        i_limit = rng.uniform(0.3, 2.0, 3)
        if trial % 7 == 0:
            i_limit[rng.integers(3)] = 0.01      # a coil that may carry no candidate current
        # the amplitude variance: one for all coils, or per coil (inflated where pulses proved inconsistent)
        var_amp = (1.5e-8) ** 2 if trial % 2 else (1.5e-8) ** 2 * rng.uniform(1.0, 30.0, 3)
        coil = ch.choose(P6, model, var_amp, i_limit)
        bc, bi, bt, bred, bvar = brute_force(P6, model, var_amp, 1e-3, currents, i_limit, smax, smin, 1e-3)
        assert ch.target == bt
        assert coil == bc, (trial, ch.reduction, bred)
        assert ch.current == pytest.approx(bi)
        np.testing.assert_allclose(ch.var_after, bvar, rtol=1e-9, atol=1e-18)
        for c, r in bred.items():
            assert ch.reduction[c] == pytest.approx(r, rel=1e-9, abs=1e-12)
        # the chosen coil reduces the normalised uncertainty at least as much as any other
        assert all(ch.reduction[coil] >= r - 1e-12 for r in bred.values())
        if ch.reached:
            checked_reached += 1
            assert ch.var_after[bt] <= smin[bt] ** 2
        else:
            checked_limited += 1
            assert ch.current == pytest.approx(max(i for i in currents if i <= i_limit[coil] * (1 + 1e-12)))
    assert checked_reached > 5 and checked_limited > 5


def test_smaller_current_when_the_sensor_is_near():
    """The current that reaches sigma_min falls with the distance (field ~ r^-3)."""
    coils = orthogonal()
    ch = CoilChooser(3, current_ladder(0.02, 1.5, 24), [4e-3] * 3 + [0.02] * 3, [2e-3] * 3 + [0.01] * 3)
    model = SingleCoilModel(coils)
    P6 = np.diag([3e-3 ** 2] * 3 + [0.005 ** 2] * 3)
    P6[0, 0] = 4.5e-3 ** 2                  # x beyond its bound: the target
    u = np.array([0.9, 0.3, 0.3])
    u /= np.linalg.norm(u)
    cur = []
    for r in (0.15, 0.25, 0.35, 0.5):
        model.evaluate(r * u, np.eye(3))
        ch.choose(P6, model, (1.5e-8) ** 2, np.full(3, 1.5))
        assert ch.target == 0
        cur.append(ch.current)
    assert cur == sorted(cur) and cur[0] < 0.1 * cur[-1]


def test_posterior_variances_never_exceed_the_prior():
    rng = np.random.default_rng(3)
    model = SingleCoilModel(skewed())
    out = np.zeros(6)
    A = np.zeros((3, 6))
    M = np.zeros((3, 3))
    for _ in range(50):
        p, R = random_pose(rng)
        model.evaluate(p, R)
        P6 = random_P6(rng)
        c = int(rng.integers(3))
        np.matmul(model.H[c], P6, out=A)
        np.matmul(A, model.H[c].T, out=M)
        for i in (0.0, 0.01, 0.5, 2.0):
            assert posterior_pose_variances(P6, A, M, float(model.h[c] @ model.h[c]), i, 1e-16, 0.0, out)
            assert np.all(out <= np.diag(P6) * (1 + 1e-12))
            assert np.all(out >= -1e-18)


def test_saturation_limit_keeps_every_axis_in_range():
    hu = np.array([40e-6, -80e-6, 10e-6])        # T/A in the sensor frame
    quiet = np.array([20e-6, 30e-6, -45e-6])
    rng_t = 163.84e-6
    i = saturation_current_limit(hu, quiet, rng_t, 0.9, 1.2)
    # the binding axis is y: (0.9 * range - 30 uT) / (1.2 * 80 uT)
    assert i == pytest.approx((0.9 * rng_t - 30e-6) / (1.2 * 80e-6))
    B = np.abs(quiet) + i * 1.2 * np.abs(hu)
    assert np.all(B <= 0.9 * rng_t + 1e-15)
    assert saturation_current_limit(np.zeros(3), quiet, rng_t, 0.9, 1.0) == math.inf
    assert saturation_current_limit(hu, np.array([200e-6, 0, 0]), rng_t, 0.9, 1.0) == 0.0


def test_policy_fires_on_the_bound_or_the_interval():
    pol = ActuationPolicy([4e-3] * 3 + [0.01] * 3, max_interval_us=1_000_000)
    P = np.diag([3e-3 ** 2] * 3 + [0.005 ** 2] * 3)
    assert not pol.due(P, 500_000, 0) and pol.reason == 0
    assert pol.due(P, 1_000_000, 0) and pol.reason == 2
    P[4, 4] = 0.011 ** 2
    assert pol.due(P, 10, 0) and pol.reason == 1
    assert pol.worst(P) == pytest.approx(1.1)
    P[4, 4] = np.nan
    assert pol.due(P, 10, 0)


def test_chi2_upper_is_close_to_the_exact_quantile():
    stats = pytest.importorskip("scipy.stats")
    for dof in (3, 6, 12, 24, 48):
        for z, p in ((2.326, 0.99), (3.09, 0.999)):
            assert chi2_upper(dof, z) == pytest.approx(stats.chi2.ppf(p, dof), rel=0.02 if dof < 6 else 0.01)


def test_nis_monitor_flags_a_persistent_excess_and_recovers():
    mon = NisMonitor(window=8, dof=3, min_count=4)
    rng = np.random.default_rng(0)
    for _ in range(40):                       # consistent: chi2(3)
        mon.add(float(np.sum(rng.normal(size=3) ** 2)))
        assert mon.r_scale >= 1.0
    assert not mon.inconsistent
    for _ in range(6):                        # a disturbance: NIS ~ 30
        mon.add(30.0 + float(np.sum(rng.normal(size=3) ** 2)))
    assert mon.inconsistent and mon.r_scale == pytest.approx(mon.mean / 3.0)
    for _ in range(8):
        mon.add(float(np.sum(rng.normal(size=3) ** 2)))
    assert not mon.inconsistent and mon.r_scale == 1.0
    mon.add(math.nan)                          # never raises
    assert mon.mean > 1e6


def test_current_ladder():
    lad = current_ladder(0.05, 0.91, 10)
    assert len(lad) == 10 and lad[0] == 0.05 and lad[-1] == 0.91
    r = np.diff(np.log(lad))
    assert np.allclose(r, r[0], rtol=1e-2)
    assert current_ladder(0.5, 0.5, 4) == (0.5,)


def test_pose_cov_update_is_eq4():
    from coiltrack.firmware.actuate.coil_choice import PoseCovUpdate

    rng = np.random.default_rng(11)
    model = SingleCoilModel(skewed())
    u = PoseCovUpdate()
    for _ in range(20):
        p, R = random_pose(rng)
        model.evaluate(p, R)
        P6 = random_P6(rng)
        c = int(rng.integers(3))
        i = float(rng.uniform(0.05, 1.5))
        H = i * model.H[c]
        Rv = (1e-16 + (2e-3 * i) ** 2 * float(model.h[c] @ model.h[c])) * np.eye(3)
        ref = P6 - P6 @ H.T @ np.linalg.inv(H @ P6 @ H.T + Rv) @ H @ P6
        P = P6.copy()
        assert u.apply(P, model.H[c], model.h[c], i, 1e-16, 2e-3)
        np.testing.assert_allclose(P, ref, rtol=1e-7, atol=1e-14 * np.abs(P6).max())


def test_unreached_goal_takes_the_share_at_the_least_current():
    """``unreached_share``: where no allowed current brings the target to ``sigma_min``, the
    least ladder current whose posterior target variance is within ``(1 - share)`` of the way
    from the largest current's posterior to the prior (``best + (1 - share)(prior - best)``,
    dense eq 4 by brute force); share 0 keeps the largest current. With a field-model error
    the information ``I^2 / (a + b I^2)`` saturates, so this current is well below the largest.
    Catches the share applied to the posterior instead of the reduction, a goal left at
    ``sigma_min`` (the largest current again), or a current that is not the least."""
    rng = np.random.default_rng(11)
    currents = current_ladder(0.05, 1.5, 24)
    smax = [4e-3] * 3 + [0.01] * 3
    smin = [1e-6] * 3 + [1e-6] * 3                # out of reach of any one pulse
    model = SingleCoilModel(orthogonal())
    i_limit = np.full(3, 1.5)
    share, rel, va = 0.8, 3e-3, (1.5e-8) ** 2
    ch = CoilChooser(3, currents, smax, smin, rel_model=rel, current_sigma=1e-3, unreached_share=share)
    ch0 = CoilChooser(3, currents, smax, smin, rel_model=rel, current_sigma=1e-3)
    smaller = 0
    for trial in range(20):
        p, R = random_pose(rng, (0.15, 0.25))
        P6 = random_P6(rng)
        model.evaluate(p, R)
        coil = ch.choose(P6, model, va, i_limit)
        assert ch0.choose(P6, model, va, i_limit) == coil and ch0.current == 1.5
        bc, _, bt, _, _ = brute_force(P6, model, va, rel, currents, i_limit, smax, smin, 1e-3)
        assert coil == bc and ch.target == bt and not ch.reached

        def post(i):
            H = i * model.H[coil]
            Rv = (va + ((rel * i) ** 2 + 1e-6) * float(model.h[coil] @ model.h[coil])) * np.eye(3)
            K = P6 @ H.T @ np.linalg.inv(H @ P6 @ H.T + Rv)
            return float(np.diag(P6 - K @ H @ P6)[bt])
        goal = post(1.5) + (1.0 - share) * (P6[bt, bt] - post(1.5))
        want = min(i for i in currents if post(i) <= goal)
        assert ch.current == pytest.approx(want, rel=1e-12)
        assert ch.var_after[bt] == pytest.approx(post(want), rel=1e-9)
        smaller += want < 1.0
    assert smaller >= 10
