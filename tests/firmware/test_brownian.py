"""Gietler's Brownian-motion tracker (``estimate/brownian.py``, ``model/emitters.py``) against
independent references: magpylib's dipole and a magpylib wire for the two source kinds, central
finite differences for the Jacobian, scipy's matrix exponential (Van Loan) for eqs 10 and 12,
and the bench's eq-8 trajectories and noise for the filter's consistency (NEES, 99.9 % band)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import linalg, stats

from coiltrack.firmware.estimate import brownian
from coiltrack.firmware.estimate.layout import BROWNIAN_LAYOUT as L
from coiltrack.firmware.model.emitters import CURRENT, DIPOLE, PlatformModel, euler_zyx

MU0 = 4e-7 * math.pi


def _mixed_model(ac: bool) -> PlatformModel:
    """Two channels: dipoles and current elements, complex moments, offsets off the origin."""
    rng = np.random.default_rng(3)
    n = 6
    offsets = rng.uniform(-0.05, 0.05, (n, 3))
    moments = rng.normal(size=(n, 3)) + (1j * rng.normal(size=(n, 3)) if ac else 0.0)
    return PlatformModel(offsets, moments, [DIPOLE, CURRENT, DIPOLE, CURRENT, DIPOLE, DIPOLE], [0, 0, 1, 1, 0, 1], 2,
                         ac=ac, receiver=(0.01, -0.02, 0.03))


@pytest.mark.parametrize("ac", [False, True])
def test_jacobian_matches_central_differences(ac):
    """dh/dz and dh/dtheta against central differences (step 1e-6, rel 1e-6 of the largest
    entry): catches a wrong sign of dr/dz, a dropped rotation of the moment in dh/dtheta, a
    wrong dR/dtheta_k, or a wrong gradient of either source kind."""
    model = _mixed_model(ac)
    z, th = np.array([0.21, -0.17, 0.33]), np.array([0.3, -0.4, 1.1])
    h, H = np.zeros(model.m), np.zeros((model.m, 6))
    model.measure(z, th, h, H)
    fd = np.zeros_like(H)
    hp, hm = np.zeros(model.m), np.zeros(model.m)
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        model.measure(z + d[:3], th + d[3:], hp)
        model.measure(z - d[:3], th - d[3:], hm)
        fd[:, k] = (hp - hm) / (2 * eps)
    assert np.abs(H - fd).max() <= 1e-6 * np.abs(fd).max()


def test_dipole_field_matches_magpylib():
    """Eq 1 for the three emitters (rotated platform) against magpylib's Dipole (H = B / mu0),
    rel 1e-9: catches a wrong rotation sequence (eq 3), the moment not rotated (eq 2) or a
    wrong offset of emitters 2 and 3."""
    magpy = pytest.importorskip("magpylib")
    from scipy.spatial.transform import Rotation

    offsets = np.array([[0, 0, 0], [0.05, 0.05, 0.05], [-0.02, 0.03, 0.02]])
    moments = np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0]])
    model = PlatformModel(offsets, moments, [DIPOLE] * 3, [0, 1, 2], 3, ac=False)
    z, th = np.array([0.2, -0.2, 0.3]), np.array([0.02, -0.05, math.pi / 4])
    h = np.zeros(9)
    model.measure(z, th, h)
    R = Rotation.from_euler("ZYX", th[::-1]).as_matrix()      # Rz(t3) Ry(t2) Rx(t1)
    assert np.allclose(euler_zyx(th), R, atol=1e-14)
    for k in range(3):
        dip = magpy.misc.Dipole(moment=R @ moments[k], position=z + R @ offsets[k])
        B = dip.getB(np.zeros(3))                             # T
        assert np.allclose(h[3 * k:3 * k + 3], B / MU0, rtol=1e-9, atol=1e-12)


def test_current_element_matches_a_short_wire():
    """The eq-31 first term (grad G x C) against magpylib's Biot-Savart field of a straight wire of
    length 1 mm carrying C / 1 mm, at 20 cm (rel 1e-4, the wire's finite-length term is
    (l / r)^2 ~ 2.5e-5): catches a wrong sign or a missing 1/(4 pi)."""
    magpy = pytest.importorskip("magpylib")
    C = np.array([0.3, -0.2, 0.5])
    length = 1e-3
    model = PlatformModel([[0.0, 0.0, 0.0]], [C], [CURRENT], [0], 1, ac=False, receiver=(0.1, 0.12, -0.11))
    h = np.zeros(3)
    model.measure(np.zeros(3), np.zeros(3), h)
    u = C / np.linalg.norm(C)
    wire = magpy.current.Polyline(current=np.linalg.norm(C) / length,
                                  vertices=[-u * length / 2, u * length / 2])
    H_ref = wire.getB(np.array([0.1, 0.12, -0.11])) / MU0
    assert np.allclose(h, H_ref, rtol=1e-4)


def test_transition_and_process_covariance_match_van_loan():
    """F (eq 12) and Sigma (eq 10) against the exact discretisation of the continuous model
    dv = sigma_v dW, dz = v dt (and the same for omega, theta) by Van Loan's matrix exponential
    (scipy expm), rel 1e-12: catches a dropped dt^2/2 cross term, dt^3/3 written dt^3/2, or the
    blocks of (v, z) and (omega, theta) swapped in eq 11's order."""
    dt, sv, sw = 0.1, 0.01, 0.1
    A = np.zeros((12, 12))
    A[L.POS, L.VEL] = np.eye(3)
    A[L.THETA, L.RATE] = np.eye(3)
    Qc = np.zeros((12, 12))
    Qc[L.VEL, L.VEL] = sv ** 2 * np.eye(3)
    Qc[L.RATE, L.RATE] = sw ** 2 * np.eye(3)
    M = np.block([[-A, Qc], [np.zeros((12, 12)), A.T]]) * dt
    E = linalg.expm(M)
    F_ref = E[12:, 12:].T
    Q_ref = F_ref @ E[:12, 12:]
    assert np.allclose(brownian.transition(dt), F_ref, rtol=0, atol=1e-14)
    Q = brownian.process_covariance(dt, sv, sw)
    assert np.allclose(Q, Q_ref, rtol=1e-12, atol=1e-20)
    assert np.allclose(Q, Q.T)


def test_nees_within_the_999_band():
    """Consistency of the iterated EKF: the NEES of the 12-state error at the last step of 40
    independent runs (eq-8 trajectories and noise of the bench, sigma^2 = 1e-4, filter started
    at a draw from N(X0, P0), P0 = 1e-4 I), summed, within the two-sided 99.9 % band of a
    chi-square with 40 x 12 dof: catches a Q too small or too large (eq 10), a wrong R, a
    covariance not updated (Joseph) or an update applied twice."""
    from coiltrack.tools.bench import gietler as G
    from coiltrack.tools.scenarios.gietler import SPECS, _split

    spec, cfg = _split("gietler-conductive", (("noise.var", 1e-4),))
    spec = G.GietlerSpec(**{**spec.__dict__, "cube_center": None, "duration_s": 10.0})
    p0 = 1e-4
    total, runs = 0.0, 40
    for seed in range(1, runs + 1):
        truth, V = G.truth_and_measurements(spec, seed)
        model = G.platform_model(spec, True)
        f = brownian.BrownianEKF(model, spec.dt_s, spec.sigma_v, spec.sigma_w, spec.noise_var,
                                 iterations=cfg.gietler_iterations, tol=cfg.gietler_iter_tol)
        x_true0 = np.concatenate([truth["v"][0], truth["z"][0], truth["omega"][0], truth["theta"][0]])
        rng = np.random.default_rng([seed, 77])
        f.reset(x_true0 + math.sqrt(p0) * rng.standard_normal(12), p0 * np.eye(12))
        for t in range(1, len(V)):
            f.step(V[t])
        x_true = np.concatenate([truth["v"][-1], truth["z"][-1], truth["omega"][-1], truth["theta"][-1]])
        e = f.x - x_true
        total += float(e @ np.linalg.solve(f.P, e))
    dof = 12 * runs
    lo, hi = stats.chi2.ppf(0.0005, dof), stats.chi2.ppf(0.9995, dof)
    assert lo <= total <= hi, (total / runs, lo / runs, hi / runs)


def test_moving_receiver_is_tracked_through_the_relative_pose():
    """Either side may move: with the emitters fixed (pose z_e, R_e) and the receiver moving (z_r,
    R_r), the receiver's reading R_r^T H(z_r) (magpylib, world frame) equals the model at the
    relative pose z = R_r^T (z_e - z_r), R = R_r^T R_e (rel 1e-9): catches a model that
    assumes a receiver aligned with the world or the inverse pose used."""
    magpy = pytest.importorskip("magpylib")
    from scipy.spatial.transform import Rotation

    offsets = np.array([[0, 0, 0], [0.05, 0.05, 0.05], [-0.02, 0.03, 0.02]])
    moments = np.eye(3)[::-1]
    model = PlatformModel(offsets, moments, [DIPOLE] * 3, [0, 1, 2], 3, ac=False)
    z_e, R_e = np.array([0.05, 0.02, 0.0]), Rotation.from_euler("ZYX", [0.4, -0.1, 0.2]).as_matrix()
    z_r, R_r = np.array([0.3, -0.25, 0.2]), Rotation.from_euler("ZYX", [-0.7, 0.3, 0.5]).as_matrix()
    R_rel = R_r.T @ R_e
    th_rel = Rotation.from_matrix(R_rel).as_euler("ZYX")[::-1]
    h = np.zeros(9)
    model.measure(R_r.T @ (z_e - z_r), th_rel, h)
    for k in range(3):
        B = magpy.misc.Dipole(moment=R_e @ moments[k], position=z_e + R_e @ offsets[k]).getB(z_r)
        assert np.allclose(h[3 * k:3 * k + 3], R_r.T @ B / MU0, rtol=1e-9, atol=1e-12)
