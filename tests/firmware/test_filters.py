"""The estimators against independent references (filterpy, batch least
squares) and for consistency (NEES within chi-square bounds), on seeded
synthetic data."""
import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter, rts_smoother
from scipy.stats import chi2

from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NOT_PD, EKF_OK, CovariancePredict, KalmanUpdate, chi2_gate
from coiltrack.firmware.estimate.magnetic_inertial import FusionFilter, FusionParams
from coiltrack.firmware.estimate.layout import ACC, FUSION_LAYOUT, FUSION_XI_LAYOUT, GYR, ORI, POS, VEL, fusion_layout
from coiltrack.firmware.estimate.orientation import OrientationFilter, OrientationParams
from coiltrack.firmware.estimate.smoother import FusionRecorder, rts, smooth
from coiltrack.hil.motion import HandMovedBench, matrix_to_rotvec, rotvec_to_matrix

G = np.array([0.0, 0.0, -9.81])
EARTH = np.array([20e-6, 0.0, -45e-6])
ACC_S, GYR_S = 0.0155, 0.0067          # per-sample noise at 120 Hz (MTx-class, hil.nodes.ImuSpec)
RATE = 120.0


# ------------------------------------------------------------------ layout, one update shape
def test_layout_tables_name_every_slice():
    assert FUSION_LAYOUT.n == 21 and FUSION_XI_LAYOUT.n == 24
    assert fusion_layout(1) is FUSION_LAYOUT and fusion_layout(3) is FUSION_XI_LAYOUT
    names = FUSION_XI_LAYOUT.names()
    assert names == ("POS", "VEL", "ORI", "ACC", "GYR", "QM", "PSI", "XI")
    assert POS == slice(0, 3) and GYR == slice(12, 15)
    assert "eq 6.10" in FUSION_LAYOUT.table()


def test_kalman_update_matches_filterpy_joseph_and_gates():
    rng = np.random.default_rng(0)
    for n, m in ((9, 3), (24, 9), (21, 6)):
        P = rng.normal(size=(n, n))
        P = P @ P.T * 1e-3 + 1e-4 * np.eye(n)
        u = KalmanUpdate(n, m, 1.0)
        u.H[:] = rng.normal(size=(m, n))
        u.R[:] = np.diag(rng.uniform(1e-3, 3e-3, m))
        z = rng.normal(size=m) * 0.05
        u.y[:] = z
        mine = P.copy()
        assert u.update(mine) == EKF_OK
        kf = KalmanFilter(dim_x=n, dim_z=m)
        kf.x = np.zeros(n)
        kf.P = P.copy()
        kf.update(z, R=u.R.copy(), H=u.H.copy())          # filterpy: Joseph form
        np.testing.assert_allclose(mine, kf.P, rtol=1e-10, atol=1e-15)
        np.testing.assert_allclose(u.dx, kf.x, rtol=1e-10, atol=1e-15)
        S = u.H @ P @ u.H.T + u.R
        assert u.nis == pytest.approx(z @ np.linalg.solve(S, z), rel=1e-10)
    # the gate rejects and leaves P alone; a non-PD innovation covariance is reported
    g = KalmanUpdate(3, 3, 0.99)
    assert g.gate == pytest.approx(chi2.ppf(0.99, 3), rel=1e-4)
    P = np.eye(3)
    g.H[:] = np.eye(3)
    g.R[:] = np.eye(3)
    g.y[:] = [10.0, 0.0, 0.0]
    assert g.update(P) == EKF_GATED and np.array_equal(P, np.eye(3)) and not g.dx.any()
    g.R[:] = -5 * np.eye(3)
    g.y[:] = 0.0
    assert g.update(P) == EKF_NOT_PD
    assert chi2_gate(9, 1.0) == math.inf


def test_covariance_predict_matches_filterpy():
    rng = np.random.default_rng(1)
    cp = CovariancePredict(15)
    cp.A[:] = np.eye(15) + 0.01 * rng.normal(size=(15, 15))
    cp.Q[:] = np.diag(rng.uniform(1e-6, 1e-5, 15))
    P = np.eye(15) * 1e-3
    kf = KalmanFilter(dim_x=15, dim_z=1)
    kf.P = P.copy()
    for _ in range(40):
        cp.predict(P)
        kf.predict(F=cp.A, Q=cp.Q)
    np.testing.assert_allclose(P, kf.P, rtol=1e-9)


# ------------------------------------------------------------------ synthetic IMU
def _imu(traj, T, seed, bias=True):
    rng = np.random.default_rng(seed)
    t_us = (np.arange(int(T * RATE)) * (1e6 / RATE)).astype(np.int64) + 1000
    K = traj.kinematics(t_us)
    ba = rng.normal(0, 0.02, 3) if bias else np.zeros(3)
    bg = rng.normal(0, 8.7e-3, 3) if bias else np.zeros(3)
    f = np.einsum("nji,nj->ni", K.R, K.acceleration - G) + ba + rng.normal(0, ACC_S, (t_us.size, 3))
    w = K.angular_velocity + bg + rng.normal(0, GYR_S, (t_us.size, 3))
    m = np.einsum("nji,j->ni", K.R, EARTH) + rng.normal(0, 0.5e-7, (t_us.size, 3))
    return t_us, K, f, w, m, rng


def _orientation_params():
    return OrientationParams.from_config(None, gyro_noise=GYR_S, acc_noise=ACC_S, mag_noise=0.5e-7 / 49e-6, gyro_bias_sigma=0.02,
                             mag_learn_samples=60)


TRAJ = HandMovedBench(seed=1, duration_s=60, v_max=0.12, w_max_deg=30.0)


def test_orientation_filter_matches_filterpy_covariance_recursion():
    """The same predict/update sequence through filterpy (F, Q, H, R and the
    innovation of every step) gives the same covariance and corrections."""
    t_us, K, f, w, m, _ = _imu(TRAJ, 6.0, 4)
    of = OrientationFilter(_orientation_params())
    of.initialize(int(t_us[0]), *f[0], *m[0])
    kf = KalmanFilter(dim_x=9, dim_z=3)
    kf.P = of.P.copy()
    checked = 0
    for i in range(1, t_us.size):
        of.predict(int(t_us[i]), *w[i])
        of.propagate()
        kf.predict(F=of.pred.A.copy(), Q=of.pred.Q.copy())
        np.testing.assert_allclose(of.P, kf.P, rtol=1e-7, atol=1e-16)
        for upd, call, arg in ((of.upd_acc, of.update_acc, f[i]), (of.upd_mag, of.update_mag, m[i])):
            if call(*arg) == EKF_OK:
                kf.x = np.zeros(9)
                kf.update(upd.y.copy(), R=upd.R.copy(), H=upd.H.copy())
                np.testing.assert_allclose(upd.dx, kf.x, rtol=1e-7, atol=1e-13)
                np.testing.assert_allclose(of.P, kf.P, rtol=1e-7, atol=1e-16)
                checked += 1
    assert checked > 700


def chi2_band(dof: int, n: int, p: float = 0.999) -> tuple[float, float]:
    """Two-sided ``p`` band of the mean of ``n`` independent chi-square(dof) samples."""
    lo, hi = chi2.ppf([(1 - p) / 2, (1 + p) / 2], dof * n) / n
    return float(lo), float(hi)


def assert_nees_consistent(per_seed: dict, dof: int) -> None:
    """Every seed's mean NEES and the pooled mean inside their 99.9 % bands
    (samples taken far enough apart to be nearly independent)."""
    for seed, v in per_seed.items():
        lo, hi = chi2_band(dof, len(v))
        assert lo < np.mean(v) < hi, f"seed {seed}: mean NEES {np.mean(v):.2f} outside {lo:.2f}-{hi:.2f} (n={len(v)})"
    pooled = np.concatenate(list(per_seed.values()))
    lo, hi = chi2_band(dof, pooled.size)
    assert lo < pooled.mean() < hi, f"pooled mean NEES {pooled.mean():.2f} outside {lo:.2f}-{hi:.2f} (n={pooled.size})"


#: NEES samples of the orientation filter 5 s apart: the measured autocorrelation of
#: its NEES is 0.70 at 1 s, 0.37 at 3 s and 0.14 at 5 s (seeds 3-8)
ORI_NEES_EVERY = 600


def _orientation_run(seed: int, T: float):
    """No sensor offsets: the orientation error is white-noise driven. NEES of the
    orientation error (3 dof) every ``ORI_NEES_EVERY`` samples (5 s) from 10 s on,
    and the error angle at every 12th sample from 5 s on."""
    t_us, K, f, w, m, _ = _imu(TRAJ, T, seed, bias=False)
    of = OrientationFilter(_orientation_params())
    nees, err = [], []
    for i in range(t_us.size):
        t = int(t_us[i])
        if not of.initialized:
            of.initialize(t, *f[i], *m[i])
            continue
        of.predict(t, *w[i])
        of.update_acc(*f[i])
        of.update_mag(*m[i])
        if i > 600 and i % 12 == 0:
            e = np.array(matrix_to_rotvec(K.R[i] @ of.R.T))      # global frame, true = exp(e) est
            err.append(np.linalg.norm(e))
            if i % ORI_NEES_EVERY == 0:
                Pg = np.zeros((3, 3))
                of.theta_covariance_global(Pg)
                nees.append(e @ np.linalg.solve(Pg, e))
    return np.array(nees), np.array(err)


def test_orientation_filter_is_accurate():
    """No sensor offsets: the orientation error is a few hundredths of a degree."""
    _, err = _orientation_run(3, 30.0)
    assert math.degrees(np.sqrt(np.mean(np.square(err)))) < 0.2


@pytest.mark.xfail(strict=True, reason=(
    "orientation filter overconfident: mean NEES (3 dof) 5.42 / 6.08 / 5.71 for seeds 3 / 4 / 5 "
    "over 60 s (each inside 1.08-6.22, n = 10), pooled 5.73 outside the 99.9 % band 1.74-4.69 "
    "(n = 30); seeds 3-10 pooled 5.84 against 2.18-3.98 (n = 80)"))
def test_orientation_filter_is_consistent():
    """NEES of the orientation error (3 dof), samples 5 s apart over 60 s,
    seeds 3, 4, 5: each seed's mean and the pooled mean inside the 99.9 %
    chi-square band of their sample counts (no widening)."""
    assert_nees_consistent({seed: _orientation_run(seed, 60.0)[0] for seed in (3, 4, 5)}, 3)


def test_orientation_filter_estimates_gyro_offset_and_survives_disturbance():
    """Offsets are estimated; a magnet brought near (a constant extra field
    in the global frame for 3 s) is absorbed by the disturbance state (eq 2.12)
    instead of turning the heading."""
    t_us, K, f, w, m, rng = _imu(TRAJ, 20.0, 5)
    disturbed = (t_us > 8e6) & (t_us < 11e6)
    m = m.copy()
    m[disturbed] += np.einsum("nji,j->ni", K.R[disturbed], np.array([6e-6, -4e-6, 3e-6]))
    of = OrientationFilter(_orientation_params())
    heading = []
    for i in range(t_us.size):
        t = int(t_us[i])
        if not of.initialized:
            of.initialize(t, *f[i], *m[i])
            continue
        of.predict(t, *w[i])
        of.update_acc(*f[i])
        of.update_mag(*m[i])
        if t > 4e6:
            heading.append(abs(matrix_to_rotvec(K.R[i] @ of.R.T)[2]))
    assert math.degrees(max(heading)) < 3.0
    assert math.degrees(float(np.sqrt(np.mean(np.square(heading))))) < 1.0


# ------------------------------------------------------------------ fusion
def _fusion_run(model, T, seed, *, nees=False, recorder=None, mirror=None, bias=True, source=None):
    """Synthetic run of the ch. 6 filter: IMU at 120 Hz, magnetic solutions
    every 600 ms at the burst middle, delivered 170 ms later, drawn from a
    covariance like the solver's (position 2 mm + 1 %, orientation 0.6 deg)."""
    from coiltrack.firmware.pose.reference import crlb
    from coiltrack.firmware.model.field import orthogonal_source

    coils, cur = orthogonal_source(0.055, 50), np.full(3, 1.5)
    t_us, K, f, w, m, rng = _imu(TRAJ, T, seed, bias=bias)
    of = OrientationFilter(_orientation_params())
    ff = FusionFilter(FusionParams.from_config(None, measurement_model=model, acc_noise=ACC_S, gyro_noise=GYR_S,
                                   gyro_bias_sigma=0.02), of if model != 1 else None,
                      fixed_source=source is None)
    ff.attach_recorder(recorder)
    phi = np.eye(3)
    fr = np.array([0.0, 0.0, 9.81])
    next_ref = 330_000
    ff.schedule_snapshot(next_ref)
    pending = []
    out = {"nees": [], "err": [], "mag": []}
    for i in range(t_us.size):
        t = int(t_us[i])
        if not of.initialized:
            of.initialize(t, *f[i], *m[i])
        else:
            of.predict(t, *w[i])
            of.update_acc(*f[i])
            of.update_mag(*m[i])
        if source is not None:
            phi, fr = source(t)
        ff.push_imu(t, *f[i], *w[i], *fr, phi)
        if mirror is not None:
            mirror(ff, "step")
        while ff.pop_output() >= 0:
            ff.release_output()
        if t >= next_ref and not pending:
            k = TRAJ.kinematics(next_ref)
            C = crlb(k.position, k.R, coils, cur, 2.5e-8)
            d = rng.multivariate_normal(np.zeros(6), C)
            pending.append((next_ref, k.position - d[:3], k.R @ rotvec_to_matrix(-d[3:]), C, t + 170_000))
            out["mag"].append(np.linalg.norm(d[:3]))
            next_ref += 600_000
        if pending and t >= pending[0][4]:
            ref, q, R, C, _ = pending.pop()
            fl = ff.magnetic_update(ref, q, R, C)
            assert fl in (0, 512)
            ff.schedule_snapshot(next_ref)
        if ff.initialized and t > 8e6:
            out["err"].append(np.linalg.norm(ff.p - K.position[i]))
            if nees and i % 30 == 0:
                out["nees"].append(ff.nees(K.position[i], K.R[i], K.velocity[i]))
    out["filter"] = ff
    return out


#: fusion NEES samples 2 s apart (every 8th of those taken every 0.25 s): the measured
#: autocorrelation of its NEES is 0.24 at 1 s, 0.10 at 2 s, 0.06 at 3 s (model 1, seeds 11-18)
FUSION_NEES_THIN = 8


@pytest.mark.parametrize("model", [1, 3])
def test_fusion_is_consistent_nees_within_chi_square(model):
    """Normalised estimation error squared of position, velocity and
    orientation (9 dof) after convergence, samples 2 s apart, seeds 11, 12, 13:
    each seed's mean and the pooled mean inside the 99.9 % chi-square band of
    their sample counts (no widening); the fused position beats the magnetic
    solutions it was given."""
    per_seed = {}
    for seed in (11, 12, 13):
        r = _fusion_run(model, 40.0, seed, nees=True, bias=False)
        per_seed[seed] = np.array(r["nees"])[::FUSION_NEES_THIN]
        assert np.sqrt(np.mean(np.square(r["err"]))) < np.sqrt(np.mean(np.square(r["mag"])))
    assert_nees_consistent(per_seed, 9)


def test_fusion_covariance_matches_filterpy():
    """Every predict (A, Q) and magnetic update (H, R, innovation, with the
    white blocks the filter sets) replayed through filterpy gives the same
    covariance; the rewind/replay of the delayed update is the same
    recursion applied in time order."""
    from coiltrack.firmware.estimate.magnetic_inertial import FusionFilter as FF

    log = []

    class Mirror:
        def on_init(self, fus, st):
            log.append(("init", st.t_us, st.P.copy()))

        def on_step(self, fus, st, k, t1):
            log.append(("step", t1, st.pred.A.copy(), st.pred.Q.copy(), st.P.copy()))

        def on_rewind(self, fus, t0):
            # the steps after t0 are replayed: forget them (the update at t0 stays)
            n = len(log)
            while n and log[n - 1][0] != "init" and (log[n - 1][1] > t0 or log[n - 1][0] != "step"):
                n -= 1
            log[n:] = [e for e in log[n:] if e[0] != "step"]

        def on_prior(self, fus, st):
            log.append(("prior", st.t_us, st.P.copy()))

        def on_update(self, fus, st, dx):
            log.append(("update", st.t_us, fus.upd.H.copy(), fus.upd.R.copy(), fus.upd.y.copy(),
                        np.array(dx), st.P.copy()))

    assert FF  # noqa
    _fusion_run(3, 8.0, 5, recorder=Mirror())
    kf = None
    steps = updates = 0
    for entry in log:
        if entry[0] == "init":
            kf = KalmanFilter(dim_x=24, dim_z=9)
            kf.P = entry[2].copy()
        elif entry[0] == "step":
            kf.predict(F=entry[2], Q=entry[3])
            np.testing.assert_allclose(kf.P, entry[4], rtol=1e-8, atol=1e-18)
            steps += 1
        elif entry[0] == "prior":
            kf.P = entry[2].copy()           # the white blocks set for this measurement
        elif entry[0] == "update":
            kf.x = np.zeros(24)
            kf.update(entry[4], R=entry[3], H=entry[2])
            np.testing.assert_allclose(kf.x, entry[5], rtol=1e-8, atol=1e-12)
            np.testing.assert_allclose(kf.P, entry[6], rtol=1e-8, atol=1e-18)
            updates += 1
    assert steps > 800 and updates >= 10


def test_fusion_models_and_delayed_update_and_reported_pose():
    for model in (1, 2, 3):
        r = _fusion_run(model, 16.0, 2)
        ff = r["filter"]
        assert ff.updates >= 20 and ff.rejected == 0
        assert np.sqrt(np.mean(np.square(r["err"]))) < 0.02
    # the delayed update lands at t_ref: after replay the filter is at the newest sample
    assert ff.t_us == ff.imu_t[ff.imu.peek(0)] and not ff.replaying


def test_moving_source_net_acceleration_eq_6_8():
    """Source and sensor both accelerate (a common sway); with the source's
    specific force and orientation (eq 6.8, a_net = a_sensor - a_source) the
    filter tracks the relative motion; ignoring the source drifts."""
    amp, fq = 0.15, 0.5                       # m, Hz: the source sways along x

    def source_accel(t):
        s = t * 1e-6
        return np.array([-amp * (2 * math.pi * fq) ** 2 * math.sin(2 * math.pi * fq * s), 0.0, 0.0])

    def src(t):
        return np.eye(3), source_accel(t) - G          # Phi = I, specific force in G

    t_us, K, f, w, m, rng = _imu(TRAJ, 20.0, 6)
    # the sensor's IMU sees its own global motion: relative motion plus the source's
    f_glob = f + np.einsum("nji,nj->ni", K.R, np.array([source_accel(int(t)) for t in t_us]))
    results = {}
    for name, source in (("with source", src), ("fixed", None)):
        global _imu_override
        of = OrientationFilter(_orientation_params())
        ff = FusionFilter(FusionParams.from_config(None, measurement_model=1, acc_noise=ACC_S, gyro_noise=GYR_S),
                          fixed_source=source is None)
        from coiltrack.firmware.pose.reference import crlb
        from coiltrack.firmware.model.field import orthogonal_source
        coils, cur = orthogonal_source(0.055, 50), np.full(3, 1.5)
        next_ref = 330_000
        ff.schedule_snapshot(next_ref)
        pending, err = [], []
        for i in range(t_us.size):
            t = int(t_us[i])
            phi, fr = source(t) if source else (np.eye(3), -G)
            ff.push_imu(t, *f_glob[i], *w[i], *fr, phi)
            while ff.pop_output() >= 0:
                ff.release_output()
            if t >= next_ref and not pending:
                k = TRAJ.kinematics(next_ref)
                C = crlb(k.position, k.R, coils, cur, 2.5e-8)
                d = rng.multivariate_normal(np.zeros(6), C)
                pending.append((next_ref, k.position - d[:3], k.R @ rotvec_to_matrix(-d[3:]), C, t + 170_000))
                next_ref += 600_000
            if pending and t >= pending[0][4]:
                ref, q, R, C, _ = pending.pop()
                ff.magnetic_update(ref, q, R, C)
                ff.schedule_snapshot(next_ref)
            if ff.initialized and t > 6e6:
                err.append(np.linalg.norm(ff.p - K.position[i]))
        results[name] = float(np.sqrt(np.mean(np.square(err))))
    assert results["with source"] < 0.03
    assert results["fixed"] > 2 * results["with source"]


# ------------------------------------------------------------------ smoothing
def test_rts_matches_filterpy_and_batch_least_squares():
    """Linear constant-velocity model: the RTS smoother (eqs 4.16-4.17) equals
    filterpy's rts_smoother and the batch weighted least-squares solution."""
    rng = np.random.default_rng(3)
    dt, N, q, r = 0.1, 40, 0.05, 0.2
    A = np.array([[1.0, dt], [0.0, 1.0]])
    Q = q * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
    H = np.array([[1.0, 0.0]])
    x0, P0 = np.zeros(2), np.diag([1.0, 1.0])
    truth = np.zeros((N, 2))
    xt = np.array([0.3, 1.0])
    zs = []
    for i in range(N):
        if i:
            xt = A @ xt + rng.multivariate_normal(np.zeros(2), Q)
        truth[i] = xt
        zs.append(xt[0] + rng.normal(0, math.sqrt(r)))
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = x0.copy(), P0.copy(), A, Q, H, np.array([[r]])
    xp, Pp, xm, Pm, As = [], [], [], [], []
    for i, z in enumerate(zs):
        if i:
            kf.predict()
        xm.append(kf.x.copy())
        Pm.append(kf.P.copy())
        kf.update(z)
        xp.append(kf.x.copy())
        Pp.append(kf.P.copy())
        As.append(A)
    xs, Ps = rts(np.array(xp), np.array(Pp), np.array(Pm), np.array(As))
    fx, fP, _, _ = rts_smoother(np.array(xp), np.array(Pp), [A] * N, [Q] * N)
    np.testing.assert_allclose(xs, fx, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(Ps, fP, rtol=1e-9, atol=1e-12)
    # batch least squares over the whole trajectory (prior, dynamics, measurements)
    n = 2 * N
    rows, rhs, wts = [], [], []
    def add(row, val, cov):
        Li = np.linalg.cholesky(np.linalg.inv(np.atleast_2d(cov)))
        rows.append(Li.T @ row)
        rhs.append(Li.T @ np.atleast_1d(val))
    J = np.zeros((2, n)); J[:, 0:2] = np.eye(2); add(J, x0, P0)
    for i in range(1, N):
        J = np.zeros((2, n)); J[:, 2 * i:2 * i + 2] = np.eye(2); J[:, 2 * i - 2:2 * i] = -A
        add(J, np.zeros(2), Q)
    for i, z in enumerate(zs):
        J = np.zeros((1, n)); J[0, 2 * i] = 1.0; add(J, np.array([z]), r)
    Jm = np.vstack(rows)
    b = np.concatenate(rhs)
    x_ls = np.linalg.lstsq(Jm, b, rcond=None)[0].reshape(N, 2)
    np.testing.assert_allclose(xs, x_ls, rtol=1e-8, atol=1e-10)


def test_error_state_smoother_improves_the_fusion_filter():
    rec = FusionRecorder()
    r = _fusion_run(3, 20.0, 9, recorder=rec)
    segs = smooth(rec)
    assert len(segs) == 1
    s = segs[0]
    K = TRAJ.kinematics(s["t"])
    fwd = np.sqrt(np.mean(np.sum((s["p_forward"] - K.position) ** 2, axis=1)))
    smo = np.sqrt(np.mean(np.sum((s["p"] - K.position) ** 2, axis=1)))
    assert smo < 0.7 * fwd
    assert r["filter"].updates > 25


# ------------------------------------------------------------------ bounded (resumable) update
class _Feed:
    """One fusion filter (model 3, with its ch. 2 filter) fed sample by sample
    from the synthetic IMU of ``_imu``; magnetic solutions are the truth at
    ``t_ref`` moved by a fixed error (deterministic)."""

    def __init__(self, imu_capacity=128, seed=2):
        self.t_us, self.K, self.f, self.w, self.m, _ = _imu(TRAJ, 4.0, seed)
        self.of = OrientationFilter(_orientation_params())
        self.ff = FusionFilter(FusionParams.from_config(None, measurement_model=3, acc_noise=ACC_S, gyro_noise=GYR_S,
                                            gyro_bias_sigma=0.02), self.of, imu_capacity=imu_capacity,
                               fixed_source=True)
        self.i = 0

    def push(self):
        i, of = self.i, self.of
        t = int(self.t_us[i])
        if not of.initialized:
            of.initialize(t, *self.f[i], *self.m[i])
        else:
            of.predict(t, *self.w[i])
            of.update_acc(*self.f[i])
            of.update_mag(*self.m[i])
        self.i += 1
        return t, self.ff.push_imu(t, *self.f[i], *self.w[i], 0.0, 0.0, 9.81, _EYE)

    def run_to(self, t_end):
        while int(self.t_us[self.i]) <= t_end:
            self.push()

    @staticmethod
    def solution(t_ref):
        k = TRAJ.kinematics(t_ref)
        C = np.diag([4e-6, 3e-6, 5e-6, 1e-4, 1.2e-4, 0.8e-4])
        C[0, 4] = C[4, 0] = 2e-6
        return t_ref, k.position + [0.002, -0.001, 0.0015], k.R @ rotvec_to_matrix([0.004, -0.006, 0.003]), C


_EYE = np.eye(3)


def _ready_pair(n=2, **kw):
    """``n`` identical filters, initialised by a first solution and with the
    second one (t_ref 930 ms) arrived: the IMU is 170 ms past t_ref."""
    feeds = [_Feed(**kw) for _ in range(n)]
    for fd in feeds:
        fd.ff.schedule_snapshot(330_000)
        fd.run_to(500_000)
        assert fd.ff.magnetic_update(*_Feed.solution(330_000)) == 512
        fd.ff.schedule_snapshot(930_000)
        fd.run_to(1_100_000)
    return feeds


def _assert_same_state(a, b, atol):
    for x, y in ((a.p, b.p), (a.v, b.v), (a.Th, b.Th), (a.ba, b.ba), (a.bg, b.bg), (a.P, b.P)):
        np.testing.assert_allclose(x, y, rtol=0, atol=atol)
    assert a.t_us == b.t_us


@pytest.mark.parametrize("budget", [1, 3, 50])
def test_update_split_over_steps_equals_the_uninterrupted_update(budget):
    """begin + step(budget) until done gives the state, covariance, pose
    history and snapshot of magnetic_update, to 1e-12; every call stays within
    max_replay_steps_per_step(budget); the replay covers the 170 ms since t_ref."""
    from coiltrack.firmware.estimate.magnetic_inertial import FUS_BUSY, max_replay_steps_per_step

    a, b = _ready_pair()
    sol = _Feed.solution(930_000)
    fa = a.ff.magnetic_update(*sol)
    fb = b.ff.begin_magnetic_update(*sol)
    assert fa == fb == 0 and b.ff.replaying
    assert b.ff.begin_magnetic_update(*sol) == FUS_BUSY
    calls, units = 0, 0
    while not b.ff.step(budget):
        calls += 1
        units += b.ff.last_step_units
        assert 1 <= b.ff.last_step_units <= max_replay_steps_per_step(budget)
    units += b.ff.last_step_units
    n_samples = sum(1 for t in a.t_us if 930_000 < t <= 1_100_000)
    assert units == n_samples and calls + 1 == -(-n_samples // budget)     # the last call swaps
    assert not b.ff.replaying
    _assert_same_state(a.ff.st, b.ff.st, 1e-12)
    np.testing.assert_allclose(b.ff.hist.d, a.ff.hist.d, rtol=0, atol=1e-12)
    assert np.array_equal(a.ff.hist.t, b.ff.hist.t) and len(a.ff.hist) == len(b.ff.hist)
    # the state really changed, by more than the tolerance
    c, = _ready_pair(1)
    assert np.abs(c.ff.p - a.ff.p).max() > 1e-4
    _check_history(b.ff, c.ff, 930_000)


def _check_history(ff, before, t_ref):
    """The pose history after a delayed update: one entry per instant in time
    order, unchanged up to t_ref, the corrected trajectory after it (ending at
    the live pose), as ``pose_at`` reads it."""
    h, h0 = ff.hist, before.hist
    ts = [int(h.t[h.slot(i)]) for i in range(len(h))]
    assert ts == sorted(set(ts)) and ts == [int(h0.t[h0.slot(i)]) for i in range(len(h0))]
    for i, t in enumerate(ts):
        row, row0 = h.d[h.slot(i)], h0.d[h0.slot(i)]
        if t <= t_ref:
            np.testing.assert_array_equal(row, row0)
        else:
            assert np.abs(row - row0).max() > 1e-5
    newest = h.d[h.peek(0)]
    np.testing.assert_array_equal(newest[0:3], ff.p)
    np.testing.assert_array_equal(newest[3:12], ff.Th.reshape(9))
    p, R = np.zeros(3), np.zeros((3, 3))
    assert ff.pose_at(ts[-1], p, R) and np.array_equal(p, ff.p)


def test_outputs_continue_during_the_replay_and_the_shadow_takes_over():
    """While the replay runs (2 steps per tick, one IMU sample per tick), every
    IMU sample still gives a fused pose at its own time, from the live state
    (the same as a filter without the update); a snapshot scheduled inside the
    replay window is taken from the corrected (shadow) state; once caught up,
    state, snapshot and poses are those of the uninterrupted update (1e-12).
    Nothing in the ticks allocates a numpy array."""
    from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

    a, b, c = _ready_pair(3)
    sol = _Feed.solution(930_000)
    a.ff.magnetic_update(*sol)
    counter = NumpyAllocationCounter() if available() else None
    if counter is not None:
        with counter:
            b.ff.begin_magnetic_update(*sol)
    else:
        b.ff.begin_magnetic_update(*sol)
    t_snap = 1_130_000
    for fd in (a, b, c):
        fd.ff.schedule_snapshot(t_snap)
        while fd.ff.pop_output() >= 0:
            fd.ff.release_output()
    during = after = 0
    while after < 20:
        replaying = b.ff.replaying
        outs = []
        for fd in (a, b, c):
            if fd is b and counter is not None:
                with counter:
                    t, produced = fd.push()
                    b.ff.step(2)
            else:
                t, produced = fd.push()
                if fd is b:
                    b.ff.step(2)
            assert produced
            k = fd.ff.pop_output()
            outs.append((int(fd.ff.out_t[k]), fd.ff.out_d[k].copy()))
            fd.ff.release_output()
            assert fd.ff.pop_output() == -1         # one pose per sample, not held back
        (ta, da), (tb, db), (tc, dc) = outs
        assert ta == tb == tc == t
        if replaying:
            during += 1
            np.testing.assert_array_equal(db, dc)   # the live state, untouched by the replay
        else:
            after += 1
            np.testing.assert_allclose(db, da, rtol=0, atol=1e-12)
    assert during >= 15
    assert np.abs(da - dc).max() > 1e-5            # the update shows in the poses after the swap
    _assert_same_state(a.ff.st, b.ff.st, 1e-12)
    _assert_same_state(a.ff.sn, b.ff.sn, 1e-12)
    assert a.ff.sn.t_us == t_snap and b.ff.snap.valid and b.ff.snap.initialized
    if counter is not None:
        assert counter.count == 0


def test_replay_that_loses_its_samples_is_dropped_and_live_goes_on():
    """A replay left without steps while the IMU ring (40 samples) wraps past
    t_ref cannot finish: FUS_REPLAY_LOST, the live state keeps its course;
    magnetic_update finishes a running replay before its own."""
    from coiltrack.firmware.estimate.magnetic_inertial import FUS_REPLAY_LOST

    b, c = _ready_pair(2, imu_capacity=40)
    b.ff.begin_magnetic_update(*_Feed.solution(930_000))
    for _ in range(40):
        b.push()
        c.push()
        assert not b.ff.step(0)
    assert b.ff.step(5) and not b.ff.replaying
    assert b.ff.last_flags & FUS_REPLAY_LOST and b.ff.replays_lost == 1
    _assert_same_state(b.ff.st, c.ff.st, 0.0)
    # a replay in progress is finished by the next synchronous update
    d, = _ready_pair(1)
    d.ff.begin_magnetic_update(*_Feed.solution(930_000))
    d.ff.schedule_snapshot(1_120_000)
    d.run_to(1_130_000)
    assert d.ff.replaying
    # (the snapshot at 1.12 s was taken by the running replay's shadow)
    assert d.ff.magnetic_update(*_Feed.solution(1_120_000)) == 0
    assert not d.ff.replaying and d.ff.updates == 2


def test_rejected_solution_starts_no_replay_and_keeps_the_snapshot():
    """A gated solution (a 3 m jump) offered with final=False changes
    nothing and needs no replay; the burst's other solution is then fused."""
    from coiltrack.firmware.estimate.ekf import EKF_GATED

    b, c = _ready_pair(2)
    t_ref, q, R, C = _Feed.solution(930_000)
    assert b.ff.begin_magnetic_update(t_ref, q + [3.0, 0.0, 0.0], R, C, final=False) & EKF_GATED
    assert not b.ff.replaying and b.ff.snap.valid and b.ff.rejected == 0
    _assert_same_state(b.ff.st, c.ff.st, 0.0)
    assert b.ff.begin_magnetic_update(t_ref, q, R, C) == 0 and b.ff.replaying
    b.ff.finish()
    assert b.ff.updates == 1 and np.abs(b.ff.p - c.ff.p).max() > 1e-4


def test_update_prepared_in_one_tick_and_applied_in_the_next_is_the_same_update():
    """prepare_magnetic_update, an IMU sample on the live state, then
    apply_magnetic_update and the replay give the state of begin (both halves
    at once) with the sample pushed after it, to 1e-12: the live state's
    progress between the halves does not leak into the shadow's update. A
    rejected first half (final=False) leaves the snapshot for a second
    solution, as begin does."""
    from coiltrack.firmware.estimate.magnetic_inertial import FUS_PREPARED

    a, b = _ready_pair()
    sol = _Feed.solution(930_000)
    assert a.ff.begin_magnetic_update(*sol) == 0
    a.push()
    assert b.ff.prepare_magnetic_update(*sol) == FUS_PREPARED and not b.ff.replaying
    b.push()
    assert b.ff.apply_magnetic_update() == 0 and b.ff.replaying
    a.ff.finish()
    b.ff.finish()
    _assert_same_state(a.ff.st, b.ff.st, 1e-12)
    np.testing.assert_allclose(b.ff.hist.d, a.ff.hist.d, rtol=0, atol=1e-12)
