"""Cramer-Rao bound of a pose from one magnetic cycle, computed from the
emulator's own physics (magpylib fields, finite differences), so it is
independent of the firmware's field models and Jacobians.

Measurement: the 3 x ncoils amplitudes ``y_j = R^T I_j b_j(p)`` (field of
coil ``j`` per ampere at ``p``, seen in the sensor frame) with independent
Gaussian noise of standard deviation ``sigma[:, j]``. Parameters: position
(3, m) and a rotation-vector perturbation (3, rad) of ``R``. The bound is
``F^-1`` with ``F = J^T W J`` (Schepers & Veltink 2010, sec. 2, the
covariance of eq 4 with no prior).
"""
from __future__ import annotations

import numpy as np

from .motion import rotvec_to_matrix


def amplitudes(world, p, R, currents) -> np.ndarray:
    """(3, ncoils) noise-free amplitudes in the sensor frame."""
    U = world.unit_fields(p)                     # (ncoils, 3) source frame, per ampere
    return R.T @ (U * np.asarray(currents)[:, None]).T


def fisher(world, p, R, currents, sigma, h_pos: float = 1e-5, h_rot: float = 1e-6) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    ncoil = len(world.coils)
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (3, ncoil)).ravel()
    J = np.empty((3 * ncoil, 6))
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = h_pos
        J[:, k] = ((amplitudes(world, p + dp, R, currents) - amplitudes(world, p - dp, R, currents))
                   / (2 * h_pos)).ravel()
    for k in range(3):
        w = np.zeros(3)
        w[k] = h_rot
        Rp, Rm = R @ rotvec_to_matrix(w), R @ rotvec_to_matrix(-w)
        J[:, 3 + k] = ((amplitudes(world, p, Rp, currents) - amplitudes(world, p, Rm, currents))
                       / (2 * h_rot)).ravel()
    Jw = J / sig[:, None]
    return Jw.T @ Jw


def crlb(world, p, R, currents, sigma) -> np.ndarray:
    """6x6 bound: position (m) then rotation vector (rad)."""
    F = fisher(world, p, R, currents, sigma)
    try:
        return np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf)


def crlb_position_rms(world, p, R, currents, sigma) -> float:
    C = crlb(world, p, R, currents, sigma)
    return float(np.sqrt(max(np.trace(C[:3, :3]), 0.0)))
