"""Delta-angle and delta-velocity integration on a sensor node (the bench's
emulated node; PX4's sensor pipeline does the same on a flight controller).

The node samples its IMU at its own rate and, every ``n`` samples, sends an
IMU_DELTA pair: the rotation of the body over the interval as a rotation
vector (coning-free: the interval's rotation is accumulated as a rotation
matrix, ``C <- C Exp(w dt)``, and its logarithm taken at the end, which is
what PX4's coning correction approximates to second order) and the
integrated specific force, accumulated in the frame at the interval's start
with the attitude at each sub-step's middle and expressed at the end in the
body frame at the interval's middle (``Exp(dtheta / 2)^T dv_start``), the
frame whose rate and specific force a receiver takes as the interval's mean.
Each sample stands for ``[t - dt/2, t + dt/2]``; the pair is stamped with the
interval's end on the master clock.

Quantisation to ``DANG_LSB_RAD`` / ``DVEL_LSB_MPS`` carries the remainder
into the next frame, so the sum of the sent deltas differs from the sum of
the integrated ones by less than one LSB at any time: quantisation adds no
drift.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from coiltrack.protocol.schema import DANG_LSB_RAD, DVEL_LSB_MPS


class DeltaIntegrator:
    """Sums ``n`` IMU samples (rate rad/s, specific force m/s^2, sensor frame) into one
    (delta angle rad, delta velocity m/s) pair of quantised counts."""

    def __init__(self, n: int, dt_s: float):
        if n < 1:
            raise ValueError("a delta interval holds at least one sample")
        self.n = int(n)
        self.dt = float(dt_s)
        self.rem_a = np.zeros(3)
        self.rem_v = np.zeros(3)
        self.reset()

    def reset(self) -> None:
        """Start a fresh interval (after a gap in the samples); remainders are kept."""
        self.C = np.eye(3)          # body at the current instant -> body at the interval's start
        self.dv = np.zeros(3)       # integrated specific force in the start frame
        self.k = 0

    def add(self, w, f):
        """One sample; returns ``(dang_counts, dvel_counts)`` (int arrays, 3) when the
        interval is complete, else None."""
        dth = np.asarray(w, dtype=float) * self.dt
        half = Rotation.from_rotvec(0.5 * dth).as_matrix()
        self.dv += (self.C @ half) @ (np.asarray(f, dtype=float) * self.dt)
        self.C = self.C @ Rotation.from_rotvec(dth).as_matrix()
        self.k += 1
        if self.k < self.n:
            return None
        theta = Rotation.from_matrix(self.C).as_rotvec()
        dv_mid = Rotation.from_rotvec(0.5 * theta).as_matrix().T @ self.dv
        a = self._quantise(theta, DANG_LSB_RAD, "rem_a")
        v = self._quantise(dv_mid, DVEL_LSB_MPS, "rem_v")
        self.reset()
        return a, v

    def _quantise(self, x, lsb: float, rem: str):
        want = x + getattr(self, rem)
        q = np.clip(np.round(want / lsb), -32767, 32767)
        r = want - q * lsb
        setattr(self, rem, np.clip(r, -lsb, lsb))     # a clipped frame does not carry its excess on
        return q.astype(int)
