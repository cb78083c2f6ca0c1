"""The bench's Cramer-Rao bound (hil.crlb) against a computation written
here: magpylib ``Circle`` loops built from the coil parameters, amplitudes
``y_j = R^T I_j B_j(p)``, Jacobians by central differences with other steps
and the other orientation convention (global-frame perturbation
``exp([w]x) R``), Fisher information ``J^T diag(sigma^-2) J``."""
import magpylib
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.hil import crlb as hil_crlb
from coiltrack.hil.physics import SourceCoil
from coiltrack.hil.world import World

AXES = ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.6, -0.3, 0.74])
CENTERS = ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.12, 0.05, -0.03])
RADIUS, TURNS = 0.055, 50
CURRENTS = np.array([1.5, 1.5, 1.5, -1.2])


def coils():
    return [SourceCoil(center=c, axis=a, radius=RADIUS, turns=TURNS) for c, a in zip(CENTERS, AXES)]


def loops():
    """One magpylib loop per (thin) coil: ``TURNS`` ampere-turns per ampere, axis along ``axis``."""
    out = []
    for c, a in zip(CENTERS, AXES):
        rot, _ = Rotation.align_vectors([a], [[0.0, 0.0, 1.0]])
        out.append(magpylib.current.Circle(current=float(TURNS), diameter=2 * RADIUS, position=c,
                                           orientation=rot))
    return out


def amplitudes(p, R) -> np.ndarray:
    B = np.array([np.asarray(loop.getB(p)).reshape(3) for loop in loops()])      # T per A, source frame
    return (R.T @ (B * CURRENTS[:, None]).T).ravel(order="F")                      # coil by coil


def fisher(p, R, sigma, h_p=3e-5, h_r=3e-6) -> np.ndarray:
    J = np.zeros((3 * len(AXES), 6))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h_p
        J[:, k] = (amplitudes(p + d, R) - amplitudes(p - d, R)) / (2 * h_p)
        w = np.zeros(3)
        w[k] = h_r
        Rp, Rm = Rotation.from_rotvec(w).as_matrix() @ R, Rotation.from_rotvec(-w).as_matrix() @ R
        J[:, 3 + k] = (amplitudes(p, Rp) - amplitudes(p, Rm)) / (2 * h_r)
    s = np.broadcast_to(np.asarray(sigma, dtype=float), (3, len(AXES))).ravel(order="F")
    Jw = J / s[:, None]
    return Jw.T @ Jw


@pytest.mark.parametrize("p,rv,sigma", [
    ([0.25, 0.05, -0.04], [0.2, -0.5, 0.9], 2.5e-8),
    ([-0.12, 0.38, 0.21], [1.9, 0.3, -0.4], 5e-8),
    ([0.45, -0.2, 0.3], [0.0, 0.0, 0.0], np.array([[1e-8, 3e-8, 2e-8, 4e-8]] * 3)),
])
def test_crlb_matches_an_independent_fisher_computation(p, rv, sigma):
    """Position block, orientation block (turned into the sensor frame, where
    hil.crlb states its rotation vector: ``R_true = R exp([w]x)``) and the
    position RMS. Tolerance 0.1 % of the standard deviations (finite
    differences; measured agreement 4e-7)."""
    p = np.asarray(p, dtype=float)
    R = Rotation.from_rotvec(rv).as_matrix()
    world = World(coils(), trajectory=None)
    C = hil_crlb.crlb(world, p, R, CURRENTS, sigma)
    mine = np.linalg.inv(fisher(p, R, sigma))
    T = np.eye(6)
    T[3:, 3:] = R.T                             # global-frame rotation vector -> sensor frame
    mine = T @ mine @ T.T
    scale = np.sqrt(np.outer(np.diag(mine), np.diag(mine)))
    np.testing.assert_allclose(C / scale, mine / scale, rtol=0, atol=1e-3)
    assert hil_crlb.crlb_position_rms(world, p, R, CURRENTS, sigma) == pytest.approx(
        np.sqrt(np.trace(mine[:3, :3])), rel=1e-3)

