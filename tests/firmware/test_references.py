"""The estimators against references that do not take the firmware's own
matrices: exact rational arithmetic for the Joseph-form update, a textbook
linear-Gaussian update for the fusion filter's magnetic update, finite
differences of the nonlinear models written here from the thesis
(``002_cd7f1fdb7fc67471.txt`` ch. 2 and ch. 6) for ``F`` and ``H``, and batch
weighted least squares for a static sensor.

Only public entry points are used (``KalmanUpdate``, ``FusionFilter``,
``OrientationFilter``, their nominal state ``p, v, Th, ba, bg, R, bias,
dist, h_g, P`` and the state-layout slices); the transition and measurement
matrices the filters used last are read through :func:`_transition` and
:func:`_measurement_matrices`, the one place that knows where they live.
"""
from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware.estimate.ekf import EKF_OK, KalmanUpdate
from coiltrack.firmware.estimate.layout import ACC, BIAS, DIST, GYR, ORI, POS, PSI, QM, THETA, VEL
from coiltrack.firmware.estimate.magnetic_inertial import FUS_INITIALISED, FusionFilter, FusionParams
from coiltrack.firmware.estimate.orientation import OrientationFilter, OrientationParams

G_SRC = np.array([0.0, 0.0, 9.81])      # specific force of a fixed level source, global frame
CORE = slice(POS.start, GYR.stop)       # position, velocity, orientation, accelerometer, gyroscope errors


def rot(v) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(v, dtype=float)).as_matrix()


def log(R) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


def _transition(filt) -> np.ndarray:
    """The state transition matrix of the filter's last covariance prediction."""
    return filt.pred.A.copy()


def _measurement_matrices(filt) -> list[np.ndarray]:
    """The measurement matrices of the filter's last updates."""
    if isinstance(filt, OrientationFilter):
        return [filt.upd_acc.H.copy(), filt.upd_mag.H.copy()]
    return [filt.upd.H.copy()]


def _jacobian(fun, n: int, h: float = 1e-6) -> np.ndarray:
    """Central differences of ``fun(delta)`` (a vector) at ``delta = 0``."""
    cols = []
    for j in range(n):
        d = np.zeros(n)
        d[j] = h
        cols.append((fun(d) - fun(-d)) / (2 * h))
    return np.array(cols).T


# ------------------------------------------------------------------ Joseph form
def _exact_posterior(P, H, R) -> np.ndarray:
    """``P - P H^T (H P H^T + R)^-1 H P`` in exact rational arithmetic of the float inputs."""
    F = lambda A: [[Fraction(float(x)) for x in row] for row in np.atleast_2d(A)]  # noqa: E731
    Pf, Hf, Rf = F(P), F(H), F(R)
    n, m = len(Pf), len(Hf)
    PHt = [[sum(Pf[i][k] * Hf[j][k] for k in range(n)) for j in range(m)] for i in range(n)]
    S = [[sum(Hf[i][k] * PHt[k][j] for k in range(n)) + Rf[i][j] for j in range(m)] for i in range(m)]
    aug = [S[i] + [Fraction(int(i == j)) for j in range(m)] for i in range(m)]
    for c in range(m):                       # Gauss-Jordan (S is positive definite: no pivoting)
        aug[c] = [x / aug[c][c] for x in aug[c]]
        for r in range(m):
            if r != c:
                f = aug[r][c]
                aug[r] = [a - f * b for a, b in zip(aug[r], aug[c])]
    Si = [row[m:] for row in aug]
    K = [[sum(PHt[i][k] * Si[k][j] for k in range(m)) for j in range(m)] for i in range(n)]
    return np.array([[float(Pf[i][j] - sum(K[i][k] * PHt[j][k] for k in range(m))) for j in range(n)]
                     for i in range(n)])


@pytest.mark.parametrize("n,m", [(9, 3), (12, 6), (5, 1), (8, 2)])
def test_joseph_form_keeps_the_posterior_of_a_precise_measurement(n, m):
    """With the optimal gain the Joseph form and ``P = (I - K H) P`` agree
    except numerically. The observable difference: a measurement of states
    far more precise than their prior (``R = 1e-16 P``, below the float64
    resolution of ``S = H P H^T + R``). ``(I - K H) P`` then computes the
    measured states' posterior variance as ``(1 - K) P`` with ``K`` rounded to
    1 and loses it (relative error 0.13-1.45 here); the Joseph form
    carries it in ``K R K^T`` and keeps it to rounding. Reference: the exact
    rational-arithmetic posterior of the same float64 inputs. Tolerance:
    relative 1e-9 on the measured states' variances (measured: at most
    1.3e-15 with the Joseph form), 1e-12 absolute on the whole ``P`` (entries ~1)."""
    rng = np.random.default_rng(n * 10 + m)
    A = rng.normal(size=(n, n))
    P = A @ A.T / n + 0.1 * np.eye(n)
    u = KalmanUpdate(n, m, 1.0)
    idx = rng.choice(n, m, replace=False)
    u.H[np.arange(m), idx] = 1.0
    u.R[:] = np.diag(rng.uniform(1.0, 2.0, m)) * 1e-16
    u.y[:] = rng.normal(size=m) * 1e-8
    exact = _exact_posterior(P, u.H, u.R)
    post = P.copy()
    assert u.update(post) == EKF_OK
    np.testing.assert_allclose(np.diag(post)[idx], np.diag(exact)[idx], rtol=1e-9)
    np.testing.assert_allclose(post, exact, rtol=0, atol=1e-12)


# ------------------------------------------------------------------ fusion filter, fixed level source
T_US = 8333                     # 120 Hz IMU
T0_US = 1000


def _fusion(**kw) -> FusionFilter:
    prm = dict(measurement_model=1, acc_noise=0.0155, gyro_noise=0.0067)
    prm.update(kw)
    ff = FusionFilter(FusionParams.from_config(None, **prm), fixed_source=True)
    return ff


def _push(ff, k0: int, k1: int, f, w, dt_us: int = T_US) -> None:
    """IMU samples ``k0..k1`` (inclusive), constant specific force and rate (sensor frame)."""
    for k in range(k0, k1 + 1):
        ff.push_imu(T0_US + k * dt_us, *f, *w, *G_SRC, np.eye(3))
        while ff.pop_output() >= 0:
            ff.release_output()


def _solution_cov(rng, pos_sigma, ori_sigma) -> np.ndarray:
    """A 6x6 covariance like the solver's, ``(p, dtheta)`` with correlated blocks."""
    A = rng.normal(size=(6, 6)) * 0.4 + np.eye(6)
    C = A @ A.T
    s = np.r_[np.full(3, pos_sigma), np.full(3, ori_sigma)]
    d = np.sqrt(np.diag(C))
    return C / np.outer(d, d) * np.outer(s, s)


def _initialised(ff, p, R_true, C, rng, k_ref=10, dt_us: int = T_US):
    """Filter initialised from one magnetic solution at IMU sample ``k_ref``; the
    sensor is at rest at ``(p, R_true)``."""
    f = R_true.T @ G_SRC
    t_ref = T0_US + k_ref * dt_us
    ff.schedule_snapshot(t_ref)
    _push(ff, 0, k_ref, f, np.zeros(3), dt_us)
    d = rng.multivariate_normal(np.zeros(6), C)
    assert ff.magnetic_update(t_ref, p + d[:3], R_true @ rot(d[3:]), C) == FUS_INITIALISED
    return f, k_ref


def _prior_at(ff, k_prev, k_ref, f, w=np.zeros(3)):
    """Run the IMU to sample ``k_ref`` with a snapshot there; the state then is
    the prior of an update at ``t_ref`` (nothing to replay after it)."""
    t_ref = T0_US + k_ref * T_US
    ff.schedule_snapshot(t_ref)
    _push(ff, k_prev + 1, k_ref, f, w)
    prior = dict(p=ff.p.copy(), v=ff.v.copy(), Th=ff.Th.copy(), ba=ff.ba.copy(), bg=ff.bg.copy(),
                 P=ff.P.copy())
    return t_ref, prior


def _magnetic_h(prior, delta) -> np.ndarray:
    """Measurement function of eq 6.18 (fixed source, ``Phi = I``) at the prior
    perturbed by a core error ``delta``: the magnetic position and orientation
    a perfect solver would return, ``[p ; log(Theta Theta_prior^T)]``."""
    p = prior["p"] + delta[POS]
    Th = rot(delta[ORI]) @ prior["Th"]
    return np.r_[p, log(Th @ prior["Th"].T)]


def _textbook_update(prior, q, R_ms, C, meas_sigma):
    """Linear-Gaussian update of the core error state with the magnetic solution
    as the measurement: ``H`` by finite differences of eq 6.18, noise the
    solver's covariance turned into the global frame (orientation error
    ``Psi dtheta``, ``R_true = R exp([dtheta]x)``) plus ``meas_sigma^2 I``."""
    n = CORE.stop
    H = _jacobian(lambda d: _magnetic_h(prior, d) - _magnetic_h(prior, np.zeros(n)), n)
    T = np.zeros((6, 6))
    T[:3, :3] = np.eye(3)
    T[3:, 3:] = R_ms                              # Psi = Phi R_ms, Phi = I
    N = T @ C @ T.T + meas_sigma ** 2 * np.eye(6)
    y = np.r_[q - prior["p"], log(R_ms @ prior["Th"].T)]
    P0 = prior["P"][CORE, CORE]
    S = H @ P0 @ H.T + N
    K = P0 @ H.T @ np.linalg.inv(S)
    dx = K @ y
    post = dict(p=prior["p"] + dx[POS], v=prior["v"] + dx[VEL], Th=rot(dx[ORI]) @ prior["Th"],
                ba=prior["ba"] + dx[ACC], bg=prior["bg"] + dx[GYR], P=P0 - K @ S @ K.T)
    return post, H


def test_fusion_magnetic_update_matches_a_textbook_update():
    """Posterior of one magnetic update (model 1, eq 6.18) against the
    linear-Gaussian update computed here from the prior, the solution and its
    covariance as documented (not from the filter's ``H``, ``R`` or white
    blocks). Catches a wrong scale of the solution covariance (the white
    blocks), a wrong frame of its orientation block, a sign of ``C``.
    Tolerances: covariance relative 1e-7; position 1e-9 m; orientation 1e-9 rad."""
    rng = np.random.default_rng(21)
    ff = _fusion()
    p_true, R_true = np.array([0.21, -0.08, 0.12]), rot([0.4, -0.7, 1.1])
    C = _solution_cov(rng, 3e-3, 0.012)
    f, k = _initialised(ff, p_true, R_true, C, rng)
    t_ref, prior = _prior_at(ff, k, k + 72, f)
    C2 = _solution_cov(rng, 2e-3, 0.008)
    d = rng.multivariate_normal(np.zeros(6), C2)
    q, R_ms = p_true + d[:3], R_true @ rot(d[3:])
    ref, H = _textbook_update(prior, q, R_ms, C2, ff.prm.meas_sigma)
    assert ff.magnetic_update(t_ref, q, R_ms, C2) == EKF_OK
    np.testing.assert_allclose(ff.P[CORE, CORE], ref["P"], rtol=1e-7, atol=1e-18)
    np.testing.assert_allclose(ff.p, ref["p"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(log(ff.Th @ ref["Th"].T), 0.0, atol=1e-9)
    np.testing.assert_allclose(ff.v, ref["v"], rtol=0, atol=1e-8)
    # the update moved the state by a sizeable part of the innovation (the test has power)
    assert np.linalg.norm(ff.p - prior["p"]) > 0.2 * np.linalg.norm(q - prior["p"])
    # eq 6.18: C = [I 0 0 0 0 I 0; 0 0 I 0 0 0 I] on (core, white magnetic states)
    Hf = _measurement_matrices(ff)[0]
    np.testing.assert_allclose(Hf[:, CORE], H, atol=1e-8)
    np.testing.assert_array_equal(Hf[:, QM], np.r_[np.eye(3), np.zeros((3, 3))])
    np.testing.assert_array_equal(Hf[:, PSI], np.r_[np.zeros((3, 3)), np.eye(3)])


def _strapdown(x, f, w, T, tau_a, tau_g):
    """One IMU step of eqs 6.1-6.4 (fixed level source): biases removed,
    ``Theta' = Theta exp([w T]x)``, the net acceleration ``Theta f - g``
    linear over the step (specific force at both ends), integrated exactly
    for velocity and position; offsets decay with their time constants."""
    p, v, Th, ba, bg = x
    fs, ws = f - ba, w - bg
    Th1 = Th @ rot(ws * T)
    a0, a1 = Th @ fs - G_SRC, Th1 @ fs - G_SRC
    return (p + T * v + T * T * (a0 / 3 + a1 / 6), v + T * (a0 + a1) / 2, Th1,
            np.exp(-T / tau_a) * ba, np.exp(-T / tau_g) * bg)


def _plus(x, d):
    """``true = estimate (+) error`` (module convention: global-frame orientation error)."""
    p, v, Th, ba, bg = x
    return p + d[POS], v + d[VEL], rot(d[ORI]) @ Th, ba + d[ACC], bg + d[GYR]


def _minus(xt, xe):
    return np.r_[xt[0] - xe[0], xt[1] - xe[1], log(xt[2] @ xe[2].T), xt[3] - xe[3], xt[4] - xe[4]]


def test_fusion_transition_matches_finite_differences_of_the_strapdown():
    """``A`` of one IMU step (eq 6.17) against the Jacobian of the error
    propagated through the nonlinear strapdown written here (eqs 6.1-6.4),
    at a turning, accelerating sensor with offsets estimated; the white
    magnetic states have no dynamics (eqs 6.15-6.16). Tolerance ``T^2 g``
    (1e-5 at 1 kHz): eq 6.17 is first order in ``T`` (it drops
    ``p_e' += T^2/2 (...)``); the blocks it keeps are of order ``T`` (1e-3)
    and ``T g`` (1e-2). The nominal step itself agrees to 1e-12."""
    rng = np.random.default_rng(5)
    dt_us = 1000
    ff = _fusion(acc_bias_tau_s=0.7, gyro_bias_tau_s=0.9)
    f, k = _initialised(ff, np.array([0.2, 0.1, -0.1]), rot([0.3, 0.2, -0.5]),
                        _solution_cov(rng, 3e-3, 0.01), rng, dt_us=dt_us)
    ff.ba[:] = [0.02, -0.03, 0.01]
    ff.bg[:] = [0.004, 0.002, -0.003]
    ff.v[:] = [0.1, -0.05, 0.02]
    f = f + np.array([0.6, -0.4, 0.3])                 # accelerating
    w = np.array([0.5, -0.3, 0.8])                     # and turning
    _push(ff, k + 1, k + 1, f, w, dt_us)               # a sample with this input before the step
    x0 = (ff.p.copy(), ff.v.copy(), ff.Th.copy(), ff.ba.copy(), ff.bg.copy())
    _push(ff, k + 2, k + 2, f, w, dt_us)
    A = _transition(ff)
    T, tau = dt_us * 1e-6, (ff.prm.acc_bias_tau_s, ff.prm.gyro_bias_tau_s)
    x1 = _strapdown(x0, f, w, T, *tau)
    np.testing.assert_allclose(ff.p, x1[0], atol=1e-12)
    np.testing.assert_allclose(ff.v, x1[1], atol=1e-12)
    np.testing.assert_allclose(ff.Th, x1[2], atol=1e-12)
    F = _jacobian(lambda d: _minus(_strapdown(_plus(x0, d), f, w, T, *tau), x1), CORE.stop)
    full = np.zeros_like(A)
    full[CORE, CORE] = F
    np.testing.assert_allclose(A, full, rtol=0, atol=T * T * 9.81)
    # the blocks that carry the physics are really there (the test has power)
    assert np.abs(F[VEL, ORI]).max() > 5 * T


def test_fusion_static_sensor_equals_batch_least_squares():
    """A sensor at rest with a perfect IMU, offsets known, the orientation
    known to 1e-7 rad and no velocity uncertainty: the fused position after
    eight magnetic solutions is the weighted least-squares combination of
    them, ``(sum W_k)^-1 sum W_k q_k`` with ``W_0 = C_0^-1`` (initialisation)
    and ``W_k = (C_k + meas_sigma^2 I)^-1``, and its covariance is
    ``(sum W_k)^-1``. Tolerance: 1e-3 of the smallest standard deviation
    (the 1e-7 rad orientation uncertainty leaks ~1e-7 g t^2 into position)."""
    rng = np.random.default_rng(8)
    tiny = 1e-9
    ff = _fusion(acc_noise=0.0, gyro_noise=0.0, acc_bias_sigma=tiny, gyro_bias_sigma=tiny, acc_bias_rw=0.0,
                 gyro_bias_rw=0.0, velocity0_sigma=tiny)
    p_true, R_true = np.array([0.18, 0.05, -0.11]), rot([0.2, -0.1, 0.3])
    covs, qs = [], []

    def solution():
        C = _solution_cov(rng, rng.uniform(1e-3, 4e-3), 1e-7)
        C[:3, 3:] = C[3:, :3] = 0.0
        q = p_true + rng.multivariate_normal(np.zeros(3), C[:3, :3])
        covs.append(C[:3, :3])
        qs.append(q)
        return q, R_true, C

    t_ref = T0_US + 10 * T_US
    ff.schedule_snapshot(t_ref)
    f = R_true.T @ G_SRC
    _push(ff, 0, 10, f, np.zeros(3))
    assert ff.magnetic_update(t_ref, *solution()) == FUS_INITIALISED
    k = 10
    for _ in range(7):
        t_ref, _ = _prior_at(ff, k, k + 72, f)
        k += 72
        assert ff.magnetic_update(t_ref, *solution()) == EKF_OK
    r2 = ff.prm.meas_sigma ** 2
    W = [np.linalg.inv(covs[0])] + [np.linalg.inv(C + r2 * np.eye(3)) for C in covs[1:]]
    cov = np.linalg.inv(sum(W))
    p_ls = cov @ sum(Wk @ q for Wk, q in zip(W, qs))
    tol = 1e-3 * np.sqrt(np.linalg.eigvalsh(cov).min())
    np.testing.assert_allclose(ff.p, p_ls, rtol=0, atol=tol)
    np.testing.assert_allclose(ff.P[POS, POS], cov, rtol=0, atol=1e-3 * np.linalg.eigvalsh(cov).min())
    assert np.linalg.norm(p_ls - qs[-1]) > 10 * tol            # the combination is not the last solution


# ------------------------------------------------------------------ orientation filter (ch. 2)
def _ori_plus(R, b, dist, d):
    """``R_true = R exp([theta]x)`` (sensor-frame error), offsets and disturbance additive."""
    return R @ rot(d[THETA]), b + d[BIAS], dist + d[DIST]


def test_orientation_filter_F_and_H_match_finite_differences():
    """Eq 2.28 (and its offset / disturbance rows) over three gyroscope
    steps, and the inclination and compass measurement matrices (eqs 2.31-2.33),
    against finite differences of the nonlinear models written here:
    strapdown ``R <- R exp([(w - b) T]x)``, disturbance ``d <- c_d d``,
    inclination ``R^T e_z`` and compass ``R^T h_G + d``. Tolerances: ``F``
    1e-5 (the trapezoidal offset term is exact to ``T_N^3 |w|^2``, T_N = 25 ms),
    ``H`` 1e-7 (exact Jacobians)."""
    prm = OrientationParams.from_config(None, mag_learn_samples=1, dist_corr=0.97)
    of = OrientationFilter(prm)
    R0 = rot([0.3, -0.4, 0.9])
    h_true = np.array([20e-6, 0.0, -45e-6])
    acc = R0.T @ G_SRC
    assert of.initialize(0, *acc, *(R0.T @ h_true))
    for _ in range(2):                                   # learn |m| and the dip (eqs 2.8-2.10)
        of.update_mag(*(R0.T @ h_true))
    of.set_bias(0.01, -0.02, 0.015)
    of.dist[:] = [0.01, -0.02, 0.005]
    w = np.array([0.4, -0.3, 0.5])
    T = 1 / 120
    x0 = (of.R.copy(), of.bias.copy(), of.dist.copy())
    for k in range(1, 4):
        of.predict(int(round(k * T * 1e6)), *w)
    of.propagate()
    A = _transition(of)
    TN = 3 * int(round(T * 1e6)) * 1e-6
    Ts = TN / 3

    def prop(x):
        R, b, dist = x
        for _ in range(3):
            R = R @ rot((w - b) * Ts)
            dist = prm.dist_corr * dist
        return R, b, dist

    x1 = prop(x0)
    F = _jacobian(lambda d: np.r_[log(x1[0].T @ prop(_ori_plus(*x0, d))[0]),
                                  prop(_ori_plus(*x0, d))[1] - x1[1], prop(_ori_plus(*x0, d))[2] - x1[2]], 9)
    np.testing.assert_allclose(A, F, rtol=0, atol=1e-5)
    assert np.abs(F[THETA, BIAS]).max() > 0.5 * TN          # the offset term is there
    # measurements at the propagated estimate
    R, b, dist = of.R.copy(), of.bias.copy(), of.dist.copy()
    of.update_acc(*(R.T @ G_SRC))
    of.update_mag(*((R.T @ of.h_g + dist) * of.m_ref))
    H_acc, H_mag = _measurement_matrices(of)
    e_z, h_g = np.array([0.0, 0.0, 1.0]), of.h_g.copy()
    J_acc = _jacobian(lambda d: _ori_plus(R, b, dist, d)[0].T @ e_z, 9)
    J_mag = _jacobian(lambda d: _ori_plus(R, b, dist, d)[0].T @ h_g + _ori_plus(R, b, dist, d)[2], 9)
    np.testing.assert_allclose(H_acc, J_acc, rtol=0, atol=1e-7)
    np.testing.assert_allclose(H_mag, J_mag, rtol=0, atol=1e-7)
