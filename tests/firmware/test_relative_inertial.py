"""The relative inertial EKF of the tightly coupled tracker (``estimate.relative_inertial``).

References are independent of the firmware: closed-form rigid-body kinematics
(a source that accelerates and turns, a sensor that moves and turns; exact
IMU samples computed here), finite differences of the nominal step, and the
bench's field model (``hil.physics``: elliptic-integral loops) for the
pulse measurements of the consistency test.
"""
import math

import numpy as np
import pytest
from scipy.stats import chi2

from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.estimate.layout import ACC, GYR, ORI, POS, VEL
from coiltrack.firmware.estimate.relative_inertial import SACC, SGYR, RelativeInertialEKF
from coiltrack.firmware.model.field import Coil
from coiltrack.hil import physics

G = np.array([0.0, 0.0, -9.81])
D = np.array([0.0, 0.0, -0.06])          # the source IMU on the source (source frame)
W_SRC = np.array([0.15, -0.25, 0.5])     # source body rate, rad/s (constant)
W_SEN = np.array([-0.3, 0.4, 0.2])       # sensor body rate, rad/s (constant)


def _rot(v):
    return physics.rotvec_to_matrix(np.asarray(v, dtype=float))


def _truth(t):
    """Closed-form world motion (position, velocity, acceleration; orientation) of the
    source and the sensor; constant body rates, so the orientations are exponentials."""
    om = 2 * math.pi * 0.9
    a_src = np.array([0.06, 0.03, 0.02])
    ps = a_src * np.sin(om * t)
    vs = a_src * om * np.cos(om * t)
    acs = -a_src * om * om * np.sin(om * t)
    om2 = 2 * math.pi * 0.6
    c = np.array([0.25, 0.15, 0.3])
    b = np.array([0.05, -0.04, 0.03])
    pn = c + b * np.sin(om2 * t + 0.3)
    vn = b * om2 * np.cos(om2 * t + 0.3)
    acn = -b * om2 * om2 * np.sin(om2 * t + 0.3)
    Phi = _rot([0.1, -0.05, 0.2]) @ _rot(W_SRC * t)
    Th = _rot([0.3, 0.2, -0.4]) @ _rot(W_SEN * t)
    return ps, vs, acs, Phi, pn, vn, acn, Th


def _imu(t):
    """Exact samples: sensor f, w (sensor frame); source module f, w (source frame)."""
    ps, vs, acs, Phi, pn, vn, acn, Th = _truth(t)
    f_sen = Th.T @ (acn - G)
    a_mod = acs + Phi @ np.cross(W_SRC, np.cross(W_SRC, D))      # constant rate: no angular acceleration
    f_src = Phi.T @ (a_mod - G)
    return f_sen, W_SEN.copy(), f_src, W_SRC.copy()


def _relative(t):
    ps, vs, acs, Phi, pn, vn, acn, Th = _truth(t)
    q = Phi.T @ (pn - ps)
    v_mod = vs + Phi @ np.cross(W_SRC, D)
    v = Phi.T @ (vn - v_mod)
    return q, v, Phi.T @ Th


def _filter(**kw):
    args = dict(n_clones=3, gravity=G, acc_noise=2e-3, gyr_noise=8.7e-4, acc_bias_rw=0.0, gyr_bias_rw=0.0,
                pos_noise=0.0, gate_probability=0.999, iterations=1, src_position=D, src_acc_noise=2e-3,
                src_gyr_noise=8.7e-4, src_acc_bias_sigma=0.02, src_gyr_bias_sigma=8.7e-3, extra_acc_noise=0.0)
    args.update(kw)
    return RelativeInertialEKF(**args)


def _dead_reckon(drop_source=False, duration_s=2.0, rate=120.0):
    ekf = _filter()
    q, v, R = _relative(0.0)
    ekf.p[:] = q
    ekf.v[:] = v
    ekf.R[:] = R
    n = int(duration_s * rate)
    for k in range(n + 1):
        t = k / rate
        f, w, fs, ws = _imu(t)
        if drop_source:
            fs = -_truth(t)[3].T @ G                # the source taken as unaccelerated (no a_source)
        ekf.propagate_relative(int(round(t * 1e6)), f, w, fs, ws)
    q, v, R = _relative(n / rate)
    dR = R.T @ ekf.R
    ang = math.acos(max(-1.0, min(1.0, (np.trace(dR) - 1) / 2)))
    return float(np.linalg.norm(ekf.p - q)), float(np.linalg.norm(ekf.v - v)), ang


def test_dead_reckoning_follows_the_closed_form_relative_motion():
    """2 s of exact samples of a source accelerating at 1.9 m/s^2 and turning at 0.6 rad/s,
    its IMU 6 cm from the coil centre, and a sensor moving and turning: the relative pose
    follows the closed form to 1 mm and 0.01 deg (the interval's linear-in-time input
    leaves a few 1e-4 m of the 0.06 m x (5.7 rad/s)^2 sinusoid). Catches a wrong sign or a
    dropped transport term (w_s x r, w_s x v), the module position, the frame change or the
    left rotation of R."""
    dp, dv, ang = _dead_reckon()
    assert dp < 1e-3, dp
    assert dv < 2e-3, dv
    assert math.degrees(ang) < 0.01, math.degrees(ang)


def test_dead_reckoning_without_the_source_acceleration_is_wrong():
    """Eq 6.8: the same run with ``f_source`` replaced by gravity alone (the source's own
    acceleration dropped) ends more than 50 mm off, fifty times the bound above, so the
    closed-form test fails if the source term is dropped from the propagation."""
    dp, dv, ang = _dead_reckon(drop_source=True)
    assert dp > 0.05, dp


def test_error_transition_matches_finite_differences():
    """Each column of the step's error transition ``F`` (POS, VEL, ORI, ACC, GYR, SACC,
    SGYR) against the nominal step of a perturbed state, central differences: rows POS,
    VEL, ORI agree to 2e-3 of the column's norm plus ``dt^2 |f|`` (the second-order terms
    the first-order transition leaves out; 6e-4 here, a tenth of the smallest source block).
    Catches a wrong sign or frame in a source block (-[r]x, -[v]x, R^T) or a
    missing frame change on the POS and VEL rows."""
    dt = 1 / 120

    def make():
        e = _filter()
        e.p[:] = (0.2, -0.1, 0.35)
        e.v[:] = (0.4, -0.3, 0.2)
        e.R[:] = _rot([0.4, -0.3, 0.8])
        e.f[:] = (1.0, -2.0, 9.0)
        e.w[:] = (0.5, -0.7, 0.3)
        e.fs[:] = (0.5, 0.8, 9.6)
        e.ws[:] = (-0.6, 0.4, 0.9)
        e.initialized = True
        e.P[:] = np.eye(e.nx) * 1e-6
        return e

    base = make()
    base._step(dt)
    F = base.F.copy()
    cols = [(s, i) for s in (POS, VEL, ORI, ACC, GYR, SACC, SGYR) for i in range(3)]
    eps = 1e-6
    for s, i in cols:
        outs = []
        for sign in (1.0, -1.0):
            e = make()
            e.initialized = False
            d = sign * eps
            if s == POS:
                e.p[i] += d
            elif s == VEL:
                e.v[i] += d
            elif s == ORI:
                u = np.zeros(3)
                u[i] = d
                e.R[:] = e.R @ _rot(u)
            elif s == ACC:
                e.f[i] -= d                  # true offset = estimate + error: f = y - b
            elif s == GYR:
                e.w[i] -= d
            elif s == SACC:
                e.fs[i] -= d
            else:
                e.ws[i] -= d
            e._step(dt)
            rv = physics.matrix_to_rotvec(base.R.T @ e.R)
            outs.append(np.concatenate([e.p - base.p, e.v - base.v, rv]))
        fd = (outs[0] - outs[1]) / (2 * eps)
        col = s.start + i
        an = np.concatenate([F[POS, col], F[VEL, col], F[ORI, col]])
        # first order in dt: the shared strapdown transition leaves out the dt^2 terms of the
        # rate's effect on the mid-interval specific force (dt^2 |f| / 2, twice as a margin)
        tol = 2e-3 * np.linalg.norm(fd) + dt * dt * np.linalg.norm(base.f) + 1e-9
        assert np.linalg.norm(fd - an) <= tol, (s, i, fd, an)


def _coils():
    return [Coil((0, 0, 0), a, 0.055, 50) for a in np.eye(3)]


@pytest.mark.parametrize("seed0", [11])
def test_nees_of_delayed_window_updates_on_a_moving_source(seed0):
    """Consistency: 12 seeded runs of 2 s, the closed-form moving source and sensor of
    the tests above, IMUs with white noise at the filter's densities and offsets drawn
    from its initial standard deviations, a pulse of coil X, Y, Z every 100 ms from the
    bench's field model (``hil.physics``) with noise, each applied through its clone
    50 ms after its time. The summed NEES of the final pose (position and orientation,
    6 dof per run) lies within the two-sided 99.9 % chi-square band of 72 dof.
    Catches a covariance that is too small (a dropped process-noise term, a wrong clone
    cross-covariance, a source offset left out of the transition) or far too large."""
    coils = _coils()
    src = physics.Source([physics.SourceCoil(center=c.center, axis=c.axis, radius=c.radius, turns=c.turns)
                          for c in coils])
    model = SingleCoilModel(coils)
    rate = 120.0
    acc_d, gyr_d = 2e-3, 8.7e-4
    sig_amp = 2e-8
    current = 1.5
    total = 0.0
    runs = 12
    for r in range(runs):
        rng = np.random.default_rng(seed0 + r)
        ekf = _filter(acc_bias_rw=0.0, gyr_bias_rw=0.0)
        ba, bg = rng.normal(0, 0.05, 3), rng.normal(0, 0.02, 3)
        bsa, bsg = rng.normal(0, 0.02, 3), rng.normal(0, 8.7e-3, 3)
        q, v, R = _relative(0.0)
        P6 = np.diag([4e-3 ** 2] * 3 + [0.02 ** 2] * 3)
        e6 = rng.multivariate_normal(np.zeros(6), P6)
        ekf.initialize(q - e6[:3], R @ _rot(-e6[3:]), P6, 0, 0.05, 0.05, 0.02)
        ekf.v[:] = v - rng.normal(0, 0.05, 3)
        n = int(2.0 * rate)
        pending = []          # (clone, coil, due time, amplitude)
        k_pulse = 0
        for k in range(n + 1):
            t = k / rate
            t_us = int(round(t * 1e6))
            f, w, fs, ws = _imu(t)
            sd = math.sqrt(rate / 2.0)
            f = f + ba + rng.normal(0, acc_d * sd, 3)
            w = w + bg + rng.normal(0, gyr_d * sd, 3)
            fs = fs + bsa + rng.normal(0, acc_d * sd, 3)
            ws = ws + bsg + rng.normal(0, gyr_d * sd, 3)
            if k and k % 12 == 0 and k < n - 12:           # a pulse every 100 ms
                j = k_pulse % 3
                ekf.schedule_clone(j, t_us)
                qq, _, RR = _relative(t)
                y = current * RR.T @ src.unit_fields(qq[None, :])[j, 0] + rng.normal(0, sig_amp, 3)
                pending.append((j, j, t_us + 50_000, y))
                k_pulse += 1
            ekf.propagate_relative(t_us, f, w, fs, ws)
            while pending and pending[0][2] <= t_us:
                j, c, _, y = pending.pop(0)
                ekf.update_single_coil(j, y, np.full(3, sig_amp ** 2), c, current, model, 0.0, 1.0, gate=False)
                ekf.release_clone(j)
        q, v, R = _relative(n / rate)
        err = np.concatenate([q - ekf.p, physics.matrix_to_rotvec(ekf.R.T @ R)])
        P6 = np.zeros((6, 6))
        idx = list(range(POS.start, POS.stop)) + list(range(ORI.start, ORI.stop))
        P6[:] = ekf.P[np.ix_(idx, idx)]
        total += float(err @ np.linalg.solve(P6, err))
    dof = 6 * runs
    lo, hi = chi2.ppf(0.0005, dof), chi2.ppf(0.9995, dof)
    assert lo <= total <= hi, (total, lo, hi)


#: the earth field of the bench's world (``hil.physics.EARTH_FIELD_T``), world frame
EARTH = physics.EARTH_FIELD_T


def test_quiet_field_jacobian_matches_finite_differences():
    """The quiet-field update's prediction is ``R^T e`` and its ORI block ``[h]x`` agrees with
    central differences of ``(R exp([u]x))^T e`` to 1e-6 of the field (the error convention
    ``R_true = R exp([ori]x)``); every other column is zero. Catches a transposed ``R``
    (``R e``), the opposite sign of ``[h]x`` or the block in the wrong columns."""
    e = _filter()
    R = _rot([0.4, -0.3, 0.8])
    ev = _rot([0.2, 0.1, -0.3]).T @ EARTH            # some source-frame earth field
    e.initialize(np.zeros(3), R, np.eye(6) * 1e-12, 0, 1e-6, 1e-6, 1e-6)
    h = R.T @ ev
    e.update_quiet_field(h, ev, 1e-14)               # zero innovation: the state stays
    np.testing.assert_allclose(e.quiet_pred, h, rtol=0, atol=1e-15)
    H = e.upd.H
    eps = 1e-6
    fd = np.zeros((3, 3))
    for i in range(3):
        u = np.zeros(3)
        u[i] = eps
        fd[:, i] = ((R @ _rot(u)).T @ ev - (R @ _rot(-u)).T @ ev) / (2 * eps)
    np.testing.assert_allclose(H[:, ORI], fd, rtol=0, atol=1e-6 * np.linalg.norm(ev))
    rest = np.delete(H, np.r_[ORI.start:ORI.stop], axis=1)
    assert not rest.any()
    assert abs(e.quiet_nis) < 1e-9


def _heading_run(quiet: bool, seed: int, duration_s: float = 10.0, rate: float = 120.0, every: int = 4):
    """The closed-form moving source and sensor, IMUs with white noise at the filter's densities and
    offsets drawn from its initial standard deviations, no pulse: the relative orientation is the
    gyroscopes' alone, or (``quiet``) held by the quiet field every ``every`` steps: the earth field
    seen by both magnetometers (``Th^T E`` and ``Phi^T E`` with noise ``sig`` each). Returns the final
    orientation error (rad, sensor frame), the unit earth field in the sensor frame and the NIS of
    every quiet-field update."""
    rng = np.random.default_rng(seed)
    acc_d, gyr_d = 2e-3, 8.7e-4
    ekf = _filter(acc_bias_rw=0.0, gyr_bias_rw=0.0)
    bg, bsg = rng.normal(0, 0.02, 3), rng.normal(0, 8.7e-3, 3)
    ba, bsa = rng.normal(0, 0.05, 3), rng.normal(0, 0.02, 3)
    q, v, R = _relative(0.0)
    P6 = np.diag([4e-3 ** 2] * 3 + [0.02 ** 2] * 3)
    e6 = rng.multivariate_normal(np.zeros(6), P6)
    ekf.initialize(q - e6[:3], R @ _rot(-e6[3:]), P6, 0, 0.05, 0.05, 0.02)
    ekf.v[:] = v
    sig = 0.07e-6
    nis = []
    n = int(duration_s * rate)
    sd = math.sqrt(rate / 2.0)
    for k in range(n + 1):
        t = k / rate
        f, w, fs, ws = _imu(t)
        f = f + ba + rng.normal(0, acc_d * sd, 3)
        w = w + bg + rng.normal(0, gyr_d * sd, 3)
        fs = fs + bsa + rng.normal(0, acc_d * sd, 3)
        ws = ws + bsg + rng.normal(0, gyr_d * sd, 3)
        ekf.propagate_relative(int(round(t * 1e6)), f, w, fs, ws)
        if quiet and k and k % every == 0:
            Phi, Th = _truth(t)[3], _truth(t)[7]
            b = Th.T @ EARTH + rng.normal(0, sig, 3)
            ev = Phi.T @ EARTH + rng.normal(0, sig, 3)
            ekf.update_quiet_field(b, ev, 2 * sig * sig, gate=False)
            nis.append(ekf.quiet_nis)
    _, _, R = _relative(n / rate)
    err = physics.matrix_to_rotvec(ekf.R.T @ R)
    u = R.T @ _truth(n / rate)[3].T @ EARTH
    return err, u / np.linalg.norm(u), np.array(nis)


def test_quiet_field_holds_the_relative_orientation_the_gyroscopes_let_drift():
    """10 s without pulses (the gap between bursts, stretched): with the gyroscopes alone the
    relative orientation drifts with their offsets (0.02 rad/s drawn from the filter's prior;
    measured 7.8-20 deg across the earth field, seeds 3-5); with a quiet-field update every 4 steps
    the error across the field (the two axes one update observes) stays below 0.2 deg (measured
    0.02-0.09 deg), at least 50x smaller (measured 108-420x).
    Catches the update not applied (no injection), a wrong sign of ``H`` (the error grows) or the
    field taken in the wrong frame."""
    worse = []
    for seed in (3, 4, 5):
        drift, u, _ = _heading_run(False, seed)
        held, u2, _ = _heading_run(True, seed)
        across = held - u2 * (u2 @ held)
        across0 = drift - u * (u @ drift)
        assert math.degrees(np.linalg.norm(across)) < 0.2, (seed, math.degrees(np.linalg.norm(across)))
        worse.append(np.linalg.norm(across0) / np.linalg.norm(across))
    assert min(worse) > 50.0, worse


def test_quiet_field_nis_within_the_chi_square_band():
    """Consistency of the quiet-field update: over 3 seeded runs of 10 s (the run above), the summed
    NIS of the updates after the first second (about 870 of 3 dof; measured mean 2.73-3.04 per run) lies within the two-sided 99.9 %
    chi-square band of their degrees of freedom, with ``R = 2 sig^2 I`` the two magnetometers' noise.
    Catches an update covariance too small (``R`` of one magnetometer, a Jacobian that leaves the
    prior out of ``S``) or far too large."""
    total, dof = 0.0, 0
    for seed in (3, 4, 5):
        _, _, nis = _heading_run(True, seed)
        nis = nis[30:]
        total += float(nis.sum())
        dof += 3 * len(nis)
    lo, hi = chi2.ppf(0.0005, dof), chi2.ppf(0.9995, dof)
    assert lo <= total <= hi, (total / dof * 3, lo, hi)
