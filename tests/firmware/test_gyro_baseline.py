"""The pulse window of a sensor turning in the earth field, with and without
the baseline turned by the gyroscope (``measure.gyro_baseline``).

Closed form: the sensor turns at a constant rate ``w`` about a fixed axis
``u``, ``R_w(t) = exp([u w t]x)`` (sensor to world, scipy's Rotation as the
reference); it sees ``y(t) = R_w(t)^T (B_e + C on(t))`` with the earth field
``B_e`` and a coil field ``C`` (both fixed in the world). The true amplitude
in the frame of the window's middle ``t_m`` is ``R_w(t_m)^T C``.
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware.measure.gyro_baseline import GyroBaselineExtractor, GyroRing
from coiltrack.firmware.measure.pulse import PulseExtractor, SampleRing
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

KW = dict(settle_us=3000, fall_us=3000, baseline_us=35000, guard_us=2000, sigma_t=5e-8, max_samples=64)
START, END = 1_000_000, 1_060_000
B_E = np.array([20e-6, 0.0, -44.7e-6])        # 49 uT, dip 66 deg
C = np.array([0.3e-6, -0.2e-6, 0.15e-6])       # a coil field of about 0.4 uT (45 cm from the thesis source)
AXIS = np.array([0.3, -0.5, 0.81])
AXIS = AXIS / np.linalg.norm(AXIS)


def _rot(w, t_us):
    return Rotation.from_rotvec(AXIS * w * (t_us - START) * 1e-6)


def _window(w, mag_dt=8333, gyro_dt=10_000, gyro_phase=1234):
    """Rings holding the window of a sensor turning at ``w`` rad/s; the true amplitude at t_m."""
    ring = SampleRing(128)
    gyro = GyroRing(64)
    t = START - 60_000
    used = []
    while t < END + 110_000:
        on = START <= t <= END
        y = _rot(w, t).inv().apply(B_E + (C if on else 0.0))
        ring.push(t, y[0], y[1], y[2], False, 0)
        if START + KW["settle_us"] <= t <= END - KW["guard_us"]:
            used.append(t)
        t += mag_dt
    tg = START - 70_000 + gyro_phase
    while tg < END + 120_000:
        gyro.push_rate(tg, *(AXIS * w))          # body rate of a constant-axis rotation
        tg += gyro_dt
    return ring, gyro, None


def _amp(ex):
    amp = np.zeros(3)
    var = np.zeros(3)
    flags, n_p, n_b = ex.extract(START, END, amp, var)
    return amp, flags, n_p


@pytest.mark.parametrize("w", [0.7, 1.2])
def test_turning_sensor_amplitude_with_and_without_the_gyro(w):
    """40 and 70 deg/s (walking trunk, arm flexion). Without the gyroscope the
    linear baseline leaves the earth field's curvature: tens of percent of
    the amplitude (5 % at 40 deg/s, 15 % at 70 deg/s here; the closed form's
leading term, the earth field's quadratic in the sensor frame, is checked to
10 %). With it the
    amplitude is the closed form to 1e-6 of |C| (the integration is exact for a
    constant rate; the rest is float rounding of 49 uT against 0.4 uT). Catches
    a wrong rotation sense (the residual doubles), a missing turn back to the
    frame at t_m (error ~ |C| w 0.1 s), a gyro rate taken from the wrong end of
    an interval, and a wrong interpolation between the 100 Hz gyro samples."""
    ring, gyro, _ = _window(w)
    base = PulseExtractor(ring, **KW)
    amp0, flags0, n_p = _amp(base)
    ex = GyroBaselineExtractor(ring, gyro, 64, **KW)
    amp1, flags1, n_p1 = _amp(ex)
    assert n_p1 == n_p and n_p >= 5
    used = np.zeros(64, dtype=np.int64)
    m = ex.last_used_times(used)
    t_m = (int(used[0]) + int(used[m - 1])) // 2
    truth = _rot(w, t_m).inv().apply(C)
    err0 = np.linalg.norm(amp0 - truth)
    err1 = np.linalg.norm(amp1 - truth)
    # the uncorrected error, leading term: the earth field's curvature in the sensor frame,
    # y_e(t) ~ b + t w [b]x u ... + (t w)^2 / 2 u x (u x b), with b = R_w(t_m)^T B_e (t from t_m):
    # the line through the baselines predicts the quadratic at the baselines' mean t^2 (plus the slope
    # term of their asymmetry), the pulse mean holds it at the pulse samples' mean t^2
    ts = np.arange(START - 60_000, END + 110_000, 8333, dtype=float)
    tb = ts[((ts >= START - 35_000) & (ts <= START - 2000)) | ((ts >= END + 3000) & (ts <= END + 38_000))]
    tp = np.array([int(t) for t in used[:m]], dtype=float)
    b = _rot(w, t_m).inv().apply(B_E)
    q = np.cross(AXIS, np.cross(AXIS, b)) * w * w / 2
    s = (tb - t_m) * 1e-6
    A = np.stack([np.ones_like(s), s], 1)
    coef = np.linalg.lstsq(A, s * s, rcond=None)[0]
    sp = (tp - t_m) * 1e-6
    pred = q * (np.mean(sp * sp) - (coef[0] + coef[1] * np.mean(sp)))
    np.testing.assert_allclose(amp0 - truth, pred, rtol=0, atol=0.1 * np.linalg.norm(pred))
    assert err0 > 0.04 * np.linalg.norm(C), err0
    assert err1 < 1e-6 * np.linalg.norm(C), (err0, err1)
    assert ex.turned_windows == 1
    t_a = ts[ts < START - 35_000].max()          # the bracketing sample before the span: frame origin
    assert ex.max_angle_rad == pytest.approx(w * (t_m - t_a) * 1e-6, rel=1e-9)


def test_without_rotation_the_extractor_is_the_linear_one():
    """A still sensor: the turned extractor gives the plain one's amplitude,
    variance and flags (catches a turn applied with zero rate, a dropped
    bracketing sample that flags the window incomplete, flags mangled in the
    copy)."""
    ring, gyro, _ = _window(0.0)
    a0 = np.zeros(3); v0 = np.zeros(3)
    a1 = np.zeros(3); v1 = np.zeros(3)
    r0 = PulseExtractor(ring, **KW).extract(START, END, a0, v0)
    r1 = GyroBaselineExtractor(ring, gyro, 64, **KW).extract(START, END, a1, v1)
    assert r0 == r1
    np.testing.assert_allclose(a1, a0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(v1, v0, rtol=1e-12)
    np.testing.assert_allclose(a1, C, rtol=0, atol=1e-13)


def test_no_gyro_samples_falls_back_to_the_linear_baseline():
    """No IMU samples from the node: the extractor is the plain one (catches a
    crash or a zero amplitude when the gyro ring is empty)."""
    ring, _, _ = _window(0.7)
    a0 = np.zeros(3); v0 = np.zeros(3)
    a1 = np.zeros(3); v1 = np.zeros(3)
    r0 = PulseExtractor(ring, **KW).extract(START, END, a0, v0)
    r1 = GyroBaselineExtractor(ring, GyroRing(8), 64, **KW).extract(START, END, a1, v1)
    assert r0 == r1
    np.testing.assert_array_equal(a0, a1)


def test_gyro_stream_that_stopped_falls_back_to_the_linear_baseline():
    """Rates that end 0.5 s before the window (the IMU stream stopped): the
    window is the plain one, counted (catches the last rate held over the
    window and turning the samples by a rotation nobody measured)."""
    ring, _, _ = _window(0.7)
    gyro = GyroRing(64)
    for k in range(20):
        gyro.push_rate(START - 700_000 + 10_000 * k, 0.0, 0.0, 3.0)
    a0 = np.zeros(3); v0 = np.zeros(3)
    a1 = np.zeros(3); v1 = np.zeros(3)
    r0 = PulseExtractor(ring, **KW).extract(START, END, a0, v0)
    ex = GyroBaselineExtractor(ring, gyro, 64, gyro_gap_us=30_000, **KW)
    r1 = ex.extract(START, END, a1, v1)
    assert r0 == r1 and ex.plain_windows == 1 and ex.turned_windows == 0
    np.testing.assert_array_equal(a0, a1)


@pytest.mark.skipif(not available(), reason="numpy memory handler API not reachable")
def test_extract_allocates_no_array():
    """The turned extraction runs on preallocated rings (catches a numpy
    temporary in the per-sample turn)."""
    ring, gyro, _ = _window(0.7)
    ex = GyroBaselineExtractor(ring, gyro, 64, **KW)
    amp = np.zeros(3)
    var = np.zeros(3)
    ex.extract(START, END, amp, var)
    counter = NumpyAllocationCounter()
    with counter:
        ex.extract(START, END, amp, var)
    assert counter.count == 0
