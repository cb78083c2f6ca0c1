"""The sensor node's delta integration (hil.imu_delta) against closed forms and
scipy: a constant rate about a fixed axis, a coning motion integrated on a fine
grid, and the quantisation remainder carried across frames."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.hil.imu_delta import DeltaIntegrator
from coiltrack.protocol.schema import DANG_LSB_RAD, DVEL_LSB_MPS


def test_constant_rate_gives_the_closed_form_deltas():
    """Rotation at w about a fixed axis, specific force constant in the interval's start frame:
    dtheta = w T exactly and dv (mid frame) = Rz(w T / 2)^T f T. Catches a delta velocity left
    in the start or end frame (error w T / 2 x |f| T = 2.6e-2 m/s here, 260 LSB) and a dropped
    sub-step rotation."""
    n, dt = 12, 1.0 / 120.0
    w = np.array([0.0, 0.0, 0.8])                       # rad/s
    f_s = np.array([0.3, -0.2, 9.81])                   # m/s^2, start frame
    integ = DeltaIntegrator(n, dt)
    out = None
    for i in range(n):
        t = (i + 0.5) * dt                              # the sample's middle
        f_b = Rotation.from_rotvec(w * t).as_matrix().T @ f_s
        out = integ.add(w, f_b)
    a, v = out
    T = n * dt
    assert np.max(np.abs(a * DANG_LSB_RAD - w * T)) <= 0.5 * DANG_LSB_RAD + 1e-12
    want_v = Rotation.from_rotvec(0.5 * w * T).as_matrix().T @ (f_s * T)
    # the sub-step midpoint rule for f: second order, (w dt)^2 / 24 relative
    assert np.max(np.abs(v * DVEL_LSB_MPS - want_v)) <= 0.5 * DVEL_LSB_MPS + 1e-5


def test_coning_motion_matches_a_fine_grid_rotation():
    """Coning (rates about x and y in quadrature): the interval's rotation vector against scipy's
    composition of 1200 sub-steps. A plain sum of w dt misses the coning term (3e-4 rad here, 6
    LSB); the node's rotation-matrix accumulation keeps it to its 120 Hz sampling error."""
    n, dt = 12, 1.0 / 120.0
    A, om = 0.6, 2 * np.pi * 2.0

    def rate(t):
        return np.array([A * np.cos(om * t), A * np.sin(om * t), 0.0])
    integ = DeltaIntegrator(n, dt)
    for i in range(n):
        out = integ.add(rate((i + 0.5) * dt), np.zeros(3))
    fine = Rotation.identity()
    m = 100
    for j in range(n * m):
        fine = fine * Rotation.from_rotvec(rate((j + 0.5) * dt / m) * dt / m)
    plain = sum(rate((i + 0.5) * dt) * dt for i in range(n))
    exact = fine.as_rotvec()
    got = out[0] * DANG_LSB_RAD
    assert np.linalg.norm(plain - exact) > 5 * DANG_LSB_RAD           # the coning term matters here
    assert np.linalg.norm(got - exact) < 2 * DANG_LSB_RAD


def test_running_sums_carry_the_remainder_and_survive_a_lost_frame():
    """The frames carry running sums (wrapped to 16 bits): over 200 frames their differences add
    up to the integrated deltas within half an LSB (a node that rounded each frame's delta on
    its own would drift by ~sqrt(200) x 0.29 LSB), and the difference across a lost frame is
    the two intervals' sum (a per-frame delta would lose that interval). Seeded random rates."""
    rng = np.random.default_rng(3)
    integ = DeltaIntegrator(3, 0.01)
    exact_a = np.zeros(3)
    exact_v = np.zeros(3)
    sums = []
    for _ in range(200):
        ws = [rng.normal(0, 1e-3, 3) for _ in range(3)]        # tiny rates: the delta is its own log
        fs = [rng.normal(0, 1e-2, 3) for _ in range(3)]
        for w, f in zip(ws, fs):
            out = integ.add(w, f)
        sums.append(out)
        exact_a += sum(ws) * 0.01
        exact_v += sum(fs) * 0.01
    d16 = lambda a, b: (a - b + 32768) % 65536 - 32768
    da = sum(d16(sums[k][0], sums[k - 1][0]) for k in range(1, 200)) + sums[0][0]
    dv = sum(d16(sums[k][1], sums[k - 1][1]) for k in range(1, 200)) + sums[0][1]
    assert np.max(np.abs(da * DANG_LSB_RAD - exact_a)) <= 0.5 * DANG_LSB_RAD + 1e-12
    assert np.max(np.abs(dv * DVEL_LSB_MPS - exact_v)) <= 0.5 * DVEL_LSB_MPS + 1e-9
    # frame 100 lost: frame 101 minus frame 99 is both intervals
    two = d16(sums[101][0], sums[99][0])
    assert np.array_equal(two, d16(sums[101][0], sums[100][0]) + d16(sums[100][0], sums[99][0]))


def test_sums_wrap_at_16_bits():
    """A steady 10 rad/s about z for 1 s in 0.1 s frames: the sum passes +32767 counts (1.638 rad)
    and wraps; each difference of consecutive wrapped sums is still the frame's 1 rad (20000
    counts). Catches a sum clipped at the i16 limit."""
    integ = DeltaIntegrator(10, 0.01)
    prev = np.zeros(3, dtype=int)
    for _ in range(10):
        for _ in range(10):
            out = integ.add([0.0, 0.0, 10.0], [0.0, 0.0, 0.0])
        d = (out[0] - prev + 32768) % 65536 - 32768
        assert d[2] == 20000
        prev = out[0]
