"""The two measurement updates of the ch. 2 orientation filter
(:mod:`coiltrack.firmware.estimate.orientation`), one class each.

Roetenberg thesis (``002_cd7f1fdb7fc67471.txt``) ch. 2, in the sign
convention of :mod:`~coiltrack.firmware.estimate.orientation`:

* :class:`Inclination` (eqs 2.20, 2.23, 2.29, 2.31-2.32): ``z = Z_A - Z_G =
  [Z x] theta + v``, with the adaptive motion variance ``Q_wa + k var(y_A -
  g Z-)`` (``body.acc_adapt_gain``);
* :class:`Compass` (eqs 2.21, 2.24, 2.30, 2.33): ``z = H_M - H_G = [H x] theta
  + d + v``; it first learns ``|m|`` and the dip (eqs 2.8-2.10) and raises the
  disturbance's driving noise with the change of norm and dip (eq 2.12);
  ``compass_heading_only`` turns its rows so it corrects the heading only.

Each fills the buffers of the one update shape (``ekf.KalmanUpdate``) and
runs it on the filter's ``P``; the filter applies the correction. Nothing
here allocates after ``__init__``.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import KalmanUpdate
from coiltrack.firmware.estimate.layout import DIST, ORIENTATION_LAYOUT, THETA

N = ORIENTATION_LAYOUT.n

#: the compass's state (``Compass.state``; the compiled core's ``CT_CS_*``): ``|m|`` (T), the
#: disturbance's driving noise ``qwd`` (eq 2.12), the low-passed norm and dip
CS_MREF, CS_QWD, CS_NORM, CS_DIP = range(4)
#: the inclination's motion level (``Inclination.st``; the compiled core's ``CT_IN_*``): the variance,
#: the running mean (3), the mean square, started (0 / 1)
IN_MOTION, IN_MEAN, IN_SQ, IN_STARTED = 0, 1, 4, 5


class Inclination:
    """The accelerometer's inclination update and the motion level it is weighted by
    (``motion_ms``: variance of ``y_A - g Z-``, m^2/s^4)."""

    def __init__(self, params, core=_DEFAULT_CORE):
        self.prm = params
        self.upd = KalmanUpdate(N, 3, params.gate_probability, core)
        self._H = memoryview(self.upd.H)
        self._R = memoryview(self.upd.R)
        # the motion level, the running mean of y_A - g Z- (a tilt error shows here, not above), the
        # running mean of |y_A - g Z-|^2 and whether it started (IN_*; the compiled core's CT_IN_*)
        self.st = np.zeros(6)
        self._st = memoryview(self.st)

    motion_ms = property(lambda self: self._st[IN_MOTION])    # variance of y_A - g Z-, m^2/s^4

    def reset(self) -> None:
        """A new start: no motion seen yet."""
        self.st.fill(0.0)

    def observe(self, R, ax, ay, az, dt: float) -> None:
        """The motion the accelerometer sees besides gravity, ``|y_A - g Z-|^2``, averaged over
        ``acc_adapt_tau_s``: the variance of the inclination's motion term follows the motion
        level (only when ``acc_adapt_gain`` is on); ``dt`` (s): the prediction time since the
        last call (the filter's ``SUM_INCL_DT``)."""
        p = self.prm
        if p.acc_adapt_gain > 0.0:
            g = p.gravity
            ex, ey, ez = ax - g * R[2, 0], ay - g * R[2, 1], az - g * R[2, 2]
            k = dt / p.acc_adapt_tau_s if p.acc_adapt_tau_s > 0.0 else 1.0
            k = k if k < 1.0 else 1.0
            s = self._st
            if s[IN_STARTED] == 0.0:      # the first sample is the mean: no variance yet
                k = 1.0
                s[IN_STARTED] = 1.0
            m0 = s[IN_MEAN] + k * (ex - s[IN_MEAN])
            m1 = s[IN_MEAN + 1] + k * (ey - s[IN_MEAN + 1])
            m2 = s[IN_MEAN + 2] + k * (ez - s[IN_MEAN + 2])
            s[IN_MEAN], s[IN_MEAN + 1], s[IN_MEAN + 2] = m0, m1, m2
            sq = s[IN_SQ] + k * (ex * ex + ey * ey + ez * ez - s[IN_SQ])
            s[IN_SQ] = sq
            v = sq - (m0 * m0 + m1 * m1 + m2 * m2)
            s[IN_MOTION] = v if v > 0.0 else 0.0

    def update(self, R, P, vx, vy, vz, vn, ca) -> int:
        """The update of ``P`` with the specific force less the predicted acceleration ``v``
        (norm ``vn``) against ``Z = R^T e_z``; ``ca`` the acceleration's correlation over the
        step (eq 2.5). Returns the ekf flags (the correction in ``upd.dx``)."""
        p = self.prm
        g = p.gravity
        zx, zy, zz = R[2, 0], R[2, 1], R[2, 2]
        u = self.upd
        y = u._yv
        y[0] = vx / vn - zx
        y[1] = vy / vn - zy
        y[2] = vz / vn - zz
        # the predicted acceleration c_a a+ carries c_a times the previous
        # orientation error (a+ = y_A - g Z+), so only (1 - c_a) of the
        # orientation error shows in the inclination difference; its noise is
        # the accelerometer noise of both samples and the driving noise w_a
        skew_block(self._H, 0, THETA.start, (1.0 - ca) * zx, (1.0 - ca) * zy, (1.0 - ca) * zz)
        r = ((1.0 + ca * ca) * p.acc_noise ** 2 + p.acc_motion_sigma ** 2
             + p.acc_adapt_gain * self.motion_ms) / (g * g)
        Rm = self._R
        for i in range(3):
            Rm[i, i] = r
        return u.update(P)


class Compass:
    """The magnetometer's compass update, the learning of ``|m|`` (``m_ref``, T) and of the
    earth field's direction ``h_g`` (global frame), and the disturbance's driving noise
    (``qwd``, eq 2.12); the scalars in ``state`` (``CS_*``), which the compiled core shares."""

    def __init__(self, params, core=_DEFAULT_CORE):
        self.prm = params
        self.upd = KalmanUpdate(N, 3, params.gate_probability, core)
        self._H = memoryview(self.upd.H)
        self._R = memoryview(self.upd.R)
        for i in range(3):
            self._H[i, DIST.start + i] = 1.0
        self.h_g = np.zeros(3)           # earth field direction, global frame
        self._hgv = memoryview(self.h_g)
        self.state = np.zeros(4)         # CS_*: |m|, qwd, the low-passed norm and dip
        self._s = memoryview(self.state)
        self._s[CS_MREF] = 1.0           # |earth field|, T
        self._s[CS_QWD] = params.dist_sigma ** 2
        self._s[CS_NORM] = 1.0
        self._s[CS_DIP] = 0.0
        self._learn = 0
        # still learning |m| and the dip (``_learn > 0``; ``learning``): 0/1 in an int64 array the
        # compiled one-call IMU sample reads
        self.learn_state = np.zeros(1, dtype=np.int64)
        self._lsv = memoryview(self.learn_state)
        self._sum_h = 0.0
        self._sum_v = 0.0
        self._sum_n = 0.0

    def _set_learning(self, v: bool) -> None:
        self._lsv[0] = 1 if v else 0

    learning = property(lambda self: self._lsv[0] != 0, _set_learning)
    m_ref = property(lambda self: self._s[CS_MREF])      # |earth field|, T
    qwd = property(lambda self: self._s[CS_QWD])          # the disturbance's driving noise (eq 2.12)

    def start(self, hn: float, hu: float, mn: float) -> None:
        """The field of a start (north and up components of its direction, its magnitude): the
        compass learns over the next samples before it is used (:meth:`learn`)."""
        self.h_g[0] = hn
        self.h_g[1] = 0.0
        self.h_g[2] = hu
        self._s[CS_MREF] = mn
        # |m| and the dip are averaged over the next compass samples (in the
        # global frame, tilt kept by the inclination updates) before the
        # compass is used: one sample's noise (or a set/reset offset not yet
        # estimated) would tilt the reference. The first half of the window
        # only lets the inclination settle and is not averaged.
        self._learn = 2 * self.prm.mag_learn_samples
        self.learning = self._learn > 0
        self._sum_h = self._sum_v = self._sum_n = 0.0
        self._s[CS_NORM] = 1.0
        self._s[CS_DIP] = math.atan2(hu, abs(hn))

    def learn(self, R, mx, my, mz) -> bool:
        """While learning (True): the sample goes into ``|m|`` and the dip (eqs 2.8-2.10)."""
        if self._learn > self.prm.mag_learn_samples:
            self._learn -= 1                 # (still > 0: learning)
            return True
        if self._learn > 0:
            gx = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz
            gy = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz
            gz = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz
            self._sum_h += math.sqrt(gx * gx + gy * gy)
            self._sum_v += gz
            self._sum_n += math.sqrt(mx * mx + my * my + mz * mz)
            self._learn -= 1
            self.learning = self._learn > 0
            if self._learn == 0:
                k = self.prm.mag_learn_samples
                hh, hv, mn = self._sum_h / k, self._sum_v / k, self._sum_n / k
                hn = math.sqrt(hh * hh + hv * hv)
                self.h_g[0] = hh / hn
                self.h_g[2] = hv / hn
                self._s[CS_MREF] = mn
                self._s[CS_DIP] = math.atan2(self.h_g[2], self.h_g[0])
            return True
        return False

    def update(self, R, d, P, mx, my, mz) -> int:
        """The compass update of ``P`` with a magnetometer sample (T, sensor frame) against
        ``H_G = R^T h_g`` and the disturbance ``d``; adapts ``qwd`` (eq 2.12). Returns the ekf
        flags (the correction in ``upd.dx``)."""
        p = self.prm
        cs = self._s
        inv = 1.0 / cs[CS_MREF]
        nx, ny, nz = mx * inv, my * inv, mz * inv
        # eq 2.8-2.12: norm and dip of the measured field
        gx = R[0, 0] * nx + R[0, 1] * ny + R[0, 2] * nz
        gy = R[1, 0] * nx + R[1, 1] * ny + R[1, 2] * nz
        gz = R[2, 0] * nx + R[2, 1] * ny + R[2, 2] * nz
        # the sample-to-sample change is mostly sensor noise: eq 2.12 is applied
        # to low-passed norm and dip, so only a lasting change raises sigma_d
        al = p.dist_smoothing
        norm = (1.0 - al) * cs[CS_NORM] + al * math.sqrt(gx * gx + gy * gy + gz * gz)
        dip = (1.0 - al) * cs[CS_DIP] + al * math.atan2(gz, math.sqrt(gx * gx + gy * gy))
        sd = (p.dist_sigma + p.dist_norm_gain * abs(norm - cs[CS_NORM])
              + p.dist_dip_gain * abs(dip - cs[CS_DIP]))
        cs[CS_QWD] = sd * sd
        cs[CS_NORM] = norm
        cs[CS_DIP] = dip
        hg = self._hgv
        h0, h2 = hg[0], hg[2]
        # H_G = R^T h_G
        hx = R[0, 0] * h0 + R[2, 0] * h2
        hy = R[0, 1] * h0 + R[2, 1] * h2
        hz = R[0, 2] * h0 + R[2, 2] * h2
        u = self.upd
        y = u._yv
        y[0] = nx - d[0] - hx
        y[1] = ny - d[1] - hy
        y[2] = nz - d[2] - hz
        skew_block(self._H, 0, THETA.start, hx, hy, hz)
        if p.compass_heading_only:
            Hm = self._H
            for i in range(3):
                for j in range(3):
                    Hm[i, DIST.start + j] = 1.0 if i == j else 0.0
        r = p.mag_noise ** 2
        Rm = self._R
        for i in range(3):
            Rm[i, i] = r
        if p.compass_heading_only:
            self._heading_rows(R[2, 0], R[2, 1], R[2, 2], hx, hy, hz)
        return u.update(P)

    def _heading_rows(self, zx, zy, zz, hx, hy, hz) -> None:
        """The compass measurement in the basis ``e1 = Z x H_G / |.|`` (the
        way a turn about the vertical moves ``H_G``), ``e2 = Z``, ``e3 = e1 x
        e2`` (sensor frame): rows, innovation and Jacobian turned by ``E``;
        ``e2`` and ``e3`` get unit variance (the field's whole magnitude, no
        information), so the compass corrects the heading and leaves the
        inclination to the accelerometer (``body.compass_heading_only``)."""
        ax, ay, az = zy * hz - zz * hy, zz * hx - zx * hz, zx * hy - zy * hx
        an = math.sqrt(ax * ax + ay * ay + az * az)
        if not an > 1e-6:
            return                           # field along the vertical: the full update
        ax, ay, az = ax / an, ay / an, az / an
        cx, cy, cz = ay * zz - az * zy, az * zx - ax * zz, ax * zy - ay * zx
        u = self.upd
        y = u._yv
        H = self._H
        t0, d0 = THETA.start, DIST.start
        y0, y1, y2 = y[0], y[1], y[2]
        y[0] = ax * y0 + ay * y1 + az * y2
        y[1] = zx * y0 + zy * y1 + zz * y2
        y[2] = cx * y0 + cy * y1 + cz * y2
        for c in range(3):
            h0, h1, h2 = H[0, t0 + c], H[1, t0 + c], H[2, t0 + c]
            H[0, t0 + c] = ax * h0 + ay * h1 + az * h2
            H[1, t0 + c] = zx * h0 + zy * h1 + zz * h2
            H[2, t0 + c] = cx * h0 + cy * h1 + cz * h2
        H[0, d0], H[0, d0 + 1], H[0, d0 + 2] = ax, ay, az
        H[1, d0], H[1, d0 + 1], H[1, d0 + 2] = zx, zy, zz
        H[2, d0], H[2, d0 + 1], H[2, d0 + 2] = cx, cy, cz
        Rm = self._R
        Rm[1, 1] = 1.0
        Rm[2, 2] = 1.0


def skew_block(H, row, col, x, y, z) -> None:
    """Write ``[v]x`` into ``H[row:row+3, col:col+3]`` (memoryview)."""
    H[row, col] = 0.0
    H[row, col + 1] = -z
    H[row, col + 2] = y
    H[row + 1, col] = z
    H[row + 1, col + 1] = 0.0
    H[row + 1, col + 2] = -x
    H[row + 2, col] = -y
    H[row + 2, col + 1] = x
    H[row + 2, col + 2] = 0.0
