"""The compiled single-coil EKF (firmware_py/core/src/single_coil.c, py_single_coil.c) against its
reference, estimate.single_coil.SchepersEKF and estimate.single_coil_update.SingleCoilUpdate in
Python (numpy/BLAS products), and the update against filterpy's Kalman filter.

The scalar steps are the reference's operations in the same order; F P F^T, P H^T, H P H^T, H dx
and R dR go through BLAS in the reference and are summed in index order in C, so the states are
compared to 1e-12 relative (observed ~1e-15); discrete outcomes (flags, clones taken, passes) must
be the same. Seeded; skips where the extension is not built."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_OK
from coiltrack.firmware.estimate.single_coil import ORI, POS, SchepersEKF
from coiltrack.firmware.estimate.single_coil_update import CoilMeasurement
from coiltrack.firmware.model.field import Coil
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COILS = [Coil((0.02, -0.01, 0.0), (1.0, 0.2, 0.1), 0.055, 50),
         Coil((-0.015, 0.03, 0.01), (0.3, 1.0, -0.2), 0.045, 60),
         Coil((0.0, 0.0, -0.025), (0.2, 0.4, 1.0), 0.06, 40)]


def _pair(iterations=3, **kw):
    cfg = FirmwareConfig()
    ref = SchepersEKF.from_config(cfg, iterations=iterations, core=core.PYTHON, **kw)
    got = SchepersEKF.from_config(cfg, iterations=iterations, core=core.load("compiled"), **kw)
    assert (ref.kernels, got.kernels) == ("python", "compiled")
    assert (ref._coil_update.core, got._coil_update.core) == ("python", "compiled")
    return ref, got


def _start(filters, rng, sigma_p=3e-3, sigma_o=0.02):
    R0 = Rotation.from_rotvec(rng.normal(0, 0.5, 3)).as_matrix()
    p0 = np.array([0.25, -0.1, 0.15]) + rng.normal(0, 0.02, 3)
    A = rng.normal(size=(6, 6))
    P6 = np.diag([sigma_p ** 2] * 3 + [sigma_o ** 2] * 3) + 1e-7 * (A @ A.T)
    for e in filters:
        e.initialize(p0, R0, P6, 0, 0.05, 0.02, 0.003)


def _close(a, b, what, rtol=1e-12):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = max(float(np.abs(a).max()), 1e-300)
    np.testing.assert_allclose(b, a, rtol=0, atol=rtol * scale, err_msg=what)


def _same_state(ref, got, rtol=1e-12):
    for name in ("p", "v", "R", "ba", "bg", "f", "w", "clone_p", "clone_R"):
        _close(getattr(ref, name), getattr(got, name), name, rtol)
    _close(ref.P, got.P, "P", rtol)
    assert ref.t_us == got.t_us
    np.testing.assert_array_equal(ref.clone_due, got.clone_due)
    np.testing.assert_array_equal(ref.clone_taken, got.clone_taken)


def _imu(rng, t):
    """A turning, accelerating sensor's specific force and rate (sensor frame) at t us."""
    s = t * 1e-6
    f = np.array([0.3 * math.sin(2.1 * s), -0.2 * math.cos(1.3 * s), 9.81]) + rng.normal(0, 0.02, 3)
    w = np.array([0.8 * math.sin(1.7 * s), 0.5, -0.6 * math.cos(0.9 * s)]) + rng.normal(0, 0.01, 3)
    return f, w


def _run_imu(filters, rng, n=150, dt_us=10_000, clones=True):
    t = 0
    for i in range(n):
        t += dt_us + int(rng.integers(-300, 300))
        f, w = _imu(rng, t)
        if clones and i % 20 == 5:
            for e in filters:              # a clone inside the next interval: the step is split
                e.schedule_clone(0, t + 3_700)
        if clones and i % 20 == 15:
            for e in filters:
                e.release_clone(0)
        if clones and i % 37 == 7:
            for e in filters:              # a clone at or before the filter's time: taken now
                e.schedule_clone(1, t - 2_000)
        for e in filters:
            e.propagate(t, f, w)
    return t


def test_propagation_matches_the_reference():
    """150 IMU samples of a turning sensor with clones taken inside intervals, before them and
    released, past two orthonormalisations (every 64 steps): the nominal state, P and the
    clones equal to 1e-12 relative. A dropped dt^2 term, a transposed R or a clone taken at the
    wrong step is off by orders more."""
    rng = np.random.default_rng(7)
    ref, got = _pair()
    _start((ref, got), rng)
    _run_imu((ref, got), np.random.default_rng(8))
    assert ref._steps == got._ck.steps() > 128
    _same_state(ref, got)


@pytest.mark.parametrize("initialized", [True, False])
def test_a_clone_predicted_backwards_matches_the_reference(initialized):
    """back_clone (the acquisition's refinement: a pulse measured before the filter started):
    the clone's nominal pose p - v dt, R G and its rows and columns of P (T P, T P T^T), equal to
    1e-12 relative; a transposed G or a dropped dt term is off by far more."""
    rng = np.random.default_rng(51)
    ref, got = _pair()
    if initialized:
        _start((ref, got), rng)
    _run_imu((ref, got), np.random.default_rng(52), n=12, clones=False)
    G = Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
    for e in (ref, got):
        e.back_clone(1, 0.137, G)
    _same_state(ref, got)
    assert got.clone_taken[1] and not got.clone_due[1]
    if initialized:
        b = got.clones.cp[1].start
        assert np.abs(got.P[b:b + 3, b:b + 3] - ref.P[POS, POS]).max() > 1e-9     # not a plain copy


def test_propagation_before_initialisation_carries_only_the_nominal_state():
    """Without a pose the covariance is not propagated (P stays 0) but the strapdown runs."""
    ref, got = _pair()
    _run_imu((ref, got), np.random.default_rng(3), n=40)
    assert not got.P.any()
    _same_state(ref, got)


def test_prediction_ahead_and_core_transition_match_the_reference():
    """predict_pose (8 steps of the core block) and core_transition (the transition a reference
    covariance beside the filter uses) against the reference, after some propagation."""
    rng = np.random.default_rng(11)
    ref, got = _pair()
    _start((ref, got), rng)
    _run_imu((ref, got), np.random.default_rng(12), n=30)
    for horizon, steps in ((120_000, 8), (35_000, 3), (0, 8), (-50, 2)):
        outs = []
        for e in (ref, got):
            P6, pp = np.zeros((6, 6)), np.zeros(3)
            e.predict_pose(horizon, P6, pp, steps)
            outs.append((P6, pp))
        _close(outs[0][0], outs[1][0], f"P6 at {horizon}")
        _close(outs[0][1], outs[1][1], f"position at {horizon}")
    Fs, qs = [], []
    for e in (ref, got):
        F, q = np.eye(15), np.zeros(15)
        e.core_transition(memoryview(F), q, 0.013)
        Fs.append(F)
        qs.append(q)
    _close(Fs[0], Fs[1], "F")
    np.testing.assert_array_equal(qs[0], qs[1])
    # the prediction left the filters as they were
    _same_state(ref, got)


@pytest.mark.parametrize("angle", [0.3, 2.0, math.pi - 1e-9, math.pi])
def test_pose_values_are_the_reference_bit_for_bit(angle):
    """The POSE values (position, quaternion by Shepperd's method in each of its four branches,
    variances, position trace): the same operations, so equal bit for bit; the quaternion also
    against scipy (sign fixed by w >= 0) to 1e-12, near and at a half turn."""
    rng = np.random.default_rng(int(angle * 100))
    ref, got = _pair()
    _start((ref, got), rng)
    for axis in np.eye(3).tolist() + [[1.0, 1.0, 1.0]]:
        rot = Rotation.from_rotvec(np.array(axis) / np.linalg.norm(axis) * angle)
        for e in (ref, got):
            e.R[:] = rot.as_matrix()
        a, b = np.zeros(14), np.zeros(14)
        ref.pose_values(a)
        got.pose_values(b)
        np.testing.assert_array_equal(a, b)
        x, y, z, w = rot.as_quat()
        q = np.array([w, x, y, z]) * (1.0 if w > 0 or (w == 0 and x >= 0) else -1.0)
        assert abs(abs(float(np.dot(b[3:7], q))) - 1.0) < 1e-12
        np.testing.assert_array_equal(b[7:10], np.diag(ref.P)[POS])
        np.testing.assert_array_equal(b[10:13], np.diag(ref.P)[ORI])
        assert b[13] == ref.P[0, 0] + ref.P[1, 1] + ref.P[2, 2]


def _truth_amplitude(model, p, R, coil, current):
    model.evaluate(p, R)
    return model.h[coil] * current


@pytest.mark.parametrize("iterations, offset_m", [(1, 0.0), (3, 0.0), (3, 0.02), (4, 0.04)])
def test_pulse_updates_match_the_reference(iterations, offset_m):
    """Pulses of each coil applied through clone 0 and the current state, with a prior off by
    ``offset_m`` (iterated passes after an acquisition-sized error, a single pass while
    tracking), an inflated covariance (r_scale) and a column view as the amplitude: the same
    flags and NIS, state and P equal to 1e-12 relative."""
    rng = np.random.default_rng(int(offset_m * 1000) + iterations)
    ref, got = _pair(iterations)
    _start((ref, got), rng, sigma_p=max(offset_m, 3e-3))
    model_r, model_g = SingleCoilModel(COILS, "exact", core.PYTHON), SingleCoilModel(COILS, "exact", core.load("compiled"))
    truth = SingleCoilModel(COILS, "exact", core.PYTHON)
    t = _run_imu((ref, got), np.random.default_rng(5), n=10, clones=False)
    for j in range(6):
        coil = j % 3
        for e in (ref, got):
            e.schedule_clone(0, t + 2_000)
        f, w = _imu(rng, t + 10_000)
        t += 10_000
        for e in (ref, got):
            e.propagate(t, f, w)
        p_true = ref.clone_p[0] + rng.normal(0, offset_m + 1e-4, 3)
        y = _truth_amplitude(truth, p_true, ref.clone_R[0], coil, 0.9) + rng.normal(0, 3e-9, 3)
        ys = np.zeros((3, 4))
        ys[:, 2] = y                                   # a strided column, as the acquisition hands it
        var = np.full(3, 1e-17)
        k = 0 if j % 2 == 0 else -1
        r_scale = 1.0 if j < 4 else 2.5
        flags = [e.update_pulse(k, CoilMeasurement().set(ys[:, 2], var, coil, 0.9, 3e-3, r_scale, True), m)
                 for e, m in ((ref, model_r), (got, model_g))]
        assert flags[0] == flags[1]
        assert got.nis == pytest.approx(ref.nis, rel=1e-9, abs=1e-12)
        assert got.nis_nominal == pytest.approx(ref.nis_nominal, rel=1e-9, abs=1e-12)
        _same_state(ref, got, rtol=1e-10)
        for e in (ref, got):
            e.release_clone(0)
    assert ref.updates == got.updates > 0 and ref.rejected == got.rejected


def test_a_gated_pulse_leaves_the_filter_alone():
    """An amplitude far from the prediction is gated (chi-square) in both, the state untouched."""
    rng = np.random.default_rng(21)
    ref, got = _pair()
    _start((ref, got), rng)
    models = (SingleCoilModel(COILS, "exact", core.PYTHON), SingleCoilModel(COILS, "exact", core.load("compiled")))
    before = got.P.copy(), got.p.copy()
    y = np.array([1e-4, -2e-4, 3e-4])
    flags = [e.update_single_coil(-1, y, np.full(3, 1e-18), 1, 0.9, m) for e, m in zip((ref, got), models)]
    assert flags[0] == flags[1] and flags[1] & EKF_GATED
    np.testing.assert_array_equal(got.P, before[0])
    np.testing.assert_array_equal(got.p, before[1])
    assert got.rejected == ref.rejected == 1


def test_one_pass_equals_filterpy():
    """An independent reference: one pass (iterations = 1, no second-order correction) is the
    EKF update of filterpy's KalmanFilter (Joseph form) with the same H = I [R^T J, [h]x] at the
    clone's rows, R = var + (rel |h|)^2 + (2 sigma_p^2 / r^2 |h|)^2 and innovation y - h."""
    filterpy = pytest.importorskip("filterpy.kalman")
    rng = np.random.default_rng(31)
    _, got = _pair(iterations=1)
    _start((got,), rng)
    _run_imu((got,), np.random.default_rng(32), n=5, clones=False)
    model = SingleCoilModel(COILS, "exact", core.PYTHON)
    coil, cur, rel = 2, 0.8, 3e-3
    p, R = got.p.copy(), got.R.copy()
    model.evaluate(p, R)
    h, Hu = model.h[coil] * cur, model.H[coil] * cur
    y = h + rng.normal(0, 2e-9, 3)
    var = np.full(3, 4e-18)
    nx = got.nx
    kf = filterpy.KalmanFilter(dim_x=nx, dim_z=3)
    kf.x = np.zeros(nx)
    kf.P = got.P.copy()
    H = np.zeros((3, nx))
    H[:, POS] = Hu[:, 0:3]
    H[:, ORI] = Hu[:, 3:6]
    kf.H = H
    sp2 = max(got.P[i, i] for i in range(POS.start, POS.stop))
    d = p - model.cs.centers[coil]
    hn2 = float(h @ h)
    kf.R = np.eye(3) * (var[0] + (rel * rel + (2.0 * sp2 / float(d @ d)) ** 2) * hn2)
    kf.update(y - h)
    dx = kf.x
    assert got.update_single_coil(-1, y, var, coil, cur, SingleCoilModel(COILS, "exact", core.load("compiled")),
                                  rel) == EKF_OK
    _close(kf.P, got.P, "P", 1e-9)
    _close(p + dx[POS], got.p, "p", 1e-12)
    _close(R @ Rotation.from_rotvec(dx[ORI]).as_matrix(), got.R, "R", 1e-12)


def test_a_subclass_with_its_own_dynamics_keeps_them():
    """The relative filter (tight fusion) steps its own dynamics: its propagation stays the
    Python one, its single-coil update is the compiled one."""
    from coiltrack.firmware.estimate.relative_inertial import RelativeInertialEKF

    e = RelativeInertialEKF.from_config(FirmwareConfig(), core=core.load("compiled"))
    assert e.kernels == "python" and e._coil_update.core == "compiled"
    assert "_advance" not in vars(e) and "_inject" not in vars(e)


@pytest.mark.skipif(not available(), reason="numpy allocation counting needs numpy's C API hooks")
def test_the_compiled_tick_paths_allocate_no_array():
    """Propagation, prediction ahead, clones and updates through the compiled kernels create
    no numpy array."""
    rng = np.random.default_rng(41)
    _, got = _pair()
    _start((got,), rng)
    model = SingleCoilModel(COILS, "exact", core.load("compiled"))
    acc, gyr = np.array([0.1, 0.2, 9.8]), np.array([0.3, -0.1, 0.2])
    P6, pp = np.zeros((6, 6)), np.zeros(3)
    m = CoilMeasurement()
    y, var = np.zeros(3), np.full(3, 1e-17)
    got.propagate(10_000, acc, gyr)
    got.propagate(20_000, acc, gyr)
    model.evaluate(got.p, got.R)
    y[:] = model.h[0] * 0.9
    with NumpyAllocationCounter() as c:
        for t in range(30_000, 230_000, 10_000):
            got.schedule_clone(0, t + 4_000)
            got.propagate(t, acc, gyr)
            got.predict_pose(100_000, P6, pp)
            got.update_pulse(0, m.set(y, var, 0, 0.9, 3e-3, 1.0, True), model)
            got.release_clone(0)
    assert c.count == 0


def test_bad_bindings_are_refused_with_their_names():
    """The glue names what it refuses: a clone index out of range, a non-square transition."""
    _, got = _pair()
    with pytest.raises(ValueError, match="k must be"):
        got.release_clone(5)
    with pytest.raises(TypeError, match="F"):
        got.core_transition(np.zeros((15, 14)), np.zeros(15), 0.01)
    from coiltrack.firmware import _core

    with pytest.raises(ValueError, match="SchepersCore"):
        _core.SchepersCore(10, 2, (), np.zeros(2, dtype=np.int64), np.zeros(2, bool), np.zeros(2, bool), (15, 21),
                           (18, 24), 0.0, 0.0, 0.0, 0.0, 0.0)


def test_a_replayed_adaptive_run_gives_the_same_poses_on_either_core():
    """schepers-adaptive, seed 1, 3 s recorded once and replayed through a firmware on each core
    (tools.bench.framelog): two acquisitions, updates, gated pulses and 200 fused poses; the same
    counts, times, status bits and qualities, positions, quaternions and variances equal to
    1e-12 relative (observed ~1e-15: the products summed in another order)."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools.bench.framelog import replay
    from coiltrack.tools.commands.perf import _record

    header, reads = _record("schepers-adaptive", 1, 3.0, "python")
    runs = {}
    for impl in ("python", "compiled"):
        poses = []

        def factory(cfg, port, impl=impl, poses=poses):
            fw = Firmware(cfg.with_(core={"impl": impl}), port)
            send = fw.tx.pose

            def pose(r):
                poses.append((r.node, r.t_us, r.status, r.quality, *r.p, *r.q, *r.var))
                send(r)
            fw.tx.pose = pose
            return fw
        fw = replay(factory, header, reads)
        tr = fw.tracker
        runs[impl] = (np.array(poses), (tr.updates, tr.gated, tr.unusable, tr.acquisition.acquisitions), fw.core)
    (a, ca, _), (b, cb, core_b) = runs["python"], runs["compiled"]
    assert core_b == "compiled" and ca == cb and ca[0] > 0 and ca[1] > 0 and ca[3] > 0
    assert a.shape == b.shape and a.shape[0] > 100
    np.testing.assert_array_equal(a[:, :4], b[:, :4])
    for j in range(4, a.shape[1]):
        _close(a[:, j], b[:, j], f"pose column {j}")
