"""The one strapdown propagation of both inertial filters, against references
written here from the equations (thesis ``002`` eqs 6.1-6.4, 6.8, 6.17;
Schepers & Veltink sec. 2.1):

* the nominal step of each filter equals the reference integration of the
  equations (a wrong sign of the gravity / source term, a dropped term, the
  wrong attitude for the specific force are caught);
* the error transition of each filter equals the finite-difference
  linearisation of that reference propagation, in the filter's own error
  convention (global-frame orientation error for the fusion filter,
  sensor-frame for the single-coil EKF), to the ``dt^2`` terms the first-order
  transition leaves out (a wrong sign, a transposed rotation, a block in the
  wrong place are caught: they are ``dt`` sized, the tolerance ``dt^2``);
* the whole inertial navigation over a second of constant-rate rotation and
  constant acceleration lands where the closed form says.
"""
import math

import numpy as np
import pytest

from coiltrack.firmware.estimate.layout import INS
from coiltrack.firmware.estimate.magnetic_inertial import FusionFilter, FusionParams
from coiltrack.firmware.estimate.single_coil import CORE, SchepersEKF

G = np.array([0.0, 0.0, -9.81])


def _exp(w):
    """Rodrigues, written here."""
    w = np.asarray(w, dtype=float)
    t = np.linalg.norm(w)
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if t < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(t) / t * K + (1.0 - math.cos(t)) / t ** 2 * K @ K


def _log(R):
    c = (np.trace(R) - 1.0) / 2.0
    a = math.acos(min(1.0, max(-1.0, c)))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return v if a < 1e-9 else v * a / math.sin(a)


ROT = _exp([0.7, -1.1, 0.4])              # a generic attitude (R - R^T is not small)


# ------------------------------------------------------------------ fusion filter (global-frame error)
def _fusion_ref(x, s0, s1, dt, ka, kg):
    """One step of eqs 6.1-6.4 / 6.8 / 6.13-6.14 with samples s = (f, w, f_src)
    at the step's ends: the rate at mid-step, the specific force in G with
    the attitude at each end, trapezoidal velocity, position exact for a linear
    acceleration."""
    p, v, Th, ba, bg = x
    f0, f1 = s0[0] - ba, s1[0] - ba
    w = 0.5 * (s0[1] + s1[1]) - bg
    Th1 = Th @ _exp(w * dt)
    a0 = Th @ f0 - s0[2]
    a1 = Th1 @ f1 - s1[2]
    v1 = v + dt * (a0 + a1) / 2
    p1 = p + dt * v + dt * dt * (a0 / 3 + a1 / 6)
    return p1, v1, Th1, ka * ba, kg * bg


def _fusion_filter(x, s0, s1, t0, dt_us):
    ff = FusionFilter(FusionParams.from_config(None, measurement_model=1, acc_bias_tau_s=2.0, gyro_bias_tau_s=3.0),
                      fixed_source=True)
    ff.push_imu(t0, *s0[0], *s0[1], *s0[2], np.eye(3))
    st = ff.st
    st.p[:], st.v[:], st.Th[:], st.ba[:], st.bg[:] = x
    st.t_us = t0
    ff.initialized = True
    ff.push_imu(t0 + dt_us, *s1[0], *s1[1], *s1[2], np.eye(3))
    return ff


def _samples():
    s0 = (np.array([1.2, -2.0, 9.6]), np.array([0.5, -0.3, 0.8]), np.array([0.3, -0.1, 9.81]))
    s1 = (np.array([1.0, -1.7, 9.9]), np.array([0.45, -0.2, 0.9]), np.array([0.2, 0.1, 9.7]))
    x = (np.array([0.1, -0.2, 0.3]), np.array([0.4, 0.1, -0.2]), ROT.copy(),
         np.array([0.02, -0.01, 0.03]), np.array([0.004, -0.003, 0.002]))
    return x, s0, s1


def test_fusion_nominal_step_is_the_strapdown_of_the_equations():
    x, s0, s1 = _samples()
    dt_us = 8333
    ff = _fusion_filter(x, s0, s1, 1_000_000, dt_us)
    ka, kg = math.exp(-dt_us * 1e-6 / 2.0), math.exp(-dt_us * 1e-6 / 3.0)
    ref = _fusion_ref(x, s0, s1, dt_us * 1e-6, ka, kg)
    for got, want in zip((ff.p, ff.v, ff.Th, ff.ba, ff.bg), ref):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)


def test_fusion_transition_is_the_linearised_strapdown():
    """A[INS, INS] = d(error after) / d(error before) of the reference step,
    with ``p_true = p + dp``, ``Theta_true = exp([do]x) Theta``, sensor errors
    subtracted from the samples; finite differences, central, h = 1e-6."""
    x, s0, s1 = _samples()
    dt_us = 500
    dt = dt_us * 1e-6
    ff = _fusion_filter(x, s0, s1, 1_000_000, dt_us)
    ka, kg = math.exp(-dt / 2.0), math.exp(-dt / 3.0)
    base = _fusion_ref(x, s0, s1, dt, ka, kg)

    def perturbed(e):
        p, v, Th, ba, bg = x
        return _fusion_ref((p + e[0:3], v + e[3:6], _exp(e[6:9]) @ Th, ba + e[9:12], bg + e[12:15]),
                           s0, s1, dt, ka, kg)

    def err(y):
        return np.concatenate([y[0] - base[0], y[1] - base[1], _log(y[2] @ base[2].T), y[3] - base[3],
                               y[4] - base[4]])

    h = 1e-6
    J = np.zeros((15, 15))
    for j in range(15):
        e = np.zeros(15)
        e[j] = h
        J[:, j] = (err(perturbed(e)) - err(perturbed(-e))) / (2 * h)
    A = ff.pred.A[INS, INS]
    # the first-order transition leaves out terms of order dt^2 |f|
    np.testing.assert_allclose(A, J, rtol=0, atol=2.0 * dt * dt * 12.0)
    # and the dt-sized blocks are really there (not all within the tolerance)
    assert np.abs(J - np.eye(15)).max() > 20 * 2.0 * dt * dt * 12.0


# ------------------------------------------------------------------ single-coil EKF (sensor-frame error)
def _schepers_ref(x, f, w, dt):
    """Schepers sec. 2.1 step: mid-interval attitude for the specific force,
    constant acceleration over the interval; offsets are random walks."""
    p, v, R, ba, bg = x
    fm, wm = f - ba, w - bg
    Rm = R @ _exp(wm * dt / 2)
    a = Rm @ fm + G
    return p + v * dt + a * dt * dt / 2, v + a * dt, Rm @ _exp(wm * dt / 2), ba, bg


def _schepers(x, acc, gyr, dt_us):
    ekf = SchepersEKF.from_config(None, gravity=G)
    ekf.initialize(x[0], x[2], np.eye(6) * 1e-6, 0, 0.1, 0.01, 0.01)
    ekf.v[:], ekf.ba[:], ekf.bg[:] = x[1], x[3], x[4]
    ekf.propagate(0, acc, gyr)
    ekf.propagate(dt_us, acc, gyr)
    return ekf


def test_schepers_nominal_step_is_the_strapdown_of_the_equations():
    x, s0, _ = _samples()
    ekf = _schepers(x, s0[0], s0[1], 10_000)
    ref = _schepers_ref(x, s0[0], s0[1], 0.01)
    for got, want in zip((ekf.p, ekf.v, ekf.R, ekf.ba, ekf.bg), ref):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)


def test_schepers_transition_is_the_linearised_strapdown():
    """F[CORE, CORE] = d(error after) / d(error before) with ``R_true = R
    exp([do]x)`` (sensor frame), including the dt^2/2 position terms."""
    x, s0, _ = _samples()
    dt = 5e-4
    ekf = _schepers(x, s0[0], s0[1], 500)
    base = _schepers_ref(x, s0[0], s0[1], dt)

    def perturbed(e):
        p, v, R, ba, bg = x
        return _schepers_ref((p + e[0:3], v + e[3:6], R @ _exp(e[6:9]), ba + e[9:12], bg + e[12:15]),
                             s0[0], s0[1], dt)

    def err(y):
        return np.concatenate([y[0] - base[0], y[1] - base[1], _log(base[2].T @ y[2]), y[3] - base[3],
                               y[4] - base[4]])

    h = 1e-6
    J = np.zeros((15, 15))
    for j in range(15):
        e = np.zeros(15)
        e[j] = h
        J[:, j] = (err(perturbed(e)) - err(perturbed(-e))) / (2 * h)
    F = ekf.F[CORE, CORE]
    np.testing.assert_allclose(F, J, rtol=0, atol=2.0 * dt * dt * 12.0)
    # the dt^2/2 position rows are in: POS-ORI matches to dt^3
    np.testing.assert_allclose(F[0:3, 6:9], J[0:3, 6:9], rtol=0, atol=dt ** 3 * 12.0 * 10)
    assert np.abs(J[0:3, 6:9]).max() > 20 * dt ** 3 * 12.0 * 10


# ------------------------------------------------------------------ a second of navigation
@pytest.mark.parametrize("which", ["fusion", "schepers"])
def test_navigation_over_a_second_matches_the_closed_form(which):
    """Constant body rate, constant global acceleration: ``p = p0 + v0 t +
    a t^2 / 2``, ``R = R0 exp([w t]x)``, samples ``f = R^T (a - g)``. The
    fusion filter's trapezoid is exact here; the single-coil EKF's mean of
    two samples at the mid attitude is second order in ``w dt``."""
    a = np.array([0.3, -0.2, 0.5])
    w = np.array([0.4, -0.25, 0.6])
    v0 = np.array([0.1, 0.05, -0.02])
    rate = 100
    n = rate
    ts = np.arange(n + 1) * (1_000_000 // rate)
    Rs = [ROT @ _exp(w * t * 1e-6) for t in ts]
    fs = [R.T @ (a - G) for R in Rs]
    T = ts[-1] * 1e-6
    if which == "fusion":
        ff = FusionFilter(FusionParams.from_config(None, measurement_model=1, acc_bias_tau_s=0.0,
                                                   gyro_bias_tau_s=0.0), fixed_source=True)
        ff.push_imu(int(ts[0]), *fs[0], *w, *(-G), np.eye(3))
        ff.st.Th[:] = ROT
        ff.st.v[:] = v0
        ff.st.t_us = int(ts[0])
        ff.initialized = True
        for t, f in zip(ts[1:], fs[1:]):
            ff.push_imu(int(t), *f, *w, *(-G), np.eye(3))
        p, v, R, tol = ff.p, ff.v, ff.Th, 1e-9
    else:
        ekf = SchepersEKF.from_config(None, gravity=G)
        ekf.initialize(np.zeros(3), ROT, np.eye(6) * 1e-6, 0, 0.1, 0.01, 0.01)
        ekf.v[:] = v0
        for t, f in zip(ts, fs):
            ekf.propagate(int(t), f, w)
        p, v, R, tol = ekf.p, ekf.v, ekf.R, 2e-4
    np.testing.assert_allclose(p, v0 * T + a * T * T / 2, rtol=0, atol=tol)
    np.testing.assert_allclose(v, v0 + a * T, rtol=0, atol=tol * 4)
    np.testing.assert_allclose(R, Rs[-1], rtol=0, atol=1e-9)


def test_fusion_process_noise_is_written_for_each_step():
    """``Q`` of the live state after steps of 8333 us and then 8334 us (what an IMU's timestamps
    alternate between): the diagonal of velocity ``(s_a^2 + s_as^2) dt^2``, orientation
    ``(s_g dt)^2``, offsets ``rw^2 dt``, the white magnetic states ``qm_sigma^2`` and
    ``psi_sigma^2``, every other element zero, each written for the step just taken. Catches a
    diagonal index off by one (an element beside the diagonal), the white states left at zero
    and a step's noise kept from the step before."""
    from coiltrack.firmware.estimate.layout import ACC, GYR, ORI, PSI, QM, VEL

    x, s0, s1 = _samples()
    ff = _fusion_filter(x, s0, s1, 1_000_000, 8333)
    prm = ff.prm
    for dt_us in (8333, 8334):
        if dt_us == 8334:
            ff.push_imu(1_000_000 + 8333 + 8334, *s0[0], *s0[1], *s0[2], np.eye(3))
        dt = dt_us * 1e-6
        want = np.zeros((ff.n, ff.n))
        for blk, q in ((VEL, (prm.acc_noise ** 2 + prm.source_acc_noise ** 2) * dt * dt),
                       (ORI, (prm.gyro_noise * dt) ** 2), (ACC, prm.acc_bias_rw ** 2 * dt),
                       (GYR, prm.gyro_bias_rw ** 2 * dt), (QM, prm.qm_sigma ** 2), (PSI, prm.psi_sigma ** 2)):
            for i in range(blk.start, blk.stop):
                want[i, i] = q
        np.testing.assert_allclose(ff.st.pred.Q, want, rtol=1e-12, atol=0)
        assert ff.st.dt_last == dt
