"""Trajectories: determinism, bounds, and analytic derivatives against finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from coiltrack.hil import motion as mo


def all_trajectories():
    return {
        "bench": mo.HandMovedBench(seed=3, duration_s=60.0),
        "arm": mo.ArmAbduction(seed=3),
        "walk-leg": mo.Walking(seed=3, segment="leg"),
        "walk-arm": mo.Walking(seed=3, segment="arm"),
        "walk-back": mo.Walking(seed=3, segment="back"),
        "brownian": mo.BrownianMotion(seed=3, duration_s=30.0),
        "helix": mo.Helix(),
        "static": mo.StaticPose([0.3, 0.1, -0.2], mo.rotvec_to_matrix([0.1, 0.2, 0.3])),
    }


TRAJ = all_trajectories()


def sample_times(traj, n, seed=0, margin_us=5_000):
    rng = np.random.default_rng(seed)
    end = traj.duration_us or 10_000_000
    t = rng.integers(margin_us, end - margin_us, n)
    if isinstance(traj, mo.BrownianMotion):
        # keep the FD stencil inside one Hermite interval (acceleration jumps at nodes)
        phase = t % traj.dt_us
        t = t - phase + np.clip(phase, margin_us, traj.dt_us - margin_us)
    return t


# ---------------------------------------------------------------------------
# Rotation helpers (scipy is the independent reference)
# ---------------------------------------------------------------------------

rotvecs = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(np.array)


@settings(max_examples=60, deadline=None)
@given(rotvecs)
def test_rotvec_matrix_quaternion_against_scipy(v):
    R = mo.rotvec_to_matrix(v)
    ref = Rotation.from_rotvec(v)
    np.testing.assert_allclose(R, ref.as_matrix(), atol=1e-12)
    q = mo.matrix_to_quat(R)
    q_ref = np.roll(ref.as_quat(), 1)  # scipy is scalar-last
    q_ref *= np.sign(q_ref[0]) if q_ref[0] != 0 else 1.0
    np.testing.assert_allclose(q, q_ref, atol=1e-9)
    np.testing.assert_allclose(mo.quat_to_matrix(q), R, atol=1e-12)
    back = mo.matrix_to_rotvec(R)
    np.testing.assert_allclose(mo.rotvec_to_matrix(back), R, atol=1e-9)
    assert np.linalg.norm(back) <= np.pi + 1e-12
    np.testing.assert_allclose(mo.quat_to_matrix(mo.rotvec_to_quat(v)), R, atol=1e-12)
    np.testing.assert_allclose(mo.rotvec_to_matrix(mo.quat_to_rotvec(mo.rotvec_to_quat(v))), R, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(rotvecs, rotvecs)
def test_quaternion_product_composes_rotations(a, b):
    qa, qb = mo.rotvec_to_quat(a), mo.rotvec_to_quat(b)
    np.testing.assert_allclose(
        mo.quat_to_matrix(mo.quat_multiply(qa, qb)), mo.rotvec_to_matrix(a) @ mo.rotvec_to_matrix(b), atol=1e-12
    )
    np.testing.assert_allclose(
        mo.quat_to_matrix(mo.quat_conjugate(qa)), mo.rotvec_to_matrix(a).T, atol=1e-12)


def test_rotation_helpers_edge_cases():
    for v in ([0, 0, 0], [1e-9, 0, 0], [np.pi, 0, 0], [0, -np.pi + 1e-9, 0], [2, 2, 1]):
        R = mo.rotvec_to_matrix(v)
        np.testing.assert_allclose(mo.rotvec_to_matrix(mo.matrix_to_rotvec(R)), R, atol=1e-8)
    # vectorised shapes
    V = np.random.default_rng(0).normal(size=(4, 5, 3))
    assert mo.rotvec_to_matrix(V).shape == (4, 5, 3, 3)
    assert mo.matrix_to_quat(mo.rotvec_to_matrix(V)).shape == (4, 5, 4)
    # Gietler eqs 3-4: R = Rz Ry Rx == scipy extrinsic "xyz" / intrinsic "ZYX"
    th = np.array([0.3, -0.7, 1.9])
    np.testing.assert_allclose(
        mo.euler_zyx_to_matrix(th), Rotation.from_euler("ZYX", th[::-1]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(mo.rot_z(0.4), Rotation.from_euler("z", 0.4).as_matrix(), atol=1e-15)
    np.testing.assert_allclose(mo.rotation_angle(np.eye(3), mo.rot_y(0.3)), 0.3, atol=1e-12)
    np.testing.assert_allclose(mo.vee(mo.skew([1.0, 2.0, 3.0])), [1.0, 2.0, 3.0])


@settings(max_examples=30, deadline=None)
@given(rotvecs, rotvecs)
def test_right_jacobian(v, vd):
    """R^T dR/dt = [J_r(v) v']x, checked by central differences (h = 1e-6, tol 1e-7)."""
    h = 1e-6
    Rm, Rp = mo.rotvec_to_matrix(v - h * vd), mo.rotvec_to_matrix(v + h * vd)
    w_fd = mo.matrix_to_rotvec(Rm.T @ Rp) / (2 * h)
    np.testing.assert_allclose(mo.right_jacobian(v) @ vd, w_fd, atol=1e-7 * (1 + np.linalg.norm(vd)))


# ---------------------------------------------------------------------------
# Determinism
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make",
    [
        lambda s: mo.HandMovedBench(s),
        lambda s: mo.ArmAbduction(s),
        lambda s: mo.Walking(s),
        lambda s: mo.Walking(s, segment="arm"),
        lambda s: mo.BrownianMotion(s),
    ],
)
def test_seed_determinism(make):
    t = np.arange(0, 20_000_000, 97_001)
    a, b, c = make(11), make(11), make(12)
    ka, kb, kc = a.kinematics(t), b.kinematics(t), c.kinematics(t)
    for f in ("position", "velocity", "acceleration", "R", "angular_velocity"):
        np.testing.assert_array_equal(getattr(ka, f), getattr(kb, f))
    assert not np.allclose(ka.position, kc.position)


def test_brownian_independent_of_query_order():
    a, b = mo.BrownianMotion(5), mo.BrownianMotion(5)
    late = 250_123_456
    pa = a.pose(late)[0]
    b.pose(1_000)
    b.pose(77_000_000)
    np.testing.assert_array_equal(b.pose(late)[0], pa)


def test_integer_time_required():
    tr = mo.Helix()
    with pytest.raises(ValueError):
        tr.pose(1.5)
    p1, R1 = tr.pose(2_000_000)
    p2, R2 = tr.pose(2e6)  # integral float accepted
    np.testing.assert_array_equal(p1, p2)
    assert p1.shape == (3,) and R1.shape == (3, 3)
    P, R = tr.pose(np.array([0, 1, 2]))
    assert P.shape == (3, 3) and R.shape == (3, 3, 3)


# ---------------------------------------------------------------------------
# Bounds
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(8))
def test_bench_bounds(seed):
    tr = mo.HandMovedBench(seed, duration_s=120.0)
    t = np.arange(0, tr.duration_us, 20_000)
    k = tr.kinematics(t)
    r = np.linalg.norm(k.position, axis=1)
    assert r.min() >= 0.15 - 1e-12 and r.max() <= 0.80 + 1e-12
    assert k.position[:, 0].min() > 0.05
    speed = np.linalg.norm(k.velocity, axis=1)
    rate = np.linalg.norm(k.angular_velocity, axis=1)
    assert 0.10 <= speed.max() <= 0.20 * 1.01
    assert np.radians(30) <= rate.max() <= np.radians(60) * 1.01
    # rotates about all axes: each sensor axis sweeps well over 60 deg
    R = k.R
    for i in range(3):
        ang = np.degrees(np.arccos(np.clip(R[:, :, i] @ R[0, :, i], -1, 1)))
        assert ang.max() > 60
    # distance covers most of 15..80 cm over two minutes
    assert r.min() < 0.35 and r.max() > 0.6


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(
    "make",
    [
        lambda s: mo.ArmAbduction(s),
        lambda s: mo.ArmAbduction(s, max_abduction_deg=120.0),
        lambda s: mo.Walking(s, segment="leg"),
        lambda s: mo.Walking(s, segment="arm"),
        lambda s: mo.Walking(s, segment="back"),
    ],
)
def test_body_scenarios_stay_in_front_hemisphere(make, seed):
    tr = make(seed)
    t = np.arange(0, 20_000_000, 5_000)
    p = tr.kinematics(t).position
    assert p[:, 0].min() > 0.05
    r = np.linalg.norm(p, axis=1)
    assert r.min() > 0.3 and r.max() < 0.8


def test_walking_is_a_1hz_gait():
    tr = mo.Walking(1, segment="leg")
    t = np.arange(0, 8_000_000, 1_000)
    x = tr.kinematics(t).position[:, 0]
    spec = np.abs(np.fft.rfft(x - x.mean()))
    f = np.fft.rfftfreq(t.size, 1e-3)
    assert f[np.argmax(spec)] == pytest.approx(1.0, abs=0.13)
    # thigh angular rate and knee speed in the range of normal walking
    k = tr.kinematics(t)
    assert 1.0 < np.linalg.norm(k.angular_velocity, axis=1).max() < 5.0
    assert 0.3 < np.linalg.norm(k.velocity, axis=1).max() < 2.0


def test_arm_abduction_reaches_the_commanded_angle():
    tr = mo.ArmAbduction(0, period_s=4.0, max_abduction_deg=90.0)
    t = np.arange(0, 8_000_000, 10_000)
    R = tr.kinematics(t).R
    # sensor x points along the arm: angle from straight down
    down = np.array([0.0, 0.0, -1.0])
    ang = np.degrees(np.arccos(np.clip(R[:, :, 0] @ down, -1, 1)))
    assert 80 < ang.max() < 105 and ang.min() < 15


@pytest.mark.parametrize("seed", range(4))
def test_brownian_default_stays_in_working_volume(seed):
    tr = mo.BrownianMotion(seed)
    t = np.arange(0, 600_000_000, 50_000)  # ten minutes
    p = tr.kinematics(t).position
    r = np.linalg.norm(p, axis=1)
    assert p[:, 0].min() > 0.05
    assert r.min() > 0.12 and r.max() < 0.85


def test_static_grid():
    poses = mo.static_grid()
    assert len(poses) == 9 * 12
    P = np.array([p.pose(0)[0] for p in poses])
    r = np.linalg.norm(P, axis=1)
    assert np.isclose(r.min(), 0.10) and np.isclose(r.max(), 0.80)
    assert P[:, 0].min() > 0.05
    a = mo.static_grid(seed=4)
    b = mo.static_grid(seed=4)
    np.testing.assert_array_equal(a[7].pose(0)[1], b[7].pose(0)[1])
    k = a[3].kinematics(np.array([0, 5_000_000]))
    assert np.all(k.velocity == 0) and np.all(k.acceleration == 0) and np.all(k.angular_velocity == 0)


# ---------------------------------------------------------------------------
# Analytic derivatives vs finite differences, orthonormality
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(TRAJ))
def test_rotation_orthonormal(name):
    tr = TRAJ[name]
    R = tr.kinematics(sample_times(tr, 200)).R
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


@pytest.mark.parametrize("name", list(TRAJ))
def test_derivatives_match_finite_differences(name):
    """Central differences with h = 1 ms (integer us): error ~ h^2/6 x third derivative.

    Tolerance: 1e-4 of the trajectory's peak value of each quantity plus a tiny floor.
    """
    tr = TRAJ[name]
    t = sample_times(tr, 60, seed=1)
    h = 1_000
    k = tr.kinematics(t)
    km, kp = tr.kinematics(t - h), tr.kinematics(t + h)
    hs = h * 1e-6
    v_fd = (kp.position - km.position) / (2 * hs)
    a_fd = (kp.position - 2 * k.position + km.position) / hs**2
    w_fd = mo.matrix_to_rotvec(np.swapaxes(km.R, 1, 2) @ kp.R) / (2 * hs)
    for got, fd in ((k.velocity, v_fd), (k.acceleration, a_fd), (k.angular_velocity, w_fd)):
        scale = np.max(np.linalg.norm(got, axis=1))
        assert np.max(np.linalg.norm(got - fd, axis=1)) <= 1e-4 * scale + 1e-9
    # scalar call agrees with the vectorised call
    np.testing.assert_allclose(tr.angular_velocity(int(t[0])), k.angular_velocity[0], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(tr.acceleration(int(t[0])), k.acceleration[0], rtol=1e-12, atol=1e-15)


# ---------------------------------------------------------------------------
# Gietler's helix and Brownian model
# ---------------------------------------------------------------------------


def test_helix_is_gietler_eq33():
    tr = mo.Helix()
    assert tr.duration_us == 80_000_000
    for ts in (0.0, 3.3, 40.0, 79.9):
        p, R = tr.pose(int(round(ts * 1e6)))
        np.testing.assert_allclose(p, [0.6 * np.cos(0.2 * ts), 0.6 * np.sin(0.2 * ts), 0.01 * ts], atol=1e-12)
        ref = Rotation.from_euler("ZYX", [0.02 * ts, 0.0, 0.0831]).as_matrix()
        np.testing.assert_allclose(R, ref, atol=1e-12)
    # constant body rate: yaw rate 0.02 rad/s seen through the 0.0831 rad roll
    w = tr.angular_velocity(np.array([0, 50_000_000]))
    np.testing.assert_allclose(w, [[0.0, 0.02 * np.sin(0.0831), 0.02 * np.cos(0.0831)]] * 2, atol=1e-15)


def test_brownian_increments_follow_eq10():
    """With the restoring terms off the node increments are eq 8 with covariance eq 10 (MC, 20000 steps).

    Tolerance: 5 % on variances and the correlation (MC standard error ~1 %).
    """
    tr = mo.BrownianMotion(9, sigma_v=0.02, sigma_w=0.3, dt_s=0.05, stiffness=0, damping=0,
                           angular_damping=0, wall_stiffness=0)
    nd = tr.nodes(20_001)
    dt = 0.05
    alpha = np.diff(nd["v"], axis=0)
    beta = np.diff(nd["z"], axis=0) - nd["v"][:-1] * dt
    gamma = np.diff(nd["omega"], axis=0)
    delta = np.diff(nd["theta"], axis=0) - nd["omega"][:-1] * dt
    for (x, y), s in (((alpha, beta), 0.02), ((gamma, delta), 0.3)):
        assert np.var(x) == pytest.approx(s**2 * dt, rel=0.05)
        assert np.var(y) == pytest.approx(s**2 * dt**3 / 3, rel=0.05)
        assert np.mean(x * y) == pytest.approx(s**2 * dt**2 / 2, rel=0.05)
    # position/velocity and angle/rate increments are independent of each other
    assert abs(np.corrcoef(alpha[:, 0], gamma[:, 0])[0, 1]) < 0.03
    # the interpolated pose passes through the nodes with the node velocities
    k = tr.kinematics(nd["t_us"][:50])
    np.testing.assert_allclose(k.position, nd["z"][:50], atol=1e-12)
    np.testing.assert_allclose(k.velocity, nd["v"][:50], atol=1e-12)
    np.testing.assert_allclose(k.R, mo.euler_zyx_to_matrix(nd["theta"][:50]), atol=1e-12)


def test_brownian_gietler_initial_state():
    tr = mo.BrownianMotion.gietler(0)
    nd = tr.nodes()
    assert nd["t_us"][-1] == 20_000_000 and len(nd["t_us"]) == 201
    np.testing.assert_allclose(nd["z"][0], [0.2, -0.2, 0.3])
    np.testing.assert_allclose(nd["v"][0], [0.01, 0.0, -0.005])
    np.testing.assert_allclose(nd["theta"][0], [0.02, -0.05, np.pi / 4])
    with pytest.raises(ValueError):
        tr.pose(-1)
