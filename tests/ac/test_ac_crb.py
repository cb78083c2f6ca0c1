"""A static sensor at 15-40 cm under AC excitation reaches the Cramer-Rao bound of the AC measurement.

Seeded Monte Carlo through the firmware's demodulator and pose solver, with the
bench's physics and a bound computed independently of both:

* samples: the thesis source's per-ampere fields from magpylib
  (``hil.physics.Source.unit_fields``), currents ``A cos(2 pi f_k (t - t_ref))``
  written here in closed form, the earth field, the MMC5983MA model of
  ``hil.magnetometers`` (0.5 ms averaging by quadrature, 1.2 mG white noise,
  18-bit counts);
* firmware: ``Demodulator`` (18 ms blocks; every other block, so the blocks
  share no sample) and ``PoseSolver`` from a cold start (acquisition and least
  squares), as the AC tracker runs them;
* bound: ``hil.crlb.crlb`` (magpylib fields, finite differences) with the
  per-element sigma of ``hil.ac_nodes.ac_amplitude_sigma`` (numpy's least-squares
  covariance of the block design, divided by the part's gain).

Band: with 120 independent blocks per pose (3 position dof each) the RMS over a
pose estimates its true value to about 4 % (1 sd), so an efficient estimator
lies in 0.85-1.2 of the bound at far beyond 3 sd on either side; 1.2 is the
issue's acceptance figure.
"""
import numpy as np
import pytest

from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.measure.demod import Demodulator
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.pose.solver import SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_NONFINITE, PoseSolver
from coiltrack.hil import physics
from coiltrack.hil.ac_nodes import ac_amplitude_sigma
from coiltrack.hil.crlb import crlb
from coiltrack.hil.magnetometers import FastMagProfile
from coiltrack.hil.motion import rotvec_to_matrix
from coiltrack.hil.world import World

FREQS = (215.0, 315.0, 465.0)
AMP = 1.5
WINDOW_US, HOP_US = 18_000, 9_000
PROF = FastMagProfile.mmc5983ma(0b11, 1000.0)
EARTH = np.array([18e-6, -4e-6, -44e-6])
TRIALS = 120


def _poses(rng, n):
    out = []
    for r in np.linspace(0.15, 0.40, n):
        az, el = rng.uniform(-0.8, 0.8), rng.uniform(-0.6, 0.6)
        p = r * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        out.append((p, rotvec_to_matrix(rng.normal(0.0, 1.0, 3))))
    return out


def _blocks(world, p, R, rng, trials):
    """Demodulated in-phase signal matrices of ``trials`` independent blocks at pose (p, R)."""
    U = world.unit_fields(p)                                   # (3 coils, 3) T/A, source frame
    ref_s = 0.0123

    def field(t):
        i = AMP * np.cos(2 * np.pi * np.array(FREQS)[:, None] * (t[None, :] - ref_s))   # (3, m)
        return (R.T @ (U.T @ i + EARTH[:, None])).T

    n = (trials * 2 + 2) * 18 + 3
    t_us = 1_000_000 + np.arange(n) * 1000 + 13
    counts, _ = PROF.sample(field, t_us * 1e-6, rng)
    B = PROF.to_tesla(counts)
    d = Demodulator(FREQS, WINDOW_US, HOP_US, PROF.noise_rms_t, 500)
    d.start(1_000_000, int(round(ref_s * 1e6)), (AMP,) * 3, (0.0,) * 3)
    out = []
    for i in range(n):
        k = d.push(int(t_us[i]), float(B[i, 0]), float(B[i, 1]), float(B[i, 2]), 0)
        if k >= 0 and d.finish(k) and k % 2 == 0:
            out.append((d.S.copy(), np.sqrt(d.var)))
        if len(out) == trials:
            break
    return out


@pytest.fixture(scope="module")
def runs():
    rng = np.random.default_rng(12)
    world = World(physics.thesis_source(), None)
    cfg = FirmwareConfig()
    solver = PoseSolver([Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.source.coils], "exact")
    sigma = np.broadcast_to(ac_amplitude_sigma(FREQS, 1000.0, WINDOW_US * 1e-6, PROF.noise_rms_t, 0.5e-3), (3, 3))
    currents = np.full(3, AMP)
    res = []
    for p, R in _poses(rng, 4):
        errs = []
        for S, sig in _blocks(world, p, R, rng, TRIALS):
            st = solver.solve(S, currents, sig, np.array([1.0, 0.0, 0.0]))
            assert not st & (SOLVE_BAD_INPUT | SOLVE_NO_START | SOLVE_NONFINITE), st
            errs.append(solver.position - p)
        e = np.array(errs)
        C = crlb(world, p, R, currents, sigma)
        res.append((np.linalg.norm(p), float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))),
                    float(np.sqrt(np.trace(C[:3, :3])))))
    return res


def test_static_position_rms_within_1_2_of_the_ac_crb(runs):
    """Per pose, position RMS / CRB in 0.85-1.2: catches a demodulator that loses precision (a wrong
    phase reference projects part of the signal into the quadrature; a missed magnetometer gain
    correction biases the range), a solver that stops short, or a stated variance that is too
    large (the ratio then falls below 0.85) or too small."""
    for r, rms, bound in runs:
        assert 0.85 <= rms / bound <= 1.2, (r, rms, bound)


def test_mean_ratio_near_one(runs):
    """Pooled over the poses the ratio is 1 within 8 %: the stated noise is the noise."""
    ratios = [rms / bound for _, rms, bound in runs]
    assert abs(np.mean(ratios) - 1.0) < 0.08, ratios
