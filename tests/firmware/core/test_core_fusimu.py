"""The fused trackers' per-IMU-sample path on the compiled core (firmware_py/core/src/fusimu.c:
ct_fus_propagate with ct_fus_set_dt, ct_fus_to_source, ct_fus_output with ct_quat_from_elements,
ct_ori_predict, ct_ori_incl_begin, ct_ori_compass_fill, ct_ori_apply, ct_ori_post_acc) against
its Python reference (estimate/fusion_prediction.py InertialPrediction.push / propagate /
set_dt / history, fusion_output.PoseOutput.queue, orientation.OrientationFilter.predict /
update_acc / update_mag), and the pieces against independent references (scipy's rotations and
quaternions, numpy's products, the closed forms of eqs 6.10, 6.13-6.14 and sec 6.2.4's Q).

The interpolation, the history and output rows and the quaternion are the reference's
operations in the same order (bit-identical); the step's attitude product and covariance go
through BLAS in the reference, so the states are compared to 1e-12 relative (1e-9 over a closed
loop of thousands of samples, the bench reports' contract). Seeded; skips where the extension is
not built."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.estimate.fusion_output import (OUT_DEAD_RECKONING, OUT_INCONSISTENT, OUT_LOST, OUT_P,
                                                      OUT_Q, OUT_RECOVERED, OUT_STALE, OUT_STATUS, OUT_VAR_O,
                                                      OUT_VAR_P, PoseOutput)
from coiltrack.firmware.estimate.fusion_state import (HIST_FIELDS, HIST_P, HIST_R, IMU_FIELDS, IMU_PHI,
                                                     FixedSource, InsState, MovingSource)
from coiltrack.firmware.estimate.layout import ACC, GYR, ORI, POS, VEL
from coiltrack.firmware.estimate.magnetic_inertial import FusionFilter, FusionParams
from coiltrack.firmware.estimate.orientation import SUM_CA, SUM_INCL_DT, OrientationFilter, OrientationParams
from coiltrack.firmware.ring import Ring
from coiltrack.firmware.rotation import quat_from_elements

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

G = np.array([0.0, 0.0, 9.81])
H = np.array([0.2e-4, 0.0, -0.45e-4])       # earth field, global frame (north, west, up), T


def _rel(a, b):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b)))) / max(float(np.max(np.abs(a))), 1e-300)


def _fusion_pair(fixed: bool, model: int = 1):
    prm = FusionParams.from_config(None, measurement_model=model, acc_bias_tau_s=2.0, gyro_bias_tau_s=3.0,
                                   source_imu=not fixed)
    c = core.load("compiled")
    ref = FusionFilter(prm, OrientationFilter(OrientationParams.from_config(None), core.PYTHON),
                       fixed_source=fixed, core=core.PYTHON)
    got = FusionFilter(prm, OrientationFilter(OrientationParams.from_config(None), c), fixed_source=fixed, core=c)
    assert ref.push_imu.__func__ is FusionFilter.push_imu
    assert got.push_imu.__func__ is FusionFilter._push_imu_compiled
    return ref, got


def _start(ff, rng_state, t0: int, s0) -> None:
    """The same running state in both filters (a rotation near pi, offsets, a full covariance)."""
    rng = np.random.default_rng(rng_state)
    ff.push_imu(t0, *s0)
    st = ff.st
    n = st.P.shape[0]
    M = rng.normal(size=(n, n))
    st.p[:] = (0.1, -0.2, 0.3)
    st.v[:] = (0.4, 0.1, -0.2)
    st.Th[:] = Rotation.from_rotvec([math.pi - 1e-6, 0.2, 0.0]).as_matrix()
    st.ba[:] = (0.02, -0.01, 0.03)
    st.bg[:] = (0.004, -0.003, 0.002)
    st.P[:] = 1e-4 * (M @ M.T)
    st.t_us = t0
    ff.initialized = True


def _sample(rng, i: int, fixed: bool):
    f = G + rng.normal(size=3)
    w = rng.normal(size=3) * (1e-8 if i % 9 == 0 else 1.5)
    r = G + 0.05 * rng.normal(size=3)
    phi = np.eye(3) if fixed else Rotation.from_rotvec(0.3 * rng.normal(size=3)).as_matrix()
    return (*f, *w, *r, phi)


@pytest.mark.parametrize("fixed", [True, False])
def test_fused_samples_match_the_reference(fixed):
    """400 IMU samples at jittered steps (8333 / 8334 us and now and then a longer one: the step's
    static blocks rewritten), with snapshots scheduled inside steps (the split path) and one
    sample not newer than the state (refused): the fused outputs (position, quaternion,
    variances, status) and the history rows bit-identical or to 1e-12, the states to 1e-12,
    the step workspace (dt_last, ka, kg) equal. A wrong interpolation weight, a row of Phi where
    its column is due or the velocity's Q of the source's noise left out are off by far more."""
    rng = np.random.default_rng(41 + fixed)
    ref, got = _fusion_pair(fixed)
    t0 = 1_000_000
    s0 = _sample(rng, 1, fixed)
    for ff in (ref, got):
        _start(ff, 5, t0, s0)
    t = t0
    for i in range(400):
        t += 8333 + (i % 2) if i % 37 else int(rng.integers(2000, 30000))
        if i % 60 == 10:
            for ff in (ref, got):
                ff.schedule_snapshot(t + 4000)
        s = _sample(rng, i, fixed)
        tt = t - 5000 if i == 200 else t          # one sample older than the state
        assert ref.push_imu(tt, *s) == got.push_imu(tt, *s), i
        if i % 40 == 0 or i == 399:
            for name in ("p", "v", "Th", "ba", "bg", "P"):
                assert _rel(getattr(ref.st, name), getattr(got.st, name)) < 1e-12, (name, i)
            assert ref.st.t_us == got.st.t_us
            np.testing.assert_array_equal(got.st.ws, ref.st.ws)
        while True:
            kr, kg = ref.pop_output(), got.pop_output()
            assert (kr < 0) == (kg < 0)
            if kr < 0:
                break
            a, b = ref.out_d[kr], got.out_d[kg]
            assert ref.out_t[kr] == got.out_t[kg]
            assert a[OUT_STATUS] == b[OUT_STATUS]
            assert _rel(a, b) < 1e-12, i
            ref.release_output()
            got.release_output()
    assert ref.snap.valid and got.snap.valid and _rel(ref.sn.P, got.sn.P) < 1e-12
    assert len(ref.hist) == len(got.hist) > 20
    assert _rel(ref.hist.d, got.hist.d) < 1e-12
    assert ref.steps == got.steps > 400



@pytest.mark.parametrize("fixed", [True, False])
def test_one_call_sample_matches_the_reference(fixed):
    """The forward path in one call (``ext.FusLive.sample`` through ``InertialPrediction.sample``)
    against the Python reference over 300 samples whose fused poses are taken off the output
    queue only every 20th sample, so the queue fills and drops: the queued rows, their times, the
    drop count, the history and the state the same (to 1e-12: the reference's step goes through
    BLAS), and bit-identical to the compiled kernels called one by one (``_after_push``), with
    the one-call path taken for most samples and left for the steps after which ``P`` is
    symmetrised (its variances would read it) and for a full queue. A pose queued before the
    symmetrisation, a row written into a full queue or a history row of the previous step differ
    by far more."""
    rng = np.random.default_rng(7 + fixed)
    ref, got = _fusion_pair(fixed)
    sep = _fusion_pair(fixed)[1]             # the compiled kernels one call each
    sep.push_imu = lambda t, *a: sep._after_push(t, sep.prediction.push(t, *a))
    calls = []
    one_call = got.prediction.sample
    got.prediction.sample = lambda *a: (calls.append(a[4]), one_call(*a))   # (o: the output slot)
    t = 2_000_000
    s0 = _sample(rng, 1, fixed)
    for ff in (ref, got, sep):
        _start(ff, 9, t, s0)
    for i in range(300):
        t += 8333 + (i % 3 == 0)
        s = _sample(rng, i, fixed)
        assert ref.push_imu(t, *s) == got.push_imu(t, *s) == sep.push_imu(t, *s) is True, i
        if i % 20 == 19:
            while True:
                kr, kg, ks = ref.pop_output(), got.pop_output(), sep.pop_output()
                assert (kr < 0) == (kg < 0) == (ks < 0)
                if kr < 0:
                    break
                assert ref.out_t[kr] == got.out_t[kg] == sep.out_t[ks]
                assert ref.out_d[kr][OUT_STATUS] == got.out_d[kg][OUT_STATUS]
                assert _rel(ref.out_d[kr], got.out_d[kg]) < 1e-12, i
                np.testing.assert_array_equal(got.out_d[kg], sep.out_d[ks])
                for ff in (ref, got, sep):
                    ff.release_output()
    assert ref.out_dropped == got.out_dropped == sep.out_dropped > 40
    assert 150 < len(calls) < 300 - 300 // 16 and min(calls) >= 0
    for name in ("p", "v", "Th", "ba", "bg", "P"):
        assert _rel(getattr(ref.st, name), getattr(got.st, name)) < 1e-12, name
    assert ref.st.t_us == got.st.t_us and ref.steps == got.steps
    assert ref.st.pred.count == got.st.pred.count
    np.testing.assert_array_equal(got.hist.t, ref.hist.t)
    assert _rel(ref.hist.d, got.hist.d) < 1e-12
    np.testing.assert_array_equal(got.imu.d, ref.imu.d)
    np.testing.assert_array_equal(got.imu.t, ref.imu.t)
    for name in ("p", "v", "Th", "ba", "bg", "P", "ws"):
        np.testing.assert_array_equal(getattr(got.st, name), getattr(sep.st, name), err_msg=name)
    np.testing.assert_array_equal(got.hist.d, sep.hist.d)


def test_step_workspace_is_the_closed_form():
    """After one compiled step of dt: A's POS-VEL block dt I (eq 6.10), the offsets' decay
    exp(-dt / tau) (eqs 6.13-6.14) and Q's diagonal (sec 6.2.4: velocity (s_a^2 + s_as^2) dt^2,
    orientation (s_g dt)^2, offsets rw^2 dt), and the step written into the state's ws."""
    _, got = _fusion_pair(True)
    prm = got.prm
    rng = np.random.default_rng(7)
    s0 = _sample(rng, 1, True)
    _start(got, 3, 2_000_000, s0)
    dt_us = 8334
    got.push_imu(2_000_000 + dt_us, *s0)
    dt = dt_us * 1e-6
    A, Q = got.st.pred.A, got.st.pred.Q
    np.testing.assert_array_equal(A[POS, VEL], dt * np.eye(3))
    assert A[ACC.start, ACC.start] == math.exp(-dt / 2.0) and A[GYR.start, GYR.start] == math.exp(-dt / 3.0)
    for blk, q in ((VEL, (prm.acc_noise ** 2 + prm.source_acc_noise ** 2) * dt * dt), (ORI, (prm.gyro_noise * dt) ** 2),
                   (ACC, prm.acc_bias_rw ** 2 * dt), (GYR, prm.gyro_bias_rw ** 2 * dt)):
        np.testing.assert_allclose(np.diag(Q)[blk], q, rtol=1e-15, atol=0)
    assert tuple(got.st.ws) == (dt, math.exp(-dt / 2.0), math.exp(-dt / 3.0))


def _output_pair(moving: bool, n: int = 21):
    prm = FusionParams.from_config(None, measurement_model=1)
    frame = MovingSource() if moving else FixedSource()
    out = []
    for c in (core.PYTHON, core.load("compiled")):
        st = InsState(n, None)
        imu = Ring(8, IMU_FIELDS)
        hist = Ring(8, HIST_FIELDS)
        out.append((PoseOutput(prm, 4, frame, c, st, imu, hist), st, imu, hist))
    return prm, frame, out


@pytest.mark.parametrize("moving", [False, True])
def test_output_rows_match_the_reference_and_scipy(moving):
    """Rotations through every branch of Shepperd's method (trace > 0, each diagonal element the
    largest, angles near pi about each axis) and ages through every status bit: the compiled
    output row equals PoseOutput.queue's to the bit; the quaternion is scipy's (up to sign,
    w >= 0, 1e-12), the variances numpy's diag(Phi^T P_pp Phi) and diag(Th^T P_oo Th)."""
    rng = np.random.default_rng(51 + moving)
    prm, frame, pair = _output_pair(moving)
    rots = [np.eye(3)] + [Rotation.from_rotvec(math.pi * np.eye(3)[a] * s).as_matrix()
                          for a in range(3) for s in (1.0, 1.0 - 1e-9)]
    rots += [Rotation.from_rotvec(v).as_matrix() for v in rng.normal(size=(20, 3)) * 1.5]
    ages = (0, prm.stale_us + 1, prm.dead_reckon_after_us + 1, prm.dead_reckon_limit_us + 1)
    for i, Th in enumerate(rots):
        phi = Rotation.from_rotvec(0.4 * rng.normal(size=3)).as_matrix() if moving else np.eye(3)
        p = rng.normal(size=3)
        M = rng.normal(size=(21, 21))
        P = M @ M.T
        age = ages[i % 4]
        rows = []
        for po, st, imu, hist in pair:
            st.p[:], st.Th[:], st.P[:] = p, Th, P
            k = imu.push(1000 + i)
            frame.store(imu.dv, k, memoryview(phi))
            h = hist.push(1000 + i)
            frame.to_source(imu.dv, k, st._pv, st._Thv, hist.dv, h)
            po.queue(1000 + i, hist, st, imu.dv, k, 1000 + i - age, i % 3 == 0, i % 5 == 0)
            s = po.pop()
            rows.append(po.out.d[s].copy())
            po.release()
            hrow = hist.d[h, HIST_R:HIST_R + 9].copy()
        np.testing.assert_array_equal(rows[1], rows[0])
        r = rows[1]
        R_ms = phi.T @ Th
        q = Rotation.from_matrix(R_ms).as_quat(canonical=False)      # (x, y, z, w)
        q = np.array([q[3], q[0], q[1], q[2]])
        q = q if q[0] > 0 or (q[0] == 0 and r[OUT_Q] == 0) else -q
        assert np.max(np.abs(r[OUT_Q:OUT_Q + 4] - q)) < 1e-12 or abs(q[0]) < 1e-8, i
        assert r[OUT_Q] >= 0.0
        assert tuple(r[OUT_Q:OUT_Q + 4]) == quat_from_elements(*(float(x) for x in hrow))
        np.testing.assert_allclose(r[OUT_P:OUT_P + 3], phi.T @ p, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(r[OUT_VAR_P:OUT_VAR_P + 3], np.diag(phi.T @ P[POS, POS] @ phi), rtol=1e-12)
        np.testing.assert_allclose(r[OUT_VAR_O:OUT_VAR_O + 3], np.diag(Th.T @ P[ORI, ORI] @ Th), rtol=1e-12)
        want = ((age > prm.stale_us) * OUT_STALE | (age > prm.dead_reckon_after_us) * OUT_DEAD_RECKONING
                | (age > prm.dead_reckon_limit_us) * OUT_LOST | (i % 3 == 0) * OUT_RECOVERED
                | (i % 5 == 0) * OUT_INCONSISTENT)
        assert r[OUT_STATUS] == want, i


def test_history_row_is_the_source_frame_pose():
    """ct_fus_to_source against numpy: p_M = Phi^T p, R_MS = Phi^T Theta (eq 6.7) for a moving
    source; the identity frame copies (a transposed Phi gives another row)."""
    c = core.load("compiled")
    rng = np.random.default_rng(61)
    ff = FusionFilter(FusionParams.from_config(None, measurement_model=1, source_imu=True), core=c)
    pr, st = ff.prediction, ff.st
    phi = Rotation.from_rotvec([0.3, -1.0, 0.5]).as_matrix()
    st.p[:] = rng.normal(size=3)
    st.Th[:] = Rotation.from_rotvec([2.0, 0.1, -0.4]).as_matrix()
    k = pr.push(5, *rng.normal(size=9), phi)
    np.testing.assert_array_equal(pr.imu.d[k, IMU_PHI:IMU_PHI + 9], phi.reshape(9))
    st.t_us = 5
    pr.history(st, ff.hist, k)
    h = ff.hist.peek(0)
    np.testing.assert_allclose(ff.hist.d[h, HIST_P:HIST_P + 3], phi.T @ st.p, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(ff.hist.d[h, HIST_R:HIST_R + 9], (phi.T @ st.Th).reshape(9), rtol=0, atol=1e-15)


@pytest.mark.parametrize("gain", [0.0, 0.5])
def test_orientation_sample_path_matches_the_reference(gain):
    """The orientation filter's per-sample prediction and its two updates, with the adaptive
    motion variance on (Inclination.observe's time since the last update, SUM_INCL_DT) and off,
    updates every third sample, a free-fall sample and a magnetic disturbance: the sums
    (SUM_*), the compass's state, the acceleration a+ and the flags equal at every sample (the
    sums to 1e-15), R, P, offset and disturbance to 1e-9 relative. Against scipy: the orientation
    tracks the true one within 5 degrees."""
    rng = np.random.default_rng(71)
    prm = OrientationParams.from_config(None, mag_learn_samples=20, acc_adapt_gain=gain, acc_adapt_tau_s=0.5,
                                        acc_corr_time_s=0.02 if gain else 0.0)
    ref = OrientationFilter(prm, core.PYTHON)
    got = OrientationFilter(prm, core.load("compiled"))
    assert ref.predict.__func__ is OrientationFilter.predict
    assert got.predict.__func__ is OrientationFilter._predict_compiled
    R = Rotation.from_rotvec([0.1, -0.2, 0.3])
    w_true = np.array([0.3, -0.2, 0.9])
    for i in range(1500):
        t = i * 10_000 + (i % 3) * 7
        R = R * Rotation.from_rotvec(w_true * 0.01)
        Rm = R.as_matrix()
        acc = Rm.T @ G + 0.3 * rng.normal(size=3)
        if i == 900:
            acc = acc * 0.2
        mag = Rm.T @ (H + (0.1e-4 * np.array([1.0, 0.5, 0.0]) if i > 700 else 0.0)) + 5e-8 * rng.normal(size=3)
        gyr = w_true + 0.01 * rng.normal(size=3) + 0.02
        out = []
        for f in (ref, got):
            if not f.initialized:
                out.append(f.initialize(t, *acc, *mag))
                continue
            f.predict(t, *gyr)
            out.append((f.update_acc(*acc), f.update_mag(*mag)) if i % 3 == 0 else None)
        assert out[0] == out[1], i
        assert _rel(ref.sums, got.sums) <= 1e-15 or np.array_equal(ref.sums, got.sums), i
        assert ref.sums[SUM_INCL_DT] == got.sums[SUM_INCL_DT] and ref.sums[SUM_CA] == got.sums[SUM_CA]
        if i % 100 == 0 or i == 1499:
            for name in ("R", "P", "bias", "dist", "acc"):
                a, b = getattr(ref, name), getattr(got, name)
                assert _rel(a, b) < 1e-9, (name, i)
            assert _rel(ref.compass.state, got.compass.state) < 1e-9
            assert abs(ref.acc_motion_ms - got.acc_motion_ms) <= 1e-9 * max(ref.acc_motion_ms, 1e-30)
    assert got.upd_acc.count == ref.upd_acc.count > 50 and got.upd_mag.count == ref.upd_mag.count > 50
    assert (got.acc_motion_ms > 0.0) == (gain > 0.0)
    assert math.degrees(np.linalg.norm(Rotation.from_matrix(got.R.T @ R.as_matrix()).as_rotvec())) < 5.0


def test_orientation_prediction_is_the_rotation_composition():
    """ct_ori_predict against scipy: R exp([(w - b) dt]x) composed over steps (eq 2.27), the
    disturbance decayed by c_d per step (eq 2.7), the acceleration by exp(-dt / tau_a) (eq 2.5),
    and the sums: time, squared steps, c_d^N, sum c_d^2k qwd."""
    prm = OrientationParams.from_config(None, acc_corr_time_s=0.05)
    f = OrientationFilter(prm, core.load("compiled"))
    Rt = Rotation.from_rotvec([0.5, -1.0, 2.5])
    f.initialize(0, 0.0, 0.0, 9.81, 2e-5, 0.0, -4.5e-5)
    f.R[:] = Rt.as_matrix()
    f.set_bias(0.01, -0.02, 0.03)
    f.dist[:] = (0.1, 0.2, -0.3)
    f.acc[:] = (0.5, -0.5, 1.0)
    w = np.array([0.7, -0.4, 1.1])
    steps = (10_000, 10_001, 9_999, 20_000)
    t = 0
    qd = 0.0
    for dt_us in steps:
        t += dt_us
        f.predict(t, *w)
        dt = dt_us * 1e-6
        Rt = Rt * Rotation.from_rotvec((w - (0.01, -0.02, 0.03)) * dt)
        qd = qd * prm.dist_corr ** 2 + f.compass.qwd
    T = sum(steps) * 1e-6
    np.testing.assert_allclose(f.R, Rt.as_matrix(), rtol=0, atol=1e-14)
    np.testing.assert_allclose(f.dist, np.array([0.1, 0.2, -0.3]) * prm.dist_corr ** 4, rtol=1e-14)
    np.testing.assert_allclose(f.acc, np.array([0.5, -0.5, 1.0]) * math.exp(-T / prm.acc_corr_time_s), rtol=1e-13)
    np.testing.assert_allclose(f.sums[:4], (T, sum((s * 1e-6) ** 2 for s in steps), prm.dist_corr ** 4, qd),
                               rtol=1e-14)


def test_bad_bindings_are_refused():
    """A kernel bound to a buffer of the wrong type or size is refused with the buffer's name; a
    slot outside the ring is an IndexError, not a write past it."""
    ext = core.load("compiled").ext
    n = 21
    z = lambda *s: np.zeros(s)  # noqa: E731
    args = [n, z(3), z(3), z(3, 3), z(3), z(3), z(n, n), z(n, n), z(n, n), z(n, n), np.zeros(8, dtype=np.int64),
            z(8, 18), z(3), 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, True]
    k = ext.FusPred(*args)
    with pytest.raises(IndexError):
        k.propagate(8, 2, 0, 10)
    bad = list(args)
    bad[7] = z(n, n - 1)
    with pytest.raises(TypeError, match="P"):
        ext.FusPred(*bad)
    bad = list(args)
    bad[10] = np.zeros(8)                  # times must be int64
    with pytest.raises(TypeError, match="itv"):
        ext.FusPred(*bad)
    row = ext.FusRow(z(8, 18), 8, True)
    with pytest.raises(TypeError, match="Phi"):
        row.store(0, *([0.0] * 9), z(2, 2))
    # the one-call sample: its parts must share the ring, the state and the history it writes
    st = [z(n, n), z(3, 3)]
    args[7], args[3] = st[0], st[1]
    idv, hd, od = z(8, 18), z(8, 12), z(4, 14)
    args[11] = idv
    k = ext.FusPred(*args)
    row = ext.FusRow(idv, 8, True)
    out = ext.FusOutput(n, st[0], st[1], idv, 8, hd, 8, od, 4, True, 1, 2, 3)
    live = ext.FusLive(k, row, out, hd)
    with pytest.raises(IndexError, match="output slot"):
        live.sample(1, 2, 0, 10, 0, 4, 0, False, False, *([0.0] * 9), np.eye(3))
    with pytest.raises(ValueError, match="history"):
        ext.FusLive(k, row, out, z(8, 12))
    with pytest.raises(ValueError, match="share"):
        ext.FusLive(k, ext.FusRow(z(8, 18), 8, True), out, hd)
    with pytest.raises(TypeError):
        ext.FusLive(row, k, out, hd)


def test_report_copies_the_output_row():
    """PoseOutput.into_report on both cores: the POSE record's position, quaternion and six
    variances are the output row's (the same floats; its time is time_us), the returned status its OUT_* bits; a
    record whose lists are too short is refused, not written past."""
    from coiltrack.firmware.transmit import PoseReport

    rng = np.random.default_rng(81)
    prm, frame, pair = _output_pair(True)
    reps = []
    M = rng.normal(size=(21, 21))
    for po, st, imu, hist in pair:
        st.p[:], st.Th[:] = (0.1, 0.2, 0.3), Rotation.from_rotvec([0.3, 0.2, -1.0]).as_matrix()
        st.P[:] = M @ M.T
        k = imu.push(77)
        frame.store(imu.dv, k, memoryview(np.eye(3)))
        h = hist.push(77)
        frame.to_source(imu.dv, k, st._pv, st._Thv, hist.dv, h)
        po.queue(77, hist, st, imu.dv, k, 77 - prm.dead_reckon_after_us - 1, True, False)
        r = PoseReport(3)
        s = po.pop()
        status = po.into_report(s, r)
        r.t_us = po.time_us(s)
        row = po.out.d[s]
        age = prm.dead_reckon_after_us + 1
        want = (age > prm.stale_us) * OUT_STALE | OUT_DEAD_RECKONING | OUT_RECOVERED
        assert status == int(row[OUT_STATUS]) == want
        assert r.t_us == 77 and r.p == list(row[OUT_P:OUT_P + 3]) and r.q == list(row[OUT_Q:OUT_Q + 4])
        assert r.var == list(row[OUT_VAR_P:OUT_VAR_P + 3]) + list(row[OUT_VAR_O:OUT_VAR_O + 3])
        reps.append((r.t_us, r.p, r.q, r.var))
        if po.into_report.__func__ is PoseOutput._into_report_compiled:
            r.var = [0.0] * 5
            with pytest.raises(TypeError, match="var"):
                po.into_report(s, r)
    assert reps[0] == reps[1]


def test_quiet_sample_matches_the_reference():
    """The compass sample's search (``ct_quiet_sample``, ``ext.QuietSample`` through
    ``PulseGate.sample_kernel``) against ``burst_fusion.quiet_sample`` on seeded rings: empty,
    part-filled and wrapped, saturated samples, IMU times between, before and after the samples,
    pulses around them, the age limit and the previous compass sample's time; the same slot
    every time (integer logic: exact). The nearest sample found by brute force too, where one
    qualifies. A search that stops at the newest sample, an inclusive age limit read as exclusive
    or a pulse's fall time left out picks another sample."""
    from coiltrack.firmware.measure.pulse import SampleRing
    from coiltrack.firmware.track.burst_fusion import PulseGate, quiet_sample

    ext = core.load("compiled").ext
    rng = np.random.default_rng(23)
    starts, ends = np.zeros(3, np.int64), np.zeros(3, np.int64)
    gate = PulseGate(starts, ends, 600, 200)
    agree = found = 0
    for case in range(60):
        ring = SampleRing(16)
        k = gate.sample_kernel(ext, ring)
        t = 1_000_000
        for _ in range(int(rng.integers(0, 40))):
            t += int(rng.integers(5000, 12000))
            ring.push(t, 1e-5, 2e-5, -4e-5, rng.random() < 0.1, int(rng.integers(0, 2)))
        t_first = ring.time_at(ring.slot(0)) if len(ring) else t
        starts[:] = np.sort(rng.integers(t_first - 20000, t + 20000, 3))
        ends[:] = starts + int(rng.integers(1000, 15000))
        for _ in range(25):
            t_imu = int(rng.integers(t_first - 30000, t + 30000))
            after = int(rng.integers(t_first - 20000, t + 5000)) if rng.random() < 0.5 else -(1 << 62)
            age = int(rng.choice([8000, 16666, 40000]))
            want = quiet_sample(ring, after, t_imu, age, gate)
            h = ring.last_pushed_slot() + 1
            got = k.find(h if h < ring.capacity else 0, len(ring), after, t_imu, age)
            assert got == want, (case, t_imu, after, age)
            agree += 1
            if want >= 0:
                found += 1
                tw = ring.time_at(want)
                times = [ring.time_at(ring.slot(i)) for i in range(len(ring))]
                assert abs(tw - t_imu) == min(abs(x - t_imu) for x in times)
                assert tw > after and abs(tw - t_imu) <= age and not ring.saturated_at(want)
                assert all(not (a - 200 <= tw <= b + 800) for a, b in zip(starts, ends))
    assert agree == 1500 and found > 100
    with pytest.raises(IndexError):
        gate.sample_kernel(ext, SampleRing(16)).find(16, 0, 0, 0, 0)
    with pytest.raises(TypeError, match="flags"):
        ext.QuietSample(np.zeros(16, np.int64), np.zeros(16), starts, ends, 1, 2)
