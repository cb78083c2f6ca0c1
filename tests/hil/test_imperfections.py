"""The imperfect bench (``hil.imperfections``, ``hil.calibrun``) against independent references.

References: magpylib ``Circle`` filaments placed and rotated with scipy's ``Rotation`` (not
``hil.physics``'s frames), the matrices written out, the dipole field of the calibration table's
parameters, and stated statistical bands. Seeded; no wall clock.
"""
from __future__ import annotations

import math

import magpylib
import numpy as np
import pytest
from scipy import integrate, stats
from scipy.spatial.transform import Rotation

from coiltrack.hil import calibrun
from coiltrack.hil import physics as ph
from coiltrack.hil.imperfections import (
    GaussMarkov,
    ImperfectionSpec,
    Imperfections,
    ImuImperfection,
    MagImperfection,
    TemperatureProfile,
)
from coiltrack.hil.motion import StaticPose
from coiltrack.hil.nodes import ImuSpec, SensorNode
from coiltrack.hil.world import World

DEG = math.pi / 180.0


def _draw(seed=3, spec=None):
    return Imperfections.draw(seed, ph.thesis_source().coils, sensor_ids=(16,), spec=spec)


def _points(rng, n=12):
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(0.12, 0.6, (n, 1))


def test_built_coils_equal_magpylib_coils_rotated_moved_scaled():
    """Each coil as built is the nominal winding (its filaments) rotated by the drawn tilt about
    its centre, moved by the offset and carrying gain x the current, evaluated by magpylib ``Circle``
    objects oriented with scipy's Rotation: rel. tol 1e-9 (the same kernel, different frames).
    Catches a tilt of the wrong sign or about the wrong point, an offset not applied or applied
    twice, a gain lost, or the tilt applied downstream of the field."""
    imp = _draw()
    nominal = ph.thesis_source().coils
    built = ph.Source(imp.apply_source(nominal))
    pts = _points(np.random.default_rng(5))
    U = built.unit_fields(pts)
    for k, c in enumerate(nominal):
        r, z, w = c.filaments
        # coil frame z -> nominal axis, then the tilt (world frame)
        align, _ = Rotation.align_vectors([c.axis], [[0.0, 0.0, 1.0]])
        rot = Rotation.from_rotvec(imp.source.tilt_rotvec[k]) * align
        col = magpylib.Collection(*[magpylib.current.Circle(current=float(wi * imp.source.gain[k]),
                                                             diameter=2 * float(ri), position=(0, 0, float(zi)))
                                    for ri, zi, wi in zip(r, z, w)])
        col.rotate(rot, anchor=(0, 0, 0))
        col.move(c.center + imp.source.offset_m[k])
        ref = np.asarray(col.getB(pts))
        np.testing.assert_allclose(U[k], ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def test_draws_follow_their_stated_distributions():
    """Tilts perpendicular to the coil axis and <= 2 deg, gains within +-5 %, offsets of mm size;
    a seed gives the same unit, groups draw from streams of their own (the source stays when the
    IMU is switched off). Catches a tilt in degrees taken as radians, a bound not applied, a draw
    that consumes another group's stream."""
    a, b = _draw(7), _draw(7)
    assert a.listing() == b.listing()
    for k, c in enumerate(ph.thesis_source().coils):
        t = a.source.tilt_rotvec[k]
        assert np.linalg.norm(t) <= 2.0 * DEG + 1e-15
        assert abs(t @ c.axis) < 1e-15
    assert np.all(np.abs(a.source.gain - 1.0) <= 0.05)
    assert np.all(np.abs(a.source.offset_m) < 6e-3)                  # 6 sigma of 1 mm
    c = _draw(7, ImperfectionSpec(imu=False, mag_to_imu=False))
    np.testing.assert_array_equal(c.source.tilt_rotvec, a.source.tilt_rotvec)
    np.testing.assert_array_equal(c.sensors[16].mag.soft, a.sensors[16].mag.soft)
    assert c.sensors[16].imu is None
    # over many units the tilt angle is U(0, 2 deg): Kolmogorov-Smirnov at alpha = 1e-3
    ang = np.concatenate([np.linalg.norm(_draw(s).source.tilt_rotvec, axis=1) for s in range(60)])
    assert stats.kstest(ang / (2.0 * DEG), "uniform").pvalue > 1e-3


def test_magnetometer_model_is_the_stated_matrices():
    """``measure`` = soft @ B + hard, then x (1 - k3 (x/range)^2) per axis, then
    tempco (T(t) - T_ref), T(t) the warm-up profile written out: rel. tol 1e-12. Catches soft iron
    transposed, hard iron inside the soft matrix, the non-linearity's sign or power, the
    temperature offset's reference."""
    rng = np.random.default_rng(2)
    soft = np.eye(3) + 0.03 * rng.standard_normal((3, 3))
    hard = rng.normal(0, 3e-6, 3)
    tc = rng.normal(0, 1e-8, 3)
    k3 = np.array([0.004, 0.001, 0.0025])
    prof = TemperatureProfile(t0_c=20.0, rise_c=6.0, tau_s=100.0, ripple_c=0.4, period_s=50.0)
    m = MagImperfection(soft, hard, tc, k3, 160e-6, prof, temp_ref_c=21.0)
    B = np.array([60e-6, -20e-6, 45e-6])
    t_us = 37_000_000
    x = np.array([sum(soft[i, j] * B[j] for j in range(3)) + hard[i] for i in range(3)])
    T = 20.0 + 6.0 * (1 - math.exp(-37.0 / 100.0)) + 0.4 * math.sin(2 * math.pi * 37.0 / 50.0)
    ref = x * (1 - k3 * (x / 160e-6) ** 2) + tc * (T - 21.0)
    np.testing.assert_allclose(m.measure(B, t_us), ref, rtol=1e-12)
    # at full scale on one axis the compression is k3 of the reading
    m0 = MagImperfection(np.eye(3), np.zeros(3), np.zeros(3), k3, 160e-6)
    np.testing.assert_allclose(m0.measure(np.array([160e-6, 0, 0]), 0)[0], 160e-6 * (1 - 0.004), rtol=1e-12)


def test_sensor_node_reads_through_its_magnetometer_model():
    """A node with imperfections reads ``measure(R^T B_world)``: the world's field in the sensor
    frame through the node's own model, the flip artefact through it too; a node without stays the
    world's field exactly. Catches the model applied in the source frame, or not at all."""
    imp = _draw(4)
    R = Rotation.from_rotvec([0.3, -0.5, 0.9]).as_matrix()
    world = World(imp.apply_source(ph.thesis_source().coils), StaticPose([0.2, 0.05, -0.03], R))
    node = SensorNode(16, world, seed=1)
    t = 1_234_567
    plain = node._sensed(t)
    np.testing.assert_array_equal(plain, world.field_sensor_frame(t))
    imp.install([node])
    ref = imp.sensors[16].mag.measure(R.T @ world.field_source_frame(t), t)
    np.testing.assert_allclose(node._sensed(t), ref, rtol=1e-12, atol=1e-18)
    Bm = node._sensed(t)
    soft, hard = imp.sensors[16].mag.soft, imp.sensors[16].mag.hard_t
    # the linear part dominates: soft @ B + hard within the 0.5 % non-linearity + temperature offset
    assert np.linalg.norm(Bm - (soft @ plain + hard)) < 0.005 * np.linalg.norm(soft @ plain + hard) + 1e-7


def test_imu_model_matrices_and_mag_to_imu_rotation():
    """f = A R_mi^T f_mag, w = G R_mi^T w_mag + Gs R_mi^T f_mag with R_mi = scipy's
    Rotation.from_rotvec(mag_to_imu_rotvec): rel. tol 1e-12 (no bias instability). Catches R_mi
    transposed, the g-sensitivity applied to the magnetometer-frame force or to the rate."""
    rng = np.random.default_rng(8)
    A = np.eye(3) + 0.01 * rng.standard_normal((3, 3))
    G = np.eye(3) + 0.01 * rng.standard_normal((3, 3))
    Gs = 2e-4 * rng.standard_normal((3, 3))
    mi = np.array([0.01, -0.02, 0.015])
    u = ImuImperfection(A, G, Gs, mi, 0.0, 0.0, 100.0)
    f = np.array([0.3, -1.2, 9.7])
    w = np.array([0.5, 0.1, -0.8])
    Rm = Rotation.from_rotvec(mi).as_matrix()
    fa, wg = u.measure(f, w, 0.01)
    np.testing.assert_allclose(fa, A @ Rm.T @ f, rtol=1e-12)
    np.testing.assert_allclose(wg, G @ Rm.T @ w + Gs @ Rm.T @ f, rtol=1e-12)


def test_sensor_node_imu_sample_through_the_model():
    """The node's IMU sample (no noise, no bias) equals the model applied to R^T (a - g) and the
    body rate of a static pose, within one LSB of the protocol's quantisation. Catches the node
    adding the model after its bias (then the matrices would scale the bias) or skipping it."""
    from coiltrack.protocol.schema import ACC_LSB, GYR_LSB

    imp = _draw(5, ImperfectionSpec(imu=True, gyro_instability_rad_s=0.0, accel_instability_m_s2=0.0))
    R = Rotation.from_rotvec([0.4, 0.2, -1.1]).as_matrix()
    world = World(ph.thesis_source().coils, StaticPose([0.2, 0.0, 0.0], R))
    spec = ImuSpec(rate_hz=100.0, acc_noise_density=0.0, acc_bias_sigma=0.0, acc_bias_rw=0.0,
                   gyro_noise_density=0.0, gyro_bias_sigma=0.0, gyro_bias_rw=0.0)
    node = SensorNode(16, world, imu=spec, seed=1)
    imp.install([node])
    out = []
    node._imu_sample(node._imu_t(0), 0, lambda _n, msg: out.append(msg))
    u = imp.sensors[16].imu
    f = R.T @ np.array([0.0, 0.0, spec.gravity])
    Rm = Rotation.from_rotvec(u.mag_to_imu_rotvec).as_matrix()
    fa = u.accel_matrix @ Rm.T @ f
    wg = u.gyro_g_sens @ Rm.T @ f
    m = out[0]
    np.testing.assert_allclose(np.array([m.ax, m.ay, m.az]) * ACC_LSB, fa, atol=ACC_LSB)
    np.testing.assert_allclose(np.array([m.gx, m.gy, m.gz]) * GYR_LSB, wg, atol=GYR_LSB)


def test_bias_instability_gauss_markov_step_variance():
    """From x = 0 one step has variance sigma^2 (1 - e^{-2 dt/tau}); over 3000 values the sample
    variance lies in its 99.9 % chi-square band. Catches sqrt(1 - a^2) dropped (variance sigma^2)
    or dt/tau inverted."""
    sigma, tau, dt = 0.02, 50.0, 0.5
    g = GaussMarkov(sigma, tau, np.random.default_rng(11))
    vals = []
    for _ in range(1000):
        g.x = np.zeros(3)
        vals.append(g.step(dt).copy())
    v = np.concatenate(vals)
    n = v.size
    var = sigma**2 * (1 - math.exp(-2 * dt / tau))
    s2 = np.sum(v**2) / var
    assert stats.chi2.ppf(5e-4, n) < s2 < stats.chi2.ppf(1 - 5e-4, n)


def test_calibration_table_reproduces_the_built_coils():
    """A winding built from the truth table alone (the nominal filaments along
    ``coil_moment / |coil_moment|``, carrying ``|coil_moment|`` x the current, centred at nominal
    centre + ``coil_offset_m``; magpylib ``Circle`` objects oriented by scipy) has the built coil's
    field at 12-60 cm: rel. tol 1e-9. The soft/hard iron and IMU entries are the drawn ones.
    Catches a table in another parameterisation (moment without the gain, offset with the wrong
    sign, the axis not tilted), which imp-cal's recovery test would then compare against."""
    imp = _draw(9)
    tab = imp.as_calibration_table()
    nominal = ph.thesis_source().coils
    built = ph.Source(imp.apply_source(nominal))
    pts = _points(np.random.default_rng(1), 20)
    U = built.unit_fields(pts)
    mom = np.asarray(tab["source"]["coil_moment"])
    off = np.asarray(tab["source"]["coil_offset_m"])
    for k, c in enumerate(nominal):
        r, z, w = c.filaments
        g = float(np.linalg.norm(mom[k]))
        rot, _ = Rotation.align_vectors([mom[k] / g], [[0.0, 0.0, 1.0]])
        col = magpylib.Collection(*[magpylib.current.Circle(current=float(wi * g), diameter=2 * float(ri),
                                                             position=(0, 0, float(zi)))
                                    for ri, zi, wi in zip(r, z, w)])
        col.rotate(rot, anchor=(0, 0, 0))
        col.move(c.center + off[k])
        ref = np.asarray(col.getB(pts))
        np.testing.assert_allclose(U[k], ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
    s = tab["sensor"]["16"]
    np.testing.assert_array_equal(np.asarray(s["mag_soft"]), imp.sensors[16].mag.soft)
    np.testing.assert_array_equal(np.asarray(s["mag_to_imu_rotvec"]), imp.sensors[16].imu.mag_to_imu_rotvec)
    assert np.all(np.asarray(s["mag_soft_sigma"]) == 0.0) and tab["meta"]["method"] == "truth"


def test_grid_recording_is_the_jig_field_through_the_magnetometer(tmp_path):
    """``b_on - b_off`` at a jig station equals soft @ R^T (I_k x magpylib's field of the built
    coil) within 5 sigma of the means' noise (non-linearity off); the file round-trips. Catches
    the station's rotation transposed, the current not applied, the soft iron skipped."""
    spec = ImperfectionSpec(mag_nonlin_max=0.0)
    rec = calibrun.record_grid(unit=2, seed=3, n_xy=3, z_levels=(0.0,), n_ori=2, spec=spec)
    path = tmp_path / "grid.npz"
    calibrun.save_recording(rec, path)
    back = calibrun.load_recording(path)
    assert back["kind"] == "grid" and back["meta"]["unit"] == 2
    np.testing.assert_array_equal(back["b_on"], rec["b_on"])
    imp = Imperfections.draw(2, ph.thesis_source().coils, sensor_ids=(16,), spec=spec)
    coils = imp.apply_source(ph.thesis_source().coils)
    soft = imp.sensors[16].mag.soft
    sig = rec["noise_t"] * math.sqrt(1 / rec["n_on"] + 1 / rec["n_off"])
    for s in (0, 3, 17):
        p, R = rec["p_true"][s], rec["R_true"][s]
        for k in range(3):
            Bk = rec["currents_a"][k] * (R.T @ coils[k].unit_field_magpylib(p[None, :])[0])
            d = back["b_on"][s, k] - back["b_off"][s]
            assert np.all(np.abs(d - soft @ Bk) < 5 * sig)


def test_free_recording_still_periods_are_gravity_and_earth_field():
    """In the first still period the accelerometer's mean is A R_mi^T R^T (0, 0, g) + the turn-on
    bias, and the magnetometer's |soft^-1 (B - hard)| is the earth field's magnitude,
    within 5 sigma of the mean's noise (+ the bias random walk and instability). Catches gravity's
    sign, the IMU frame rotated the wrong way, the still flags misplaced."""
    spec = ImperfectionSpec(mag_nonlin_max=0.0, mag_tempco_sigma_t_per_k=0.0)
    rec = calibrun.record_free(unit=3, seed=1, n_random=0, still_s=1.0, move_s=0.5, spec=spec)
    imp = Imperfections.draw(3, ph.thesis_source().coils, sensor_ids=(16,), spec=spec)
    u = imp.sensors[16].imu
    st = rec["still"]
    first = np.flatnonzero(st[: int(1.0 * rec["rate_hz"])])
    R = rec["truth_R"][first[0]]
    Rm = Rotation.from_rotvec(u.mag_to_imu_rotvec).as_matrix()
    ref = u.accel_matrix @ Rm.T @ R.T @ np.array([0.0, 0.0, 9.81]) + rec["truth_accel_bias0"]
    acc = rec["acc_m_s2"][first].mean(axis=0)
    tol = 5 * rec["meta"]["acc_sigma"] / math.sqrt(first.size) + 5 * 2e-3 + 2e-4
    np.testing.assert_allclose(acc, ref, atol=tol)
    assert st.sum() == 24 * int(rec["rate_hz"])
    assert np.all(np.linalg.norm(rec["truth_w_mag"][st], axis=1) == 0.0)
    m = imp.sensors[16].mag
    Bm = rec["mag_t"][first].mean(axis=0) - m.hard_t
    sig_b = rec["meta"]["noise_t"] / math.sqrt(first.size)
    assert abs(np.linalg.norm(np.linalg.solve(m.soft, Bm)) - np.linalg.norm(ph.EARTH_FIELD_T)) < 5 * sig_b * 1.1


def test_perfect_twin_is_the_nominal_bench():
    """The perfect twin of imperfect-bench builds the nominal thesis source (field bit-identical
    to ``thesis_source``) on the same trajectory, without imperfections; a coil of gain 1 is the
    coil without the argument, bit for bit. Catches imperfections leaking into the perfect run
    (its figures would move) or a trajectory drawn from another seed."""
    from coiltrack.tools.scenarios import imperfect as si
    from coiltrack.tools.scenarios import get

    imp_world = get("imperfect-bench").build_world(5, 10.0)
    twin = si.PERFECT["imperfect-bench"].build_world(5, 10.0)
    assert twin.imperfections is None and imp_world.imperfections is not None
    p, R = imp_world.trajectory.pose(3_000_000)
    p2, R2 = twin.trajectory.pose(3_000_000)
    np.testing.assert_array_equal(p, p2)
    pts = _points(np.random.default_rng(3))
    np.testing.assert_array_equal(twin.source.unit_fields(pts), ph.thesis_source().unit_fields(pts))
    assert np.max(np.abs(imp_world.source.unit_fields(pts) - twin.source.unit_fields(pts))) > 0
    c = ph.thesis_source().coils[0]
    c1 = ph.SourceCoil(c.center, c.axis, c.radius, c.turns, c.inner_radius, c.outer_radius, c.length, gain=1.0)
    c0 = ph.SourceCoil(c.center, c.axis, c.radius, c.turns, c.inner_radius, c.outer_radius, c.length)
    np.testing.assert_array_equal(c1.filaments[2], c0.filaments[2])


@pytest.mark.parametrize("name", ["imperfect-bench"])
def test_scenario_reports_the_contract_keys(name):
    """A short imperfect-bench run reports every imperfection and, with the comparison, the
    uncalibrated and perfect figures of the same seed (without a calibration file the uncalibrated
    run is the run itself). Catches a key missing or the perfect run not being perfect (its
    listing would not be empty)."""
    from coiltrack.tools.scenarios import imperfect as si
    from coiltrack.tools.bench.runner import run_inproc
    from coiltrack.tools.scenarios import get

    sc = get(name)
    rep = run_inproc(sc, 2, 2.0)
    assert any(e["what"] == "source.coil0.tilt_deg" for e in rep["imperfections"])
    assert rep["calibration"] is None
    si.add_imperfect_comparison(rep, sc, 2, 2.0)
    for k in ("uncalibrated_position_rms_mm", "uncalibrated_orientation_rms_deg", "perfect_position_rms_mm",
              "perfect_orientation_rms_deg"):
        assert k in rep
    assert rep["uncalibrated_position_rms_mm"] == rep["position_rms_mm"]


def test_fast_magnetometer_node_reads_through_the_model():
    """The fast (AC) magnetometer node's sample, noise and offset zeroed, is the model applied to the
    world's field in its frame, within one 5 nT LSB. Catches the fast profile bypassing the model."""
    from coiltrack.hil.ac_nodes import FastSensorNode
    from coiltrack.protocol.schema import MAG_LSB_T

    imp = _draw(6)
    R = Rotation.from_rotvec([-0.2, 0.7, 0.1]).as_matrix()
    world = World(imp.apply_source(ph.thesis_source().coils), StaticPose([0.22, -0.04, 0.05], R))
    node = FastSensorNode(16, world, seed=2)
    node.mag.noise_t = 0.0
    node.offset = np.zeros(3)
    imp.install([node])
    out = []
    t = 2_000_000
    node._mag_sample(t, 1, lambda _n, msg: out.append(msg))
    ref = imp.sensors[16].mag.measure(R.T @ world.field_source_frame(t), t)
    got = np.array([out[0].x, out[0].y, out[0].z]) * MAG_LSB_T
    np.testing.assert_allclose(got, ref, atol=MAG_LSB_T)


def test_free_recording_rates_integrate_to_its_rotations():
    """The body rate of the free recording integrates (trapezoid over each turn, still samples at
    both ends) to the rotation between the still orientations: relative 1e-4 (the trapezoid's
    O(dt^2) on a smoothstep turn). Catches a rate on another time scale than the poses (a turn of
    n samples timed as n instead of n + 1 intervals: 1/n = 0.6 % too much rotation, which a
    calibration would read as a gyroscope scale error)."""
    rec = calibrun.record_free(unit=1, seed=0, n_random=2, still_s=0.5, move_s=1.5)
    st, w, R = rec["still"], rec["truth_w_mag"], rec["truth_R"]
    dt = 1.0 / rec["rate_hz"]
    edges = np.flatnonzero(np.diff(st.astype(int)))         # last still, last moving sample
    for a, b in zip(edges[0::2], edges[1::2] + 1):
        ang = float(np.linalg.norm(integrate.trapezoid(w[a:b + 1], dx=dt, axis=0)))
        ref = float(np.linalg.norm(Rotation.from_matrix(R[a].T @ R[b]).as_rotvec()))
        assert abs(ang - ref) < 1e-4 * ref
