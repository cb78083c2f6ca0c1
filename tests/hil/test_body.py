"""The moving source of the body-worn bench (``hil.body``, ``World.source_trajectory``):
the source module's IMU against the closed form of a known source motion, the
composed sensor kinematics against the body chain's own world kinematics, the
relative trajectory against finite differences, the field of the moved source
against magpylib with the source moved and rotated in the world, and the
body-worn scenarios' registration and configuration keys."""
from __future__ import annotations

import math

import magpylib
import numpy as np
import pytest

from coiltrack.firmware.config import ConfigError, FirmwareConfig, config_from_dict
from coiltrack.hil import body, motion
from coiltrack.hil import physics as ph
from coiltrack.hil.imu import SourceImuNode
from coiltrack.hil.nodes import ImuSpec, MagSpec
from coiltrack.hil.world import World
from coiltrack.protocol import FrameEncoder
from coiltrack.protocol.schema import ACC_LSB, GYR_LSB

from .test_nodes import Master

G = np.array([0.0, 0.0, -9.81])


class _SpinningSource(motion.Trajectory):
    """Source turning about the world z axis at ``W`` rad/s while its centre oscillates
    along x (``A sin(w t)``) and is lifted by ``H``: closed forms for every derivative."""

    A, w, W, H = 0.05, 2.0 * math.pi * 1.5, 1.2, 0.9

    def _eval(self, t):
        n = t.shape[0]
        p = np.stack([self.A * np.sin(self.w * t), np.zeros(n), np.full(n, self.H)], axis=-1)
        v = np.stack([self.A * self.w * np.cos(self.w * t), np.zeros(n), np.zeros(n)], axis=-1)
        a = np.stack([-self.A * self.w ** 2 * np.sin(self.w * t), np.zeros(n), np.zeros(n)], axis=-1)
        R = motion.rot_z(self.W * t)
        wb = np.tile([0.0, 0.0, self.W], (n, 1))         # about z: the same in body and world
        return p, v, a, R, wb


def test_source_module_imu_matches_the_closed_form_of_a_spinning_oscillating_source():
    """The source module (6 cm below the coil centre, here off-axis at (0.03, 0, -0.06) so the
    centripetal term shows) reads ``R_s^T (a_s + w x (w x R_s d) - g)`` and ``(0, 0, W)``.
    Closed form: ``a_s = (-A w^2 sin wt, 0, 0)``, centripetal ``-W^2 (R_s d)_xy``. Catches a
    dropped centripetal term (0.04 m/s^2, 40 LSB), gravity with the wrong sign, the specific
    force left in the world frame (the source turns 1.2 rad/s) or a still source's reading."""
    offset = np.array([0.03, 0.0, -0.06])
    world = World(ph.thesis_source(), motion.StaticPose([0.0, 0.0, 0.4]), source_trajectory=_SpinningSource())
    m = Master(world)
    spec = ImuSpec(rate_hz=100.0, acc_noise_density=0.0, acc_bias_sigma=0.0, acc_bias_rw=0.0,
                   gyro_noise_density=0.0, gyro_bias_sigma=0.0, gyro_bias_rw=0.0)
    node = SourceImuNode(8, world, imu=spec, mag=MagSpec(noise_t=0.0, offset_t=0.0), position=offset, seed=3)
    m.bench.emulator.nodes.append(node)
    m.bench.emulator.encoders[8] = FrameEncoder(8)
    m.run_to(2_000_000)
    got = [x for x in m.msgs("IMU_SAMPLE") if x.node == 8]
    assert len(got) > 100
    src = _SpinningSource()
    for x in got[::13]:
        t = node.clock.true(node.sync.to_local(x.t_us)) * 1e-6
        Rs = motion.rot_z(src.W * t)
        d = Rs @ offset
        a = np.array([-src.A * src.w ** 2 * math.sin(src.w * t), 0.0, 0.0]) - src.W ** 2 * np.array([d[0], d[1], 0.0])
        f = Rs.T @ (a - G)
        np.testing.assert_allclose(np.array([x.ax, x.ay, x.az]) * ACC_LSB, f, atol=0.6 * ACC_LSB + 2e-3)
        np.testing.assert_allclose(np.array([x.gx, x.gy, x.gz]) * GYR_LSB, [0.0, 0.0, src.W],
                                   atol=0.6 * GYR_LSB)


def test_source_module_magnetometer_sees_the_earth_field_turned_into_the_source_frame():
    """Between pulses the module reads ``R_s^T B_earth`` (a quarter turn after 1.31 s: the
    horizontal component moves from x to -y). Catches the earth field left in the world frame."""
    world = World(ph.thesis_source(), motion.StaticPose([0.0, 0.0, 0.4]), source_trajectory=_SpinningSource())
    for t_us in (0, 400_000, 1_309_000):
        Rs = motion.rot_z(_SpinningSource.W * t_us * 1e-6)
        np.testing.assert_allclose(world.earth_source_frame(t_us), Rs.T @ ph.EARTH_FIELD_T, atol=1e-15)


@pytest.mark.parametrize("name", ["back-flexion", "arm-walking", "leg-walking"])
def test_world_composes_the_sensor_kinematics_of_the_body_chain(name):
    """``World.sensor_kinematics`` from the source's motion and the relative trajectory (no world
    trajectory of the sensor given) equals the chain's own world kinematics of the sensor's
    segment (1e-9): the transport terms ``al x r``, ``w x (w x r)``, ``2 w x R_s q'`` and the
    body rate ``R_q^T R_s^T w + w_q``. Catches a dropped Coriolis term (walking: ~0.3 m/s^2) or
    the source's rate in the wrong frame."""
    src, sen, rel = body.body_worn(name, seed=4, duration_s=5.0)
    world = World(ph.thesis_source(), rel, source_trajectory=src)
    t = np.arange(0, 5_000_000, 37_000, dtype=np.int64)
    k = world.sensor_kinematics(t)
    ref = sen.kinematics(t)
    for a, b in ((k.position, ref.position), (k.velocity, ref.velocity), (k.acceleration, ref.acceleration),
                 (k.R, ref.R), (k.angular_velocity, ref.angular_velocity)):
        np.testing.assert_allclose(a, b, atol=1e-9)


@pytest.mark.parametrize("name", sorted(body.MOVEMENTS))
def test_relative_trajectory_against_finite_differences(name):
    """The sensor in the source frame: velocity, acceleration and body rate equal central
    differences of its pose (h = 1 ms; the differences' own error is the third derivative
    times h^2 / 6: velocity to 5e-5 m/s, acceleration to 2e-3 m/s^2, rate to 1e-4 rad/s, for
    signals up to 1 m/s, 10 m/s^2 and 3 rad/s). Catches a wrong sign of ``w x d`` (the source turns up to 36 deg/s) or the
    relative rate taken in the world frame. Also: the sensor stays in the configured hemisphere
    (z > 0 above the source for the back and arm sites, z < 0 for the thigh) at 40-65 cm."""
    _, _, rel = body.body_worn(name, seed=2, duration_s=12.0)
    t = np.arange(5_000, 12_000_000, 9_973, dtype=np.int64)
    h = 1_000
    k = rel.kinematics(t)
    pm, Rm = rel.pose(t - h)
    pp, Rp = rel.pose(t + h)
    dt = h * 1e-6
    np.testing.assert_allclose(k.velocity, (pp - pm) / (2 * dt), atol=5e-5)
    np.testing.assert_allclose(k.acceleration, (pp - 2 * k.position + pm) / dt ** 2, atol=2e-3)
    w_fd = motion.matrix_to_rotvec(np.swapaxes(Rm, -1, -2) @ Rp) / (2 * dt)
    np.testing.assert_allclose(k.angular_velocity, w_fd, atol=1e-4)
    z = k.position[:, 2]
    assert np.all(z < -0.3) if body.MOVEMENTS[name] == "thigh" else np.all(z > 0.25)
    d = np.linalg.norm(k.position, axis=1)
    assert d.min() > 0.38 and d.max() < 0.65


def test_moving_source_field_against_magpylib_in_the_world_frame():
    """What the sensor reads with the source on a walking pelvis: ``World.field_sensor_frame``
    (coil fields from the relative pose, earth field turned into the source frame) against
    magpylib with each coil's Collection rotated by ``R_s`` and moved by ``p_s`` in the world,
    evaluated at the sensor's world position and turned into the sensor frame by ``R_x^T``
    (relative 1e-9 for the coils, 1e-15 T for the earth field). Catches ``R_s`` applied
    transposed, the earth field not turned, or the relative position taken in the world frame."""
    src, sen, rel = body.body_worn("arm-walking", seed=5, duration_s=5.0)
    world = World(ph.thesis_source(), rel, source_trajectory=src, sensor_world_trajectory=sen)
    for t_us in (250_000, 1_730_000, 3_310_000):
        ps, Rs = src.pose(t_us)
        px, Rx = sen.pose(t_us)
        q, Rq = rel.pose(t_us)
        U = world.unit_fields(q)                               # source frame, per ampere
        for k, coil in enumerate(world.coils):
            col = coil.collection().copy()
            rv = motion.matrix_to_rotvec(Rs)
            ang = float(np.linalg.norm(rv))
            col.rotate_from_angax(ang, rv / ang, anchor=(0.0, 0.0, 0.0), degrees=False)
            col.move(ps)
            B_world = np.asarray(col.getB(px)).reshape(3)
            np.testing.assert_allclose(Rq.T @ U[k], Rx.T @ B_world, rtol=1e-9, atol=1e-18)
        # no current flows: the sensor reads the earth field in its own frame
        np.testing.assert_allclose(world.field_sensor_frame(t_us), Rx.T @ ph.EARTH_FIELD_T, atol=1e-15)
    assert isinstance(magpylib.mu_0, float)


def test_fixed_source_defaults_are_unchanged():
    """No source trajectory: the source sits at the origin, level (identity, zero rates), the
    earth field is the world's and the sensor kinematics are the trajectory's own. Catches the
    body-worn path leaking into every other scenario."""
    traj = motion.Helix(radius=0.3)
    world = World(ph.thesis_source(), traj)
    assert not world.source_moving
    t = np.arange(0, 1_000_000, 50_000, dtype=np.int64)
    k, ref = world.sensor_kinematics(t), traj.kinematics(t)
    np.testing.assert_array_equal(k.acceleration, ref.acceleration)
    np.testing.assert_array_equal(world.earth_source_frame(123), ph.EARTH_FIELD_T)
    _, _, _, Rs, w, al = world.source_kinematics(t)
    np.testing.assert_array_equal(Rs, np.tile(np.eye(3), (t.size, 1, 1)))
    assert not w.any() and not al.any()


def test_body_scenarios_are_registered_with_their_thesis_rows():
    """Every body row of Tables 5.1 / 6.1 has its scenario and variants, a moving source and the
    thesis' figures. Catches a row missing from the README's list or a swapped figure."""
    from coiltrack.tools import scenarios
    from coiltrack.tools.scenarios.body import BODY_ROWS

    assert len(BODY_ROWS) == 8
    for movement, name, _, fig in BODY_ROWS:
        for suffix in ("", "-loose", "-noanet", "-nooffset", "-nomc"):
            sc = scenarios.get(name + suffix)
            assert sc.reference["magnetic_position_rms_mm"] == fig[0]
            assert sc.reference["position_rms_mm"] == fig[2]
            assert sc.sensor.source_imu_id == sc.firmware_config().link.source_imu_id != 0
        assert scenarios.get(name + "-noanet").firmware_config().body.source_acceleration is False
        assert scenarios.get(name + "-nooffset").sensor.source_acc_offset is False
        assert scenarios.get(name).firmware_config().tight.tight_fusion is True
        assert scenarios.get(name + "-loose").firmware_config().tight.tight_fusion is False
    w = scenarios.get("roetenberg-walking-leg").build_world(1, 2.0)
    assert w.source_moving


@pytest.mark.parametrize("key,value", [("source_acceleration", 1), ("source_acc_sigma", -0.1),
                                       ("source_acc_sigma", float("nan"))])
def test_body_config_keys_refused_by_name(key, value):
    """A bad ``[body]`` value is refused with a ConfigError naming ``body.<key>``, from a TOML-shaped
    dict as from the dataclass. Catches a key outside its section or an unchecked value."""
    with pytest.raises(ConfigError, match=f"body.{key}"):
        FirmwareConfig().with_keys(**{key: value}).validate()
    with pytest.raises(ConfigError, match=f"body.{key}"):
        config_from_dict({"body": {key: value}})


class _ShakenSource(motion.Trajectory):
    """Source carried level, shaken along x: ``A sin(w t)``, peak acceleration ``A w^2``
    (1.5 cm at 1.2 Hz: 0.85 m/s^2, about the pelvis' acceleration in walking)."""

    A, w = 0.015, 2.0 * math.pi * 1.2

    def _eval(self, t):
        n = t.shape[0]
        z = np.zeros(n)
        p = np.stack([self.A * np.sin(self.w * t), z, z], axis=-1)
        v = np.stack([self.A * self.w * np.cos(self.w * t), z, z], axis=-1)
        a = np.stack([-self.A * self.w ** 2 * np.sin(self.w * t), z, z], axis=-1)
        return p, v, a, np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))


def _carried_scenario(duration_s: float = 4.0):
    """Source and sensor carried together: the sensor fixed 25 cm from the shaken source."""
    import dataclasses

    from coiltrack.tools import scenarios

    base = scenarios.get("roetenberg-fusion-srcimu")
    pose = motion.StaticPose([0.25, 0.05, -0.04], motion.rotvec_to_matrix([0.2, -0.1, 0.3]))
    return dataclasses.replace(base, name="carried", duration_s=duration_s,
                               build_world=lambda seed, d: World(ph.thesis_source(), pose,
                                                                 source_trajectory=_ShakenSource()))


def test_eq68_a_net_on_the_bench_source_and_sensor_shaken_together(bench_runner):
    """Eq 6.8 on the bench: source and sensor carried together (the sensor fixed 25 cm from the
    source) while the pair is shaken at 0.85 m/s^2. With the source's acceleration left out
    (``source_acceleration = false``) the filter integrates the shaking as relative motion: the
    fused position RMS of the same run (4 s, seed 1, the body scenarios' ``acc_motion_sigma``)
    is at least 1.5x that with ``a_net = a_sensor - a_source`` (measured 71.8 against 37.4 mm;
    8 s: 52.7 against 30.1 mm; the magnetic-only RMS is 1.6 mm: what is left with eq 6.8 is
    the ch. 2 filters' tilt error under the shaking, about 1.9 deg, README "Body-worn
    experiments"). Catches eq 6.8's ``- Phi f_source`` dropped (gravity no longer cancels),
    taken with the wrong sign (twice the shaking) or in the wrong frame."""
    sc = _carried_scenario()
    body_cfg = {"acc_motion_sigma": 0.5}
    with_anet = bench_runner(scenario_obj=sc, duration_s=4.0, cfg=body_cfg)
    without = bench_runner(scenario_obj=sc, duration_s=4.0, cfg={**body_cfg, "source_acceleration": False})
    a, b = with_anet.rep, without.rep
    assert a["source_moving"] and b["source_moving"]
    assert a["magnetic_position_rms_mm"] == pytest.approx(b["magnetic_position_rms_mm"], rel=0.5)
    assert b["position_rms_mm"] > 1.5 * a["position_rms_mm"], (a["position_rms_mm"], b["position_rms_mm"])
