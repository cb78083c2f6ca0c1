"""The calibration file (firmware_py/calibration.py): loading and its refusals,
the source rows in the one signal model (against magpylib and finite
differences), the sensor models inverted on input (against an independent
forward model), and no allocation while applying them. All inputs seeded."""
import math

import magpylib
import numpy as np
import pytest
import tomllib
from scipy.spatial.transform import Rotation

from coiltrack.firmware.calibration import (Calibration, CalibrationError, SensorCalibration, SourceCalibration,
                                            calibrated_coils, dumps_toml, load_calibration)
from coiltrack.firmware.config import FirmwareConfig, config_from_dict
from coiltrack.firmware.linalg import flat
from coiltrack.firmware.model.field import orthogonal_source
from coiltrack.firmware.model.signal import SignalModel
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

RADIUS, TURNS = 0.055, 50


def _tilted_source(rng):
    """Three coils: moments tilted up to 2 deg, gains within 3 %, centres off by ~1 mm."""
    m = np.eye(3)
    for j in range(3):
        w = rng.normal(size=3)
        w *= math.radians(2.0) * rng.uniform(0.3, 1.0) / np.linalg.norm(w)
        m[j] = Rotation.from_rotvec(w).apply(m[j]) * rng.uniform(0.97, 1.03)
    return SourceCalibration(m, rng.normal(scale=1e-3, size=(3, 3)))


def _magpylib_field(moment, offset, p, current, model):
    """The bench's independent physics: a magpylib loop (or dipole) with the given
    moment direction and gain, moved by the offset."""
    g = float(np.linalg.norm(moment))
    u = moment / g
    if model == "dipole":
        src = magpylib.misc.Dipole(moment=u * g * TURNS * math.pi * RADIUS ** 2 * current, position=offset)
    else:
        src = magpylib.current.Circle(current=g * TURNS * current, diameter=2 * RADIUS)
        z = np.array([0.0, 0.0, 1.0])
        ax = np.cross(z, u)
        s = np.linalg.norm(ax)
        if s > 0:
            src.rotate_from_angax(math.degrees(math.atan2(s, u[2])), ax / s, anchor=(0, 0, 0))
        src.move(offset)
    return np.asarray(src.getB(p))


@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_calibrated_coils_match_magpylib_tilted_offset_loops(model):
    """The calibrated signal model against magpylib's tilted, offset, scaled loop
    (exact) or dipole at 12-60 cm: a dropped gain is off by ~3 %, an offset with
    the wrong sign by ~2e-2 relative at 12 cm, the nominal axis instead of the
    measured one by ~3e-2 (2 deg). Tolerance 1e-8 relative (AGM vs magpylib's
    own elliptic integrals)."""
    rng = np.random.default_rng(14)
    cal = _tilted_source(rng)
    sm = SignalModel(calibrated_coils(orthogonal_source(RADIUS, TURNS), cal), model)
    cur = [1.5, -1.2, 0.8]
    for _ in range(8):
        d = rng.normal(size=3)
        p = d / np.linalg.norm(d) * rng.uniform(0.12, 0.6)
        sm.fields(*p, cur, False)
        for j in range(3):
            ref = _magpylib_field(cal.moment[j], cal.offset[j], p, cur[j], model)
            np.testing.assert_allclose(sm.B[j], ref, rtol=1e-8, atol=1e-8 * np.linalg.norm(ref))


@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_calibrated_jacobian_matches_central_differences(model):
    """H of the calibrated coils against central differences of the signals
    (R_true = R exp([dtheta]x), scipy's exp): a Jacobian built on the nominal
    geometry while the signals use the calibrated one is off by ~3e-2; tolerance
    1e-6 of |H| (difference step 1e-6 m / rad)."""
    rng = np.random.default_rng(15)
    sm = SignalModel(calibrated_coils(orthogonal_source(RADIUS, TURNS), _tilted_source(rng)), model)
    cur = np.array([1.5, 1.5, 1.5])
    for _ in range(4):
        d = rng.normal(size=3)
        p = d / np.linalg.norm(d) * rng.uniform(0.15, 0.5)
        R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        h = np.zeros((3, 3))
        H = np.zeros((3, 3, 6))
        sm.measure(*p, R, memoryview(cur), flat(h), flat(H))
        Hn = np.zeros((9, 6))
        e = 1e-6
        for k in range(6):
            hp, hm = np.zeros((3, 3)), np.zeros((3, 3))
            dp = np.zeros(3)
            if k < 3:
                dp[k] = e
                sm.predict(*(p + dp), R, memoryview(cur), flat(hp))
                sm.predict(*(p - dp), R, memoryview(cur), flat(hm))
            else:
                dp[k - 3] = e
                sm.predict(*p, R @ Rotation.from_rotvec(dp).as_matrix(), memoryview(cur), flat(hp))
                sm.predict(*p, R @ Rotation.from_rotvec(-dp).as_matrix(), memoryview(cur), flat(hm))
            Hn[:, k] = (hp - hm).reshape(9) / (2 * e)
        np.testing.assert_allclose(H.reshape(9, 6), Hn, atol=1e-6 * np.abs(Hn).max())


def _forward_mag(S, b, B):
    return S @ B + b


def _forward_imu(v, f, w):
    """The IMU model of the file, written forward (v: the values), IMU sees R^T f."""
    R = Rotation.from_rotvec(v["mag_to_imu_rotvec"]).as_matrix()
    fi, wi = R.T @ f, R.T @ w
    return (v["accel_matrix"] @ fi + v["accel_bias_m_s2"],
            v["gyro_matrix"] @ wi + v["gyro_bias_rad_s"] + v["gyro_g_sensitivity"] @ fi)


def _sensor_values(rng):
    def mat(scale, skew):
        return np.eye(3) + np.diag(rng.uniform(-scale, scale, 3)) + skew * rng.normal(size=(3, 3))
    return {"mag_soft": mat(0.05, 0.01), "mag_hard_t": rng.normal(scale=2e-6, size=3),
            "accel_matrix": mat(0.01, 0.005), "accel_bias_m_s2": rng.normal(scale=0.05, size=3),
            "gyro_matrix": mat(0.01, 0.005), "gyro_bias_rad_s": rng.normal(scale=0.01, size=3),
            "gyro_g_sensitivity": rng.normal(scale=1e-3, size=(3, 3)),
            "mag_to_imu_rotvec": rng.normal(scale=math.radians(1.5), size=3)}


def test_sensor_corrections_invert_the_forward_models():
    """correct_mag / correct_imu undo the file's models written forward with numpy
    and scipy's rotation: the g-sensitivity taken on the measured instead of the
    corrected force, the rotation applied the wrong way or the bias subtracted
    after the matrix each leave errors of 1e-4..1e-2; tolerance 1e-12 relative."""
    rng = np.random.default_rng(16)
    v = _sensor_values(rng)
    c = SensorCalibration(33, v)
    for _ in range(5):
        B = rng.normal(scale=40e-6, size=3)
        np.testing.assert_allclose(c.correct_mag(*_forward_mag(v["mag_soft"], v["mag_hard_t"], B)), B,
                                   rtol=0, atol=1e-12 * np.linalg.norm(B))
        f, w = rng.normal(scale=5.0, size=3) + [0, 0, 9.81], rng.normal(scale=1.0, size=3)
        fm, wm = _forward_imu(v, f, w)
        out = c.correct_imu(*fm, *wm)
        np.testing.assert_allclose(out[:3], f, atol=1e-12 * 20)
        np.testing.assert_allclose(out[3:], w, atol=1e-12 * 5)


def _good_table(rng):
    src = _tilted_source(rng)
    v = _sensor_values(rng)
    sig = {k + "_sigma": (np.abs(a) * 0.01 + 1e-9).tolist() for k, a in v.items()}
    return {"meta": {"method": "grid", "residual_rms": 1e-9, "poses": 49},
            "source": src.to_table(),
            "sensor": {"32": {**{k: a.tolist() for k, a in v.items()}, **sig}}}


def test_file_round_trip_through_toml(tmp_path):
    """dumps_toml then load_calibration gives back every value and sigma
    (a writer dropping a table, a sigma or digits fails here)."""
    rng = np.random.default_rng(17)
    t = _good_table(rng)
    path = tmp_path / "cal.toml"
    path.write_text(dumps_toml(t))
    assert tomllib.loads(path.read_text()) == t
    cal = load_calibration(path, FirmwareConfig())
    np.testing.assert_array_equal(cal.source.moment, np.array(t["source"]["coil_moment"]))
    s = cal.sensors[32]
    for k in ("mag_soft", "gyro_g_sensitivity", "mag_to_imu_rotvec"):
        np.testing.assert_array_equal(s.values[k], np.array(t["sensor"]["32"][k]))
        np.testing.assert_array_equal(s.sigmas[k], np.array(t["sensor"]["32"][k + "_sigma"]))
    assert cal.to_table()["sensor"]["32"] == t["sensor"]["32"]


@pytest.mark.parametrize("edit, key", [
    (lambda t: t["source"].__setitem__("coil_moment", [[1, 0, 0], [0, 1, 0]]), "source.coil_moment"),
    (lambda t: t["source"]["coil_moment"].__setitem__(0, [1.4, 0, 0]), "source.coil_moment"),
    (lambda t: t["source"]["coil_moment"].__setitem__(1, [0.5, 0.85, 0]), "source.coil_moment"),
    (lambda t: t["source"]["coil_offset_m"].__setitem__(2, [0.1, 0, 0]), "source.coil_offset_m"),
    (lambda t: t["source"].__setitem__("coil_offset_m_sigma", [[-1, 0, 0]] * 3), "source.coil_offset_m_sigma"),
    (lambda t: t["source"].__setitem__("coil_gain", 1.0), "source.coil_gain"),
    (lambda t: t["sensor"]["32"].__setitem__("mag_soft", [[1, 0], [0, 1]]), "sensor.32.mag_soft"),
    (lambda t: t["sensor"]["32"].__setitem__("mag_soft", [[1, 0, 0], [0, 1, 0], [0, 0, 0]]), "sensor.32.mag_soft"),
    (lambda t: t["sensor"]["32"].__setitem__("accel_matrix", [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]),
     "sensor.32.accel_matrix"),
    (lambda t: t["sensor"]["32"].__setitem__("mag_hard_t", [30.0, 0, 0]), "sensor.32.mag_hard_t"),
    (lambda t: t["sensor"]["32"].__setitem__("gyro_bias_rad_s", ["a", 0, 0]), "sensor.32.gyro_bias_rad_s"),
    (lambda t: t["sensor"]["32"].__setitem__("gyro_bias_rad_s", [float("nan"), 0, 0]), "sensor.32.gyro_bias_rad_s"),
    (lambda t: t["sensor"]["32"].__setitem__("gyro_scale", [1, 1, 1]), "sensor.32.gyro_scale"),
    (lambda t: t["sensor"].__setitem__("x", {}), "sensor.x"),
    (lambda t: t.__setitem__("sources", {}), "sources"),
])
def test_loader_refuses_bad_values_naming_the_key(edit, key):
    """Each bad value (wrong row count, gain 1.4, a moment 30 deg off its axis,
    a 10 cm offset, a negative sigma, an unknown key, a wrong shape, a singular
    or mirroring matrix, a hard iron in the wrong units, text, NaN, a bad node
    id, an unknown section) is refused with the key named; a loader accepting
    any of them would run the tracker on a wrong model."""
    t = _good_table(np.random.default_rng(18))
    edit(t)
    cfg = FirmwareConfig()
    with pytest.raises(CalibrationError) as exc:
        Calibration.from_table(t, 3, [c.axis for c in cfg.source.coils], cfg.calibration.calibration_max_gain_error,
                               cfg.calibration.calibration_max_tilt_deg)
    assert exc.value.key == key
    assert f"'{key}'" in str(exc.value)


def test_loader_refuses_missing_and_broken_files(tmp_path):
    """A missing file and a file that is not TOML are refused (not a crash)."""
    with pytest.raises(CalibrationError, match="cannot read"):
        load_calibration(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[source\ncoil_moment = 1")
    with pytest.raises(CalibrationError, match="not valid TOML"):
        load_calibration(bad)


def test_config_section_refuses_bad_keys():
    """[calibration] keys: a gain bound of 0 and a non-string file are refused naming the key."""
    with pytest.raises(Exception, match="calibration.calibration_max_gain_error"):
        config_from_dict({"calibration": {"calibration_max_gain_error": 0.0}})
    with pytest.raises(Exception, match="calibration.calibration_file"):
        config_from_dict({"calibration": {"calibration_file": 3}})


@pytest.mark.skipif(not available(), reason="numpy memory handler API not reachable")
def test_applying_the_calibration_allocates_no_array():
    """The receive stage's corrections and the calibrated signal model, in the
    counting allocator of tools.bench.alloc: a temporary array in either counts >= 1."""
    from coiltrack.firmware.receive import Receiver

    rng = np.random.default_rng(19)
    c = SensorCalibration(32, _sensor_values(rng))
    rx = Receiver(None, None, (), None, None, None, None, calibration={32: c})

    class M:
        node, t_us, x, y, z, flip = 32, 10, 1000, -2000, 3000, 1
        ax, ay, az, gx, gy, gz = 10, -20, 9810, 3, -4, 5
    sm = SignalModel(calibrated_coils(orthogonal_source(RADIUS, TURNS), _tilted_source(rng)), "exact")
    cur = memoryview(np.array([1.5, 1.5, 1.5]))
    h, H = np.zeros(9), np.zeros(54)
    hv, Hv = memoryview(h), memoryview(H)
    R = np.eye(3)
    counter = NumpyAllocationCounter()
    for _ in range(2):          # the first pass warms up caches
        before = counter.count
        with counter:
            for _ in range(50):
                rx._correct_mag(M, c)
                rx._correct_imu(M, c)
                sm.measure(0.2, 0.1, -0.05, R, cur, hv, Hv)
        n = counter.count - before
    assert n == 0


@pytest.mark.skipif(not available(), reason="numpy memory handler API not reachable")
def test_a_calibrated_fused_firmware_tick_allocates_no_array(tmp_path):
    """A calibrated firmware (source rows, magnetometer ellipsoid, IMU model) on the
    fused bench (roetenberg-fusion, IMU at 120 Hz, bursts every 600 ms): after a
    5 s warm-up, 2.5 s of ticks (four bursts: solves, fusion updates, replays)
    count no numpy allocation (tools.bench.alloc's counting allocator): a correction
    that built a temporary vector per sample counts hundreds."""
    import dataclasses

    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools import scenarios
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.bench.runner import BenchSetup

    sc = scenarios.get("roetenberg-fusion")
    cfg = sc.firmware_config()
    rng = np.random.default_rng(20)
    v = {k: a.tolist() for k, a in _sensor_values(rng).items()}
    path = tmp_path / "cal.toml"
    path.write_text(dumps_toml({"source": _tilted_source(rng).to_table(),
                                "sensor": {str(s): v for s in cfg.link.sensor_ids}}))
    cfg = cfg.with_(calibration={"calibration_file": str(path)})
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 4, 8.0, emu_end)
    fw = Firmware(cfg, fw_end)
    assert fw.receiver.mag_cal and fw.receiver.imu_cal and fw.coils[0].gain != 1.0
    counter = NumpyAllocationCounter()
    t, counted = 0, 0
    while t <= 7_500_000:
        bench.emulator.step(t)
        if t >= 5_000_000:
            before = counter.count
            with counter:
                fw.tick(t)
            counted += counter.count - before
        else:
            fw.tick(t)
        t += cfg.timing.tick_us
    assert counted == 0
    assert fw.status()["cycles"] >= 10 and fw.receiver.imu_received > 800
