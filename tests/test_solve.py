"""Tests of coiltrack.firmware.pose.reference: Kuipers closed form, least-squares pose,
measurement Jacobian and Cramer-Rao bound.  All random inputs are seeded."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware.model.field import MU0, Coil, CoilSet, orthogonal_source
from coiltrack.firmware.pose.reference import (
    MAX_VARIANCE,
    crlb,
    crlb_position_rms,
    kuipers,
    measurement_jacobian,
    measurement_model,
    measurement_model_and_jacobian,
    so3_exp,
    rotation_margin,
    solve_pose,
)

A = 0.055  # coil radius, m (thesis Table 5.1)
N = 50  # turns
I = 1.5  # current, A
MOMENT = N * I * math.pi * A ** 2  # A m^2
SIGMA = 0.5e-7 / math.sqrt(5)  # T: 0.5 uT-class noise averaged over 5 samples


def rot_angle(Ra, Rb):
    """Angle (rad) of ``Ra^T Rb``."""
    return float(np.linalg.norm(Rotation.from_matrix(Ra.T @ Rb).as_rotvec()))


def pose_grid(radii, seed):
    """Positions on a direction grid covering both hemispheres of every axis,
    each with a random orientation."""
    rng = np.random.default_rng(seed)
    poses = []
    for r in radii:
        for az in np.radians([0, 50, 130, 200, 290]):
            for el in np.radians([-70, -20, 30, 80]):
                d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                              math.sin(el)])
                poses.append((r * d, Rotation.random(random_state=rng).as_matrix()))
    return poses


def dipole_signal(p, R, moment):
    """Orthogonal dipole source (thesis eqs 5.13-5.14): S = R^T k (3uu^T - I)."""
    r = np.linalg.norm(p)
    u = p / r
    k = MU0 * moment / (4 * math.pi * r ** 3)
    return R.T @ (k * (3 * np.outer(u, u) - np.eye(3)))


# ---------------------------------------------------------------------------
# Kuipers
# ---------------------------------------------------------------------------
def test_kuipers_round_trip_grid():
    worst_p = worst_r = 0.0
    for p, R in pose_grid([0.05, 0.1, 0.3, 0.8, 3.0], seed=1):
        pe, Re = kuipers(dipole_signal(p, R, MOMENT), MOMENT, hemisphere=p)
        worst_p = max(worst_p, np.linalg.norm(pe - p) / np.linalg.norm(p))
        worst_r = max(worst_r, np.abs(Re - R).max())
        assert abs(np.linalg.det(Re) - 1) < 1e-14
    # position relative and rotation-matrix absolute 1e-12 (requirement 1e-9;
    # observed ~1e-15)
    assert worst_p < 1e-12 and worst_r < 1e-12


def test_kuipers_hemisphere_selection():
    rng = np.random.default_rng(2)
    for _ in range(20):
        p = rng.normal(size=3) * 0.2
        R = Rotation.random(random_state=rng).as_matrix()
        S = dipole_signal(p, R, MOMENT)
        # the mirror position gives the same signal matrix
        np.testing.assert_allclose(dipole_signal(-p, R, MOMENT), S, rtol=1e-14)
        pe, Re = kuipers(S, MOMENT, hemisphere=p)
        pm, Rm = kuipers(S, MOMENT, hemisphere=-p)
        np.testing.assert_allclose(pe, p, rtol=1e-12)
        np.testing.assert_allclose(pm, -p, rtol=1e-12)
        np.testing.assert_allclose(Rm, Re, atol=1e-14)  # rotation does not depend on it
    # default hemisphere is +x
    p = np.array([-0.2, 0.1, 0.05])
    pe, _ = kuipers(dipole_signal(p, np.eye(3), MOMENT), MOMENT)
    np.testing.assert_allclose(pe, -p, rtol=1e-12)


def test_kuipers_negative_moment_and_bad_input():
    p = np.array([0.1, -0.2, 0.15])
    R = so3_exp([0.4, -0.2, 1.1])
    pe, Re = kuipers(dipole_signal(p, R, -MOMENT), -MOMENT, hemisphere=p)
    np.testing.assert_allclose(pe, p, rtol=1e-12)
    np.testing.assert_allclose(Re, R, atol=1e-12)
    with pytest.raises(ValueError):
        kuipers(np.full((3, 3), np.nan), MOMENT)
    with pytest.raises(ValueError):
        kuipers(np.eye(3), 0.0)
    # a zero signal has no finite solution: no exception, no NaN
    pz, Rz = kuipers(np.zeros((3, 3)), MOMENT)
    assert np.all(np.isfinite(pz)) and np.all(np.isfinite(Rz))


# ---------------------------------------------------------------------------
# measurement model
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_measurement_jacobian_vs_finite_differences(model):
    coils = [Coil([0.01, 0, 0], [1, 0.2, 0], 0.05, 40), Coil([0, 0.01, 0], [0, 1, 0.3], 0.06, 50),
             Coil([0, 0, 0.01], [0.1, 0, 1], 0.055, 45), Coil([0, 0, 0], [1, 1, 1], 0.04, 30)]
    cur = np.array([1.5, 1.2, -1.0, 2.0])
    p = np.array([0.18, -0.07, 0.12])
    R = so3_exp([0.3, -0.5, 1.0])
    h, H = measurement_model_and_jacobian(p, R, coils, cur, model)
    np.testing.assert_allclose(h, measurement_model(p, R, coils, cur, model), rtol=1e-15)
    np.testing.assert_allclose(H, measurement_jacobian(p, R, coils, cur, model), rtol=1e-15)
    Hf = np.empty_like(H)
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        hp = measurement_model(p + d[:3], R @ so3_exp(d[3:]), coils, cur, model)
        hm = measurement_model(p - d[:3], R @ so3_exp(-d[3:]), coils, cur, model)
        Hf[:, :, k] = (hp - hm) / (2 * eps)
    # central differences, step 1e-6 m / 1e-6 rad: absolute error < 1e-7 |H|
    assert np.abs(H - Hf).max() < 1e-7 * np.abs(H).max()
    # S[:, j] = R^T B_j
    for j, c in enumerate(coils):
        np.testing.assert_allclose(h[:, j], R.T @ c.field(p, cur[j], model), rtol=1e-14)


def test_so3_exp():
    rng = np.random.default_rng(3)
    for w in list(rng.normal(size=(20, 3))) + [np.zeros(3), np.array([1e-9, -2e-9, 3e-10])]:
        np.testing.assert_allclose(so3_exp(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-15)


# ---------------------------------------------------------------------------
# solve_pose, noise free
# ---------------------------------------------------------------------------
def test_solve_pose_round_trip_orthogonal_exact():
    coils = orthogonal_source(A, N)
    cur = [I, I, I]
    worst_p = worst_r = 0.0
    for p, R in pose_grid([0.1, 0.25, 0.5, 0.8], seed=4):
        S = measurement_model(p, R, coils, cur)
        info = {}
        pe, Re, C = solve_pose(S, coils, cur, SIGMA, hemisphere=p, info=info)
        assert info["converged"]
        worst_p = max(worst_p, np.linalg.norm(pe - p) / np.linalg.norm(p))
        worst_r = max(worst_r, np.abs(Re - R).max())
        assert C.shape == (6, 6) and np.all(np.isfinite(C))
    # position relative / rotation absolute 1e-9 (observed ~2e-15)
    assert worst_p < 1e-9 and worst_r < 1e-9


def test_solve_pose_near_field_on_coil_axes():
    """At 1.8 coil radii on (or near) a coil axis the Kuipers start is up to
    70 degrees off (the eigenvalues of S^T S are no longer (4, 1, 1) k^2) and a
    plain LM from it ends in a local minimum; the near-field start must not."""
    coils = orthogonal_source(A, N)
    cur = [I, I, I]
    rng = np.random.default_rng(8)
    cases = [[0.001, 0.0035, 0.1], [0.0128, -0.0992, -0.0002], [-0.0988, -0.0127, 0.0085],
             [0.034, 0.0, -0.094], [0.0025, -0.0049, 0.0798], [0.0473, -0.001, -0.0645]]
    for p in map(np.array, cases):
        R = Rotation.random(random_state=rng).as_matrix()
        S = measurement_model(p, R, coils, cur)
        info = {}
        pe, Re, _ = solve_pose(S, coils, cur, SIGMA, hemisphere=p, info=info)
        # 1e-9 (observed ~1e-15)
        assert np.linalg.norm(pe - p) / np.linalg.norm(p) < 1e-9, (p, info)
        assert np.abs(Re - R).max() < 1e-9


def test_solve_pose_round_trip_dipole_model():
    coils = orthogonal_source(A, N)
    cur = [I, I, I]
    for p, R in pose_grid([0.1, 0.5], seed=5)[::3]:
        S = measurement_model(p, R, coils, cur, model="dipole")
        pe, Re, _ = solve_pose(S, coils, cur, SIGMA, hemisphere=p, model="dipole")
        # 1e-9 (observed ~1e-15: the Kuipers start is already exact)
        assert np.linalg.norm(pe - p) / np.linalg.norm(p) < 1e-9
        assert np.abs(Re - R).max() < 1e-9


SOURCES = {
    # three tilted coils with offset centres and unequal size
    "skew3": ([Coil([0.01, 0.0, 0.0], [1.0, 0.15, -0.1], 0.05, 40),
               Coil([0.0, 0.012, 0.0], [0.2, 1.0, 0.1], 0.06, 50),
               Coil([0.0, -0.005, -0.01], [0.1, -0.2, 1.0], 0.055, 45)],
              [1.5, 1.2, 1.0]),
    # four coils, the fourth along the diagonal
    "four": ([Coil([0.01, 0, 0], [1, 0.1, 0], 0.05, 40), Coil([0, 0.012, 0], [0.2, 1, 0.1], 0.06, 50),
              Coil([0, 0, -0.01], [0.1, -0.2, 1], 0.055, 45),
              Coil([0.005, 0.005, 0.005], [1, 1, 1], 0.04, 30)],
             [1.5, 1.2, 1.0, 2.0]),
    # six coils: two orthogonal triads 4 cm apart, one driven negative
    "six": (orthogonal_source(A, N, center=(-0.02, 0, 0)) + orthogonal_source(0.03, 80, center=(0.02, 0, 0)),
            [1.5, 1.5, 1.5, -1.0, 1.0, 1.0]),
}


@pytest.mark.parametrize("name", sorted(SOURCES))
@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_solve_pose_round_trip_general_sources(name, model):
    coils, cur = SOURCES[name]
    cs = CoilSet(coils)
    for p, R in pose_grid([0.1, 0.15, 0.4, 0.8], seed=6)[::4]:
        S = measurement_model(p, R, cs, cur, model=model)
        info = {}
        pe, Re, _ = solve_pose(S, cs, cur, SIGMA, hemisphere=p, model=model, info=info)
        # 1e-9 (observed ~1e-15)
        assert np.linalg.norm(pe - p) / np.linalg.norm(p) < 1e-9, (name, p, info)
        assert np.abs(Re - R).max() < 1e-9


def test_solve_pose_from_x0_and_single_coil_without_raising():
    coils = orthogonal_source(A, N)
    p = np.array([0.2, 0.05, -0.1])
    R = so3_exp([0.2, 0.1, -0.3])
    S = measurement_model(p, R, coils, [I] * 3)
    x0 = (p + 0.01, R @ so3_exp([0.05, -0.05, 0.02]))
    pe, Re, _ = solve_pose(S, coils, [I] * 3, SIGMA, x0=x0)
    assert np.linalg.norm(pe - p) < 1e-12 and np.abs(Re - R).max() < 1e-12
    # one coil: 3 equations, 6 unknowns.  No exception, no NaN, and a huge
    # variance along the unobservable directions.
    one = coils[:1]
    S1 = measurement_model(p, R, one, [I])
    with np.errstate(all="raise"):
        pe, Re, C = solve_pose(S1, one, [I], SIGMA, x0=x0)
    assert np.all(np.isfinite(pe)) and np.all(np.isfinite(Re)) and np.all(np.isfinite(C))
    assert np.linalg.eigvalsh(C).max() > 1e6  # m^2 / rad^2
    assert np.linalg.eigvalsh(crlb(p, R, one, [I], SIGMA)).max() > 1e6
    # a start exactly at the dipole singularity: no exception, finite output,
    # and the "unknown" covariance
    info = {}
    pe, Re, C = solve_pose(S, coils, [I] * 3, SIGMA, model="dipole",
                           x0=(np.zeros(3), np.eye(3)), info=info)
    assert not info["converged"]
    assert np.all(np.isfinite(pe)) and np.all(np.isfinite(Re))
    np.testing.assert_array_equal(C, MAX_VARIANCE * np.eye(6))
    with pytest.raises(ValueError):  # Kuipers start needs 3 independent moments
        solve_pose(S1, one, [I], SIGMA)
    with pytest.raises(ValueError):
        solve_pose(np.full((3, 3), np.nan), coils, [I] * 3, SIGMA)
    with pytest.raises(ValueError):
        solve_pose(S, coils, [I] * 3, 0.0)


# ---------------------------------------------------------------------------
# statistics: efficiency against the Cramer-Rao bound
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("r", [0.15, 0.25, 0.4])
def test_monte_carlo_error_reaches_crlb(r):
    """Kuipers + exact-model refinement is the ML estimator here; at these
    SNRs it should be efficient.  200 trials per pose: the sample RMS of a
    near-Gaussian 3-D error has a relative standard deviation of ~4 %, so the
    1.3x bound leaves > 5 sigma of margin."""
    coils = CoilSet(orthogonal_source(A, N))
    cur = np.full(3, I)
    rng = np.random.default_rng(int(r * 1000))
    d = rng.normal(size=3)
    p = r * d / np.linalg.norm(d)
    R = Rotation.random(random_state=rng).as_matrix()
    S0 = measurement_model(p, R, coils, cur)
    C = crlb(p, R, coils, cur, SIGMA)
    crlb_pos = crlb_position_rms(p, R, coils, cur, SIGMA)
    assert crlb_pos == pytest.approx(math.sqrt(np.trace(C[:3, :3])), rel=1e-14)
    crlb_rot = math.sqrt(np.trace(C[3:, 3:]))
    pos_err = np.empty((200, 3))
    rot_err = np.empty(200)
    cov_pos = np.empty(200)
    for t in range(200):
        S = S0 + rng.normal(size=S0.shape) * SIGMA
        pe, Re, Ce = solve_pose(S, coils, cur, SIGMA, hemisphere=p)
        pos_err[t] = pe - p
        rot_err[t] = rot_angle(Re, R)
        cov_pos[t] = math.sqrt(np.trace(Ce[:3, :3]))
    rms = math.sqrt(np.mean(np.sum(pos_err ** 2, axis=1)))
    rms_rot = math.sqrt(np.mean(rot_err ** 2))
    # position RMS within 1.3x the CRLB (observed 0.93-1.04x)
    assert rms <= 1.3 * crlb_pos, (rms, crlb_pos)
    assert rms >= 0.7 * crlb_pos  # and not suspiciously below it
    # orientation RMS likewise (observed 0.92-1.07x)
    assert rms_rot <= 1.3 * crlb_rot
    # the returned covariance, evaluated at the estimate, matches the bound at
    # the true pose within 10 % (observed < 4 %)
    assert np.all(np.abs(cov_pos / crlb_pos - 1) < 0.1)


def test_crlb_scales_with_sigma_and_accepts_per_element_sigma():
    coils = orthogonal_source(A, N)
    p = np.array([0.2, -0.1, 0.1])
    R = so3_exp([0.1, 0.2, 0.3])
    c1 = crlb(p, R, coils, [I] * 3, SIGMA)
    c2 = crlb(p, R, coils, [I] * 3, 2 * SIGMA)
    np.testing.assert_allclose(c2, 4 * c1, rtol=1e-10)
    c3 = crlb(p, R, coils, [I] * 3, np.full((3, 3), SIGMA))
    np.testing.assert_allclose(c3, c1, rtol=1e-12)
    # more noise on one coil only increases the bound
    sig = np.full((3, 3), SIGMA)
    sig[:, 2] *= 3
    assert crlb_position_rms(p, R, coils, [I] * 3, sig) > crlb_position_rms(p, R, coils, [I] * 3, SIGMA)
    # the bound, with the second-order margin of the orientation error in its position block,
    # equals the covariance solve_pose returns for noise-free data; at this range the margin
    # is under 1e-3 of the position variances
    S = measurement_model(p, R, coils, [I] * 3)
    _, _, C = solve_pose(S, coils, [I] * 3, sig, hemisphere=p)
    cb = crlb(p, R, coils, [I] * 3, sig)
    np.testing.assert_allclose(C, rotation_margin(cb), rtol=1e-6, atol=1e-9 * np.abs(C).max())
    assert np.all(np.abs(np.diag(C)[:3] / np.diag(cb)[:3] - 1.0) < 1e-3)
