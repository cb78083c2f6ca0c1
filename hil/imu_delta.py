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

What goes on the wire is the node's **running sum** of the intervals'
deltas, quantised to ``DANG_LSB_RAD`` / ``DVEL_LSB_MPS`` and wrapped to 16
bits; the receiver takes the difference of consecutive frames. So the
quantisation remainder is carried into the next frame by construction (the
sent sums never differ from the true ones by more than half an LSB: no
drift), and a lost frame costs nothing but time resolution: the next
difference covers both intervals.

Saturation: the samples come in as the parts output them (clipped at their
full scale, ``hil.nodes.ImuSpec.clip``) with a flag per sensor; an interval
with a clipped gyroscope sample has ``sat_a`` set, one with a clipped
accelerometer sample ``sat_v`` (the node sets the stamp's saturated bit of
that frame). An interval's delta beyond what one frame's difference carries
(+-``FRAME_MAX`` counts: 1.638 rad, 3.277 m/s) is clipped to it and flagged
likewise, so the receiver's difference never wraps into a wrong sign.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from coiltrack.protocol.schema import DANG_LSB_RAD, DVEL_LSB_MPS

#: counts one interval's delta may add to a running sum: the receiver's difference of two wrapped
#: 16-bit sums carries -32768..32767, and the sums are rounded (half a count each side)
FRAME_MAX = 32766


class DeltaIntegrator:
    """Sums ``n`` IMU samples (rate rad/s, specific force m/s^2, sensor frame) into one
    (delta angle rad, delta velocity m/s) pair of quantised counts."""

    def __init__(self, n: int, dt_s: float):
        if n < 1:
            raise ValueError("a delta interval holds at least one sample")
        self.n = int(n)
        self.dt = float(dt_s)
        self.sum_a = np.zeros(3)    # running sums of the intervals' deltas, in LSB
        self.sum_v = np.zeros(3)
        self.sat_a = self.sat_v = False   # the last complete interval's saturation flags
        self.reset()

    def reset(self) -> None:
        """Start a fresh interval (after a gap in the samples); the running sums are kept."""
        self.C = np.eye(3)          # body at the current instant -> body at the interval's start
        self.dv = np.zeros(3)       # integrated specific force in the start frame
        self.k = 0
        self._sat_w = self._sat_f = False

    def add(self, w, f, sat_w: bool = False, sat_f: bool = False):
        """One sample (``sat_w`` / ``sat_f``: the gyroscope / accelerometer clipped in it);
        returns ``(dang_sum, dvel_sum)`` (int arrays, 3: the running sums in counts, wrapped to
        i16) when the interval is complete (its flags in ``sat_a``, ``sat_v``), else None."""
        self._sat_w |= bool(sat_w)
        self._sat_f |= bool(sat_f)
        dth = np.asarray(w, dtype=float) * self.dt
        half = Rotation.from_rotvec(0.5 * dth).as_matrix()
        self.dv += (self.C @ half) @ (np.asarray(f, dtype=float) * self.dt)
        self.C = self.C @ Rotation.from_rotvec(dth).as_matrix()
        self.k += 1
        if self.k < self.n:
            return None
        theta = Rotation.from_matrix(self.C).as_rotvec()
        dv_mid = Rotation.from_rotvec(0.5 * theta).as_matrix().T @ self.dv
        da, dv = theta / DANG_LSB_RAD, dv_mid / DVEL_LSB_MPS
        over_a, over_v = bool(np.any(np.abs(da) > FRAME_MAX)), bool(np.any(np.abs(dv) > FRAME_MAX))
        self.sum_a += np.clip(da, -FRAME_MAX, FRAME_MAX)
        self.sum_v += np.clip(dv, -FRAME_MAX, FRAME_MAX)
        self.sat_a, self.sat_v = self._sat_w or over_a, self._sat_f or over_v
        self.reset()
        return wrap16(self.sum_a), wrap16(self.sum_v)


def wrap16(x) -> np.ndarray:
    """Counts rounded and wrapped to a signed 16-bit value."""
    return ((np.round(np.asarray(x)).astype(np.int64) + 32768) % 65536 - 32768).astype(int)
