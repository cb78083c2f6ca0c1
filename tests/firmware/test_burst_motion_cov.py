"""The covariance a burst is fused and reported with covers the motion within
the burst (``track.burst_fusion.SensorInertial.motion_cov``).

A sensor turning while the X, Y, Z pulses are measured (100 ms apart) sees each
coil's field in another frame; the solver, which assumes it still, turns that
into a position error of about ``r |w| t_rms`` (thesis Appendix 5.A: the
position comes from the fields' mutual angles). Reference: the error of the
firmware's own solve of seeded bursts built pulse by pulse (each column in the
frame of its pulse's instant, Schepers & Veltink eq 5), against the 99.9 %
chi-square bound with 3 degrees of freedom (scipy)."""
import numpy as np
from scipy.stats import chi2

from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.compose import make_pose_solver
from coiltrack.firmware.pose.reference import measurement_model, so3_exp
from coiltrack.firmware.pose.solver import SOLVE_OK
from coiltrack.firmware.track.burst_fusion import FixedSource, PulseGate, SensorInertial

CFG = FirmwareConfig().validate()             # the thesis source: 3 orthogonal coils, r 5.5 cm, 50 turns
COILS = [Coil(c.center, c.axis, c.radius, c.turns) for c in CFG.source.coils]
CUR = np.array([c.current for c in CFG.source.coils])
SIGMA_T = 5e-8                       # 50 nT per pulse amplitude (the thesis bench's noise)
BOUND = chi2.ppf(0.999, 3)


def _inertial(cfg):
    n = len(cfg.source.coils)
    gate = PulseGate(np.zeros(n, np.int64), np.zeros(n, np.int64), cfg.pulse.fall_us, cfg.orientation.compass_guard_us)
    return SensorInertial(16, cfg, gate, FixedSource(cfg))


def _turning_bursts(seed: int, n: int, cfg):
    """Bursts at 0.17-0.30 m from the source, the sensor turning at 30 deg/s about a
    random axis (still in position): pulse j measured at ``(j - 1) spacing`` about the
    burst's middle, in the frame of that instant. Returns (S, p, R_mid, w)."""
    rng = np.random.default_rng(seed)
    dt = np.array([-1.0, 0.0, 1.0]) * cfg.timing.spacing_us * 1e-6
    out = []
    for _ in range(n):
        u = rng.normal(size=3)
        u[0] = abs(u[0]) + 0.3
        p = rng.uniform(0.17, 0.30) * u / np.linalg.norm(u)
        R = so3_exp(rng.normal(size=3))
        a = rng.normal(size=3)
        w = np.radians(30.0) * a / np.linalg.norm(a)          # rad/s, sensor frame
        S = np.empty((3, 3))
        for j in range(3):
            Rj = R @ so3_exp(w * dt[j])
            S[:, j] = measurement_model(p, Rj, COILS, CUR)[:, j]
        S += rng.normal(0.0, SIGMA_T, S.shape)
        out.append((S, p, R, w))
    return out


def test_a_turning_sensor_near_the_source_is_within_the_bound_of_the_covariance_it_is_fused_with():
    """20 seeded bursts at 17-30 cm, turning at 30 deg/s: the solver's own covariance
    (noise only: 0.1-0.4 mm) puts most solutions far outside the 99.9 % bound (the
    rotation moves them by millimetres); with the motion within the burst added
    (``motion_cov``, uncompensated) at most one of the 20 lies outside it. Catches the
    rotation's position term dropped (the old covariance: only ``|v| t_rms``, zero for
    a sensor still in position) or a rotation term given to the orientation alone."""
    cfg = CFG
    ins = _inertial(cfg)
    ps = make_pose_solver(cfg, COILS, cfg.budget.solve_gate_probability)
    sig = np.full((3, 3), SIGMA_T)
    C = np.zeros((6, 6))
    out_solver = out_fused = 0
    for S, p, R, w in _turning_bursts(11, 20, cfg):
        assert ps.solve(S, CUR, sig, np.array([1.0, 0.0, 0.0]), p, R) == SOLVE_OK
        e = ps.position - p
        ins.w_last[:] = w                   # the rate the gyroscope saw (offset removed)
        ins.motion_cov(ps.covariance, False, C, ps.position)
        d2_solver = float(e @ np.linalg.solve(ps.covariance[:3, :3], e))
        d2_fused = float(e @ np.linalg.solve(C[:3, :3], e))
        out_solver += d2_solver > BOUND
        out_fused += d2_fused > BOUND
    assert out_solver >= 10
    assert out_fused <= 1


def test_a_still_sensor_gets_nothing_added():
    """No rotation and no inertial motion: the covariance is the solver's, unchanged (the
    term must not inflate a still sensor's solutions and cost the fused accuracy)."""
    cfg = CFG
    ins = _inertial(cfg)
    C0 = np.diag([1e-8, 2e-8, 3e-8, 1e-6, 2e-6, 3e-6])
    C = np.zeros((6, 6))
    ins.w_last[:] = (0.0, 0.0, 0.0)
    ins.motion_cov(C0, False, C, np.array([0.2, 0.05, -0.03]))
    np.testing.assert_array_equal(C, C0)
    # 30 deg/s: r^2 |w|^2 t_rms^2 on each position axis, |w|^2 t_rms^2 on each orientation axis
    ins.w_last[:] = (0.0, np.radians(30.0), 0.0)
    p = np.array([0.2, 0.05, -0.03])
    ins.motion_cov(C0, False, C, p)
    t2 = (cfg.timing.spacing_us * 1e-6) ** 2 * (9 - 1) / 12.0
    ao = np.radians(30.0) ** 2 * t2
    np.testing.assert_allclose(np.diag(C), np.diag(C0) + np.r_[[float(p @ p) * ao] * 3, [ao] * 3], rtol=1e-12)
