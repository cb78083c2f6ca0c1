"""The World wires the physics objects in: cross-checked against
``physics.MagneticScene`` (which sums the same objects independently, for
arrays of points), plus switching objects on and off, carried objects, the
ground truth of a pulse's flat part and of its steady amplitude."""
from __future__ import annotations

import math

import numpy as np
import pytest

from coiltrack.hil import motion
from coiltrack.hil import physics as ph
from coiltrack.hil import world as W


def _world(traj=None, objects=()):
    return W.World(ph.thesis_source(), traj or motion.StaticPose(np.array([0.22, 0.06, -0.05]),
                                                                motion.rotvec_to_matrix([0.3, -0.2, 0.5])),
                   objects=objects)


def _pulses(w):
    for k, cur in enumerate(w.currents):
        cur.add_pulse(10_000 + k * 100_000, 60_000, 1.5)


def test_world_equals_magnetic_scene_with_all_objects():
    """Coils + eddy conductor + ferro sphere + conducting sphere + earth: World (scalar path,
    one point per call) against MagneticScene (array path): rel. 1e-9."""
    eddy = ph.EddyConductor(np.array([-0.08, 0.02, 0.0]), coupling=5e-3, tau_s=2e-3)
    ferro = ph.FerroSphere(np.array([0.15, -0.12, 0.05]), radius=0.01, mu_r=300.0)
    sphere = ph.ConductingSphere(np.array([0.05, 0.2, -0.1]), radius=0.02, sigma=3.5e7, n_modes=40)
    w = _world(objects=[W.EddyObject(eddy), W.FerroObject(ferro), W.ConductingSphereObject(sphere)])
    _pulses(w)
    scene = ph.MagneticScene(w.source, w.currents, ph.EarthField(), eddies=[eddy], ferros=[ferro], spheres=[sphere])
    p, R = w.pose(0)
    for t in (5_000, 10_000, 10_300, 11_000, 15_000, 69_990, 70_400, 112_000, 250_000):
        ref = scene.field(p[None, :], t)[0]
        got = w.field_source_frame(t)
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(w.field_sensor_frame(t), R.T @ ref, rtol=1e-9, atol=1e-15)


def test_objects_switch_on_and_off():
    metal = W.MetalObject(position=[0.25, 0.06, -0.05], t_on_us=50_000, t_off_us=80_000)
    w = _world(objects=[metal])
    base = _world()
    assert np.allclose(w.field_source_frame(49_999), base.field_source_frame(49_999))
    assert not np.allclose(w.field_source_frame(50_000), base.field_source_frame(50_000))
    assert np.allclose(w.field_source_frame(80_000), base.field_source_frame(80_000))


def test_carried_metal_moves_with_the_sensor():
    """A carried part's field, seen in the sensor frame, is the same wherever a static earth-only
    world puts the sensor if the applied field is the same: here the earth field only (no pulse),
    rotating the whole set-up about the earth field's axis changes nothing."""
    metal = W.MetalObject(carried_offset=[0.0, 0.06, 0.0], sigma=0.0)
    axis = ph.EARTH_FIELD_T / np.linalg.norm(ph.EARTH_FIELD_T)
    Rs = [motion.axis_angle_to_matrix(axis, a) for a in (0.0, 0.7, 2.0)]
    seen = []
    for R in Rs:
        w = W.World(ph.thesis_source(), motion.StaticPose(np.array([0.4, 0.1, 0.0]), R), objects=[metal])
        # field of the part alone, in the sensor frame
        p, _ = w.pose(0)
        seen.append(R.T @ metal.field_at(w, 0, p, R))
    # rotating sensor + part about the earth field's axis leaves the part's field fixed in the sensor frame
    for s in seen[1:]:
        np.testing.assert_allclose(s, seen[0], rtol=1e-9, atol=1e-16)
    # and its magnitude matches the induced dipole of a sphere in a uniform 49 uT field at 6 cm
    a, mu = metal.radius, metal.mu_r
    m = 4 * math.pi * a**3 / ph.MU0 * (mu - 1) / (mu + 2) * np.linalg.norm(ph.EARTH_FIELD_T)
    bmax = ph.MU0 / (4 * math.pi) * 2 * m / 0.06**3
    for s in seen:
        assert 0.45 * bmax <= np.linalg.norm(s) <= 1.0001 * bmax


def test_hard_iron_is_fixed_in_the_sensor_frame():
    traj = motion.Helix(radius=0.3)
    w0 = W.World(ph.thesis_source(), traj)
    w1 = W.World(ph.thesis_source(), traj, objects=[W.HardIron([1e-4, -2e-5, 3e-5], t_on_us=0)])
    for t in (0, 1_000_000, 7_654_321):
        np.testing.assert_allclose(w1.field_sensor_frame(t) - w0.field_sensor_frame(t), [1e-4, -2e-5, 3e-5],
                                   atol=1e-15)


def test_precompute_cache_gives_identical_fields():
    traj = motion.HandMovedBench(seed=3, duration_s=10.0)
    a = W.World(ph.thesis_source(), traj)
    b = W.World(ph.thesis_source(), traj)
    _pulses(a)
    _pulses(b)
    ts = list(range(0, 300_000, 8_333))
    b.precompute(ts)
    for t in ts:
        np.testing.assert_allclose(b.field_sensor_frame(t), a.field_sensor_frame(t), rtol=1e-12, atol=1e-18)


def test_flat_start_is_l_over_r_without_conductors():
    """Pure L/R rise from rest: |I - I_ss| / I_ss = exp(-t/tau) < tol from t = tau ln(1/tol)."""
    w = _world()
    w.currents[0].add_pulse(10_000, 60_000, 1.5)
    tau_us = w.currents[0].tau_us
    for tol in (1e-2, 1e-3, 1e-4):
        t_flat = w.flat_start_us(0, 10_000, 70_000, tol, step_us=1) - 10_000
        assert abs(t_flat - tau_us * math.log(1 / tol)) <= 1.5


def test_flat_start_waits_for_the_eddy_field():
    """An eddy conductor (tau_e = 2 ms) that makes ratio r of the coil field at the sensor right
    after the edge: its field is below tol of the coil field from about tau_e ln(r/tol)
    (the L/R rise drives it, so a little later), never before."""
    eddy = ph.EddyConductor(np.array([-0.08, 0.0, 0.0]), coupling=5e-2, tau_s=2e-3)
    obj = W.EddyObject(eddy)
    w = _world(objects=[obj])
    w.currents[0].add_pulse(10_000, 60_000, 1.5)
    p, R = w.pose(10_000)
    e = ph.dipole_field(p[None, :], eddy.position, eddy.moment_per_amp(w.source[0]))[0]
    r = np.linalg.norm(e) / np.linalg.norm(w.unit_fields(p)[0])
    tol = 1e-3
    t_flat = w.flat_start_us(0, 10_000, 70_000, tol, step_us=5) - 10_000
    lower = 2e-3 * math.log(r / tol) * 1e6
    assert r > 10 * tol
    assert lower <= t_flat <= lower + 5 * w.currents[0].tau_us
    # and the actual eddy field at that instant is below tol of the coil field
    y = w.currents[0].highpass_at(10_000 + t_flat, 2e-3)
    assert abs(y) * np.linalg.norm(e) < tol * 1.5 * np.linalg.norm(w.unit_fields(p)[0]) * 1.0001


def test_steady_amplitude_matches_the_late_pulse_field():
    """Ground truth amplitude = field late in the pulse minus field before it (sensor frame),
    with a ferromagnetic sphere and an eddy conductor in the world: rel. 1e-6."""
    ferro = W.FerroObject(ph.FerroSphere(np.array([0.15, -0.12, 0.05]), radius=0.015, mu_r=500.0))
    eddy = W.EddyObject(ph.EddyConductor(np.array([-0.08, 0.0, 0.0]), coupling=5e-3, tau_s=1e-3))
    w = _world(objects=[ferro, eddy])
    _pulses(w)
    for k in range(3):
        t0 = 10_000 + k * 100_000
        late = w.field_sensor_frame(t0 + 59_000) - w.field_sensor_frame(t0 - 1_000)
        truth = w.steady_amplitude(k, t0 + 59_000, 1.5)
        np.testing.assert_allclose(late, truth, rtol=1e-6, atol=1e-13)
    # without the ferro sphere's response the truth would be wrong by more than 1e-4
    bare = 1.5 * (w.pose(0)[1].T @ w.unit_fields(w.pose(0)[0])[0])
    assert np.linalg.norm(bare - w.steady_amplitude(0, 0, 1.5)) > 1e-4 * np.linalg.norm(bare)


@pytest.mark.parametrize("sigma", [0.0, 6e6])
def test_metal_object_is_ferro_plus_conducting_sphere(sigma):
    """MetalObject = FerroSphere response + the permeable ConductingSphere transient (same mu_r) at the
    same centre: catches the static part or the transient dropped, or the transient taken non-magnetic."""
    c = np.array([0.2, 0.1, 0.0])
    metal = W.MetalObject(radius=0.02, mu_r=150.0, sigma=sigma, n_modes=6, position=c)
    w = _world(objects=[metal])
    _pulses(w)
    ref_objs = [W.FerroObject(ph.FerroSphere(c, 0.02, 150.0))]
    if sigma:
        ref_objs.append(W.ConductingSphereObject(ph.ConductingSphere(c, 0.02, sigma, n_modes=6, mu_r=150.0)))
    wr = _world(objects=ref_objs)
    for cur_a, cur_b in zip(w.currents, wr.currents):
        cur_b.add_pulse(*cur_a.pulses[0])
    for t in (9_000, 10_050, 10_400, 12_000, 40_000):
        np.testing.assert_allclose(w.field_source_frame(t), wr.field_source_frame(t), rtol=1e-12)
