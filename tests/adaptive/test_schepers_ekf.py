"""The single-coil error-state EKF with inertial propagation.

Truth comes from the bench's own models (``hil.motion`` kinematics, magpylib
fields through ``hil.physics``), not from the firmware's field code.
"""
import math

import numpy as np
import pytest

from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.estimate.single_coil import CORE, ORI, POS, SchepersEKF
from coiltrack.hil import motion, physics

G = np.array([0.0, 0.0, -9.81])


def _coils(kind):
    if kind == "orthogonal":
        return [Coil((0, 0, 0), a, 0.055, 50) for a in np.eye(3)]
    return [Coil((0.02, -0.01, 0.0), (1.0, 0.2, 0.1), 0.055, 50),
            Coil((-0.015, 0.03, 0.01), (0.3, 1.0, -0.2), 0.045, 60),
            Coil((0.0, 0.0, -0.025), (0.2, 0.4, 1.0), 0.06, 40)]


def _simulate(kind, seed, duration_s=20.0, current=0.91, sigma_t=3e-8):
    """Fixed X, Y, Z single-coil updates every 200 ms with IMU propagation at
    100 Hz; returns position errors, NEES and orientation errors (after 3 s)."""
    rng = np.random.default_rng(seed)
    coils = _coils(kind)
    src = physics.Source([physics.SourceCoil(center=c.center, axis=c.axis, radius=c.radius, turns=c.turns)
                          for c in coils])
    traj = motion.HandMovedBench(seed=seed, duration_s=duration_s, r_min=0.15, r_max=0.40, v_max=0.12,
                                 w_max_deg=30.0)
    acc_d, gyr_d = 2e-3, 8.7e-4
    ba, bg = rng.normal(0, 0.02, 3), rng.normal(0, 5e-3, 3)
    ekf = SchepersEKF.from_config(None, gravity=G, acc_noise=acc_d, gyr_noise=gyr_d, acc_bias_rw=1e-4, gyr_bias_rw=1e-5)
    model = SingleCoilModel(coils)
    k0 = traj.kinematics(0)
    ekf.initialize(k0.position + rng.normal(0, 3e-3, 3), k0.R, np.diag([3e-3 ** 2] * 3 + [0.02 ** 2] * 3),
                   0, 0.2, 0.05, 0.02)
    ekf.R[:] = k0.R @ physics.rotvec_to_matrix(rng.normal(0, 0.01, 3))
    dt = 10_000
    sig_amp = sigma_t / math.sqrt(4)
    pend = None
    errs, nees, oerr = [], [], []
    for t in range(0, int(duration_s * 1e6) + 1, dt):
        k = traj.kinematics(t)
        f = k.R.T @ (k.acceleration - G) + ba + rng.normal(0, acc_d * 10, 3)
        w = k.angular_velocity + bg + rng.normal(0, gyr_d * 10, 3)
        ekf.propagate(t, f, w)
        if pend is not None and t >= pend[2] + 60_000:
            c, start, end = pend
            ts = np.arange(start + 10_000, end, 10_000)
            kk = traj.kinematics(ts)
            U = src.unit_fields(kk.position)                  # (coils, n, 3)
            y = np.mean(np.einsum("nji,nj->ni", kk.R, U[c]), axis=0) * current
            y += rng.normal(0, sig_amp, 3)
            ekf.update_single_coil(0, y, np.full(3, sig_amp ** 2), c, current, model)
            ekf.release_clone(0)
            pend = None
        if pend is None and t % 200_000 == 0:
            c = (t // 200_000) % 3
            start = t + 10_000
            pend = (c, start, start + 50_000)
            ekf.schedule_clone(0, start + 25_000)
        if t >= 3_000_000:
            e = k.position - ekf.p
            errs.append(float(np.linalg.norm(e)))
            nees.append(float(e @ np.linalg.solve(ekf.P[POS, POS], e)))
            oerr.append(motion.rotation_angle(k.R, ekf.R))
    return np.array(errs), np.array(nees), np.array(oerr), ekf


@pytest.mark.parametrize("kind", ["orthogonal", "skewed-offset"])
def test_fixed_cycle_single_coil_updates_track_and_are_consistent(kind):
    e, nees, oerr, ekf = _simulate(kind, seed=2)
    rms = math.sqrt(float(np.mean(e ** 2)))
    assert rms < 6e-3, rms
    assert math.degrees(math.sqrt(float(np.mean(oerr ** 2)))) < 0.6
    # normalised estimation error squared: 3 for a consistent filter
    assert 1.5 < float(np.mean(nees)) < 5.0
    assert ekf.rejected <= 2


def test_clone_makes_a_delayed_update_equal_to_an_update_at_its_time():
    """Stochastic cloning: an amplitude measured at t_m and applied 90 ms
    later gives (to first order) the state of a filter updated at t_m."""
    rng = np.random.default_rng(5)
    coils = _coils("orthogonal")
    model = SingleCoilModel(coils)
    p0 = np.array([0.25, 0.05, 0.02])
    R0 = physics.rotvec_to_matrix(np.array([0.2, -0.1, 0.3]))
    P6 = np.diag([2e-3 ** 2] * 3 + [5e-3 ** 2] * 3)
    a = SchepersEKF.from_config(None, gravity=G)
    b = SchepersEKF.from_config(None, gravity=G)
    for f in (a, b):
        f.initialize(p0, R0, P6, 0, 0.01, 0.01, 0.001)
    acc = R0.T @ (np.array([0.1, 0.0, 0.05]) - G)
    gyr = np.array([0.0, 0.0, 0.2])
    y = None
    t_m = 55_000
    for t in range(0, 150_001, 10_000):
        for f in (a, b):
            if t == 50_000:
                f.propagate(t, acc, gyr)
                continue
            f.propagate(t, acc, gyr)
        if t == 0:
            a.schedule_clone(1, t_m)
        if t == 50_000:
            # b: step to t_m exactly, update there, continue
            b.propagate(t_m, acc, gyr)
            model.evaluate(b.p, b.R)
            y = 0.5 * model.h[2] + rng.normal(0, 2e-8, 3)
            y += 0.5 * model.H[2] @ np.r_[1e-3, -2e-3, 0.5e-3, 2e-3, 0.0, -1e-3]
            b.update_single_coil(-1, y, np.full(3, 4e-16), 2, 0.5, model)
    # a: apply the same amplitude now, through the clone taken at t_m
    a.update_single_coil(1, y, np.full(3, 4e-16), 2, 0.5, model)
    a.release_clone(1)
    # b took an extra step boundary at t_m, so compare with tolerances well below sigma
    sig = np.sqrt(np.diag(b.P[CORE, CORE]))
    assert np.all(np.abs(a.p - b.p) < 0.05 * sig[POS])
    dth = physics.matrix_to_rotvec(b.R.T @ a.R)
    assert np.all(np.abs(dth) < 0.05 * sig[ORI])
    Pa, Pb = a.P[CORE, CORE], b.P[CORE, CORE]
    np.testing.assert_allclose(np.diag(Pa), np.diag(Pb), rtol=0.02)
    d = np.sqrt(np.diag(Pb))
    assert np.max(np.abs(Pa - Pb) / np.outer(d, d)) < 0.02


def test_gated_update_leaves_the_state_alone():
    coils = _coils("orthogonal")
    model = SingleCoilModel(coils)
    f = SchepersEKF.from_config(None, gravity=G)
    f.initialize(np.array([0.3, 0.0, 0.0]), np.eye(3), np.diag([1e-6] * 3 + [1e-5] * 3), 0, 0.01, 0.01, 0.001)
    P = f.P.copy()
    p = f.p.copy()
    model.evaluate(f.p, f.R)
    y = 0.9 * model.h[0] * 1.3          # 30 % off: far beyond the gate
    flags = f.update_single_coil(-1, y, np.full(3, 1e-16), 0, 0.9, model)
    assert flags & 1 and f.nis_nominal > 100.0
    np.testing.assert_array_equal(f.P, P)
    np.testing.assert_array_equal(f.p, p)


def test_propagation_allocates_nothing_in_steady_state():
    import tracemalloc

    f = SchepersEKF.from_config(None, gravity=G)
    f.initialize(np.array([0.3, 0.0, 0.0]), np.eye(3), np.diag([1e-6] * 3 + [1e-5] * 3), 0, 0.01, 0.01, 0.001)
    model = SingleCoilModel(_coils("skewed"))
    acc = np.array([0.1, 0.2, 9.8])
    gyr = np.array([0.01, -0.02, 0.3])
    P6 = np.zeros((6, 6))
    pp = np.zeros(3)
    y = np.full(3, 1e-6)
    var = np.full(3, 1e-16)

    def run(t0):
        for k in range(200):
            t = t0 + 10_000 * k
            if k % 20 == 0:
                f.schedule_clone(0, t + 5_000)
            f.propagate(t, acc, gyr)
            f.predict_pose(40_000, P6, pp)
            if k % 20 == 10:
                f.update_single_coil(0, y, var, 1, 0.5, model)
                f.release_clone(0)

    run(0)
    tracemalloc.start()
    s0 = tracemalloc.take_snapshot()
    run(2_000_000)
    s1 = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(st.size_diff for st in s1.compare_to(s0, "filename") if st.size_diff > 0)
    assert grown < 2048, grown
