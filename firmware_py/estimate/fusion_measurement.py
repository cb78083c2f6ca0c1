"""The fusion filter's magnetic measurement models (thesis ``002_cd7f1fdb7fc67471.txt`` sec 6.2.5).

One model is chosen when the filter is built (:func:`make_measurement_model`):

* :class:`MagneticOrientation`, model 1, eq 6.18:
  ``z = [Phi q - p ; log(Psi Theta^T)]``, ``C = [I 0 0 0 0 I 0 ; 0 0 I 0 0 0 I]``;
  the filter starts from the magnetic orientation ``Psi = Phi R_ms``;
* :class:`InertialMagneticOrientation`, models 2 (eq 6.20: the orientation
  ``Xi`` of the ch. 2 filter instead of the magnetic one) and 3 (eq 6.21:
  both, stacked with their own noise); it needs ``Xi`` and starts from it.

Both follow :class:`MeasurementModel` and fill the buffers of the one update
shape (``ekf.KalmanUpdate``): ``H`` once, ``y`` and the white blocks of ``P``
at each update. The white magnetic error states get the covariance the solver
computed for that very solution, turned into the global frame (sec 6.5).
Nothing here allocates after ``__init__``.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from coiltrack.firmware.estimate.fusion_snapshot import Snapshot
from coiltrack.firmware.estimate.fusion_state import InsState
from coiltrack.firmware.estimate.layout import (ORI, POS, POSE_ORI, POSE_POS, PSI, QM, XI, fusion_layout,
                                               fusion_measurement_layout)
from coiltrack.firmware.linalg import congruence3, rotvec_from_matrix
from coiltrack.firmware.pose.covariance import RotationMargin


class MeasurementModel(Protocol):
    """What the fusion filter asks of its measurement model.

    Reads the snapshot (``Phi``, ``Xi``) and the state it is given; owns its
    rows of the innovation (``zlayout``) and its scratch; writes only the
    buffers passed to it. Work: a fixed number of 3x3 products per call."""

    layout: object          #: the state table (``layout.fusion_layout``)
    zlayout: object         #: the innovation's rows (``layout.fusion_measurement_layout``)

    def white(self, prm) -> tuple[tuple[slice, ...], tuple[float, ...]]:
        """The white states' blocks and their per-step variances."""

    def fill_constant(self, H, R, prm) -> None:
        """The constant ``C`` of eqs 6.18-6.21 into ``H`` and the noise into ``R`` (memoryviews)."""

    def ready(self, snap: Snapshot) -> bool:
        """The filter can start from this snapshot."""

    def evaluate(self, st: InsState, snap: Snapshot, q, R_ms, C, y) -> None:
        """Innovation into ``y`` and the white blocks of ``st.P``."""

    def bind(self, st: InsState, snap: Snapshot, y, core):
        """:meth:`evaluate` for ``st``, ``snap`` and ``y`` on ``core``, chosen once: ``f(q, R_ms, C)``."""

    def start_orientation(self, st: InsState, snap: Snapshot, R_ms, C) -> None:
        """The start's orientation, gyroscope offset and orientation block of ``st.P``."""


def _fill_h(H, zp: int, rows) -> None:
    for i in range(3):
        H[zp + i, POS.start + i] = 1.0
        H[zp + i, QM.start + i] = 1.0
        for row, white in rows:
            H[row + i, ORI.start + i] = 1.0
            H[row + i, white.start + i] = 1.0


def _position_and_white(st: InsState, snap: Snapshot, q, R_ms, C, y, zp: int, s: float, psi, Psi) -> None:
    """``y[zp:zp+3] = Phi q - p``; ``psi = Phi R_ms``; the white blocks ``Phi C_pp Phi^T``,
    ``Psi C_tt Psi^T``, ``Phi C_pt Psi^T`` (times ``s``) into ``st.P``."""
    Phi = snap.Phiv
    p = st._pv
    P = st._Pv
    for i in range(3):
        y[zp + i] = Phi[i, 0] * q[0] + Phi[i, 1] * q[1] + Phi[i, 2] * q[2] - p[i]
    np.matmul(snap.Phi, R_ms, out=psi)
    q0, s0 = QM.start, PSI.start
    cp, co = POSE_POS.start, POSE_ORI.start
    for i in range(3):
        for j in range(3):
            cpp = cpt = ctt = 0.0
            for a in range(3):
                fa = Phi[i, a]
                pa = Psi[i, a]
                for b in range(3):
                    cpp += fa * C[cp + a, cp + b] * Phi[j, b]
                    cpt += fa * C[cp + a, co + b] * Psi[j, b]
                    ctt += pa * C[co + a, co + b] * Psi[j, b]
            P[q0 + i, q0 + j] = cpp * s
            P[q0 + i, s0 + j] = cpt * s
            P[s0 + j, q0 + i] = cpt * s
            P[s0 + i, s0 + j] = ctt * s


def _log_diff(Z, Th, y, row) -> None:
    """``y[row:row+3] = log(Z Theta^T)`` (rotation vector, global frame)."""
    r00 = Z[0, 0] * Th[0, 0] + Z[0, 1] * Th[0, 1] + Z[0, 2] * Th[0, 2]
    r01 = Z[0, 0] * Th[1, 0] + Z[0, 1] * Th[1, 1] + Z[0, 2] * Th[1, 2]
    r02 = Z[0, 0] * Th[2, 0] + Z[0, 1] * Th[2, 1] + Z[0, 2] * Th[2, 2]
    r10 = Z[1, 0] * Th[0, 0] + Z[1, 1] * Th[0, 1] + Z[1, 2] * Th[0, 2]
    r11 = Z[1, 0] * Th[1, 0] + Z[1, 1] * Th[1, 1] + Z[1, 2] * Th[1, 2]
    r12 = Z[1, 0] * Th[2, 0] + Z[1, 1] * Th[2, 1] + Z[1, 2] * Th[2, 2]
    r20 = Z[2, 0] * Th[0, 0] + Z[2, 1] * Th[0, 1] + Z[2, 2] * Th[0, 2]
    r21 = Z[2, 0] * Th[1, 0] + Z[2, 1] * Th[1, 1] + Z[2, 2] * Th[1, 2]
    r22 = Z[2, 0] * Th[2, 0] + Z[2, 1] * Th[2, 1] + Z[2, 2] * Th[2, 2]
    x, yy, z = rotvec_from_matrix(r00, r01, r02, r10, r11, r12, r20, r21, r22)
    y[row] = x
    y[row + 1] = yy
    y[row + 2] = z


class _Base:
    def __init__(self, model: int, prm):
        self.layout = fusion_layout(model)
        self.zlayout = fusion_measurement_layout(model)
        names = self.zlayout.names()
        self._zp = self.zlayout.ZP.start
        self._zpsi = self.zlayout.ZPSI.start if "ZPSI" in names else -1
        self._zxi = self.zlayout.ZXI.start if "ZXI" in names else -1
        self.prm = prm
        self._E = np.zeros((3, 3))       # Psi = Phi R_ms
        self._Ev = memoryview(self._E)

    def bind(self, st: InsState, snap: Snapshot, y, core):
        """This model's :meth:`evaluate` for ``st`` and ``snap`` into ``y`` (an array), chosen
        once at composition: ``f(q, R_ms, C)``. On the compiled core it is
        ``core/src/fusion.c`` ``ct_fusion_evaluate`` (the same operations; the 3x3 product
        ``Phi R_ms`` summed in order where the reference calls BLAS: equal to rounding)."""
        ext = core.ext
        if ext is None:
            yv = memoryview(y)
            return lambda q, R_ms, C: self.evaluate(st, snap, q, R_ms, C, yv)
        prm = self.prm
        x0 = XI.start if "XI" in self.layout.names() else -1
        self._ck = ext.FusionMeas(self.layout.n, self._zp, self._zpsi, self._zxi, QM.start, PSI.start, x0,
                                  POSE_POS.start, POSE_ORI.start, int(self.xi_model), prm.mag_var_scale,
                                  prm.xi_var_scale, prm.xi_sigma_floor ** 2, prm.xi_heading_sigma_floor ** 2,
                                  prm.psi_sigma ** 2, snap.Phi, snap.Xi, snap.XiP, st.p, st.Th, st.P, y, self._E)
        return self._ck.evaluate

    def fill_constant(self, H, R, prm) -> None:
        rows = tuple((r, w) for r, w in ((self._zpsi, PSI), (self._zxi, XI)) if r >= 0)
        _fill_h(H, self._zp, rows)
        r = prm.meas_sigma ** 2
        for i in range(self.zlayout.n):
            R[i, i] = r

    def _position(self, st: InsState, snap: Snapshot, q, R_ms, C, y) -> None:
        _position_and_white(st, snap, q, R_ms, C, y, self._zp, self.prm.mag_var_scale, self._E, self._Ev)


class MagneticOrientation(_Base):
    """Model 1 (eq 6.18): position and the magnetic orientation ``Psi``."""

    xi_model = False        #: the compiled evaluate's branch (``ct_fusion_evaluate``)

    def __init__(self, prm):
        super().__init__(1, prm)

    def white(self, prm):
        return (QM, PSI), (prm.qm_sigma ** 2, prm.psi_sigma ** 2)

    def ready(self, snap: Snapshot) -> bool:
        return True

    def evaluate(self, st: InsState, snap: Snapshot, q, R_ms, C, y) -> None:
        self._position(st, snap, q, R_ms, C, y)
        _log_diff(self._Ev, st._Thv, y, self._zpsi)

    def start_orientation(self, st: InsState, snap: Snapshot, R_ms, C) -> None:
        """``Theta = Phi R_ms`` with the solver's orientation covariance turned into G; no offset."""
        np.matmul(snap.Phi, R_ms, out=st.Th)
        st.bg.fill(0.0)
        congruence3(st._Thv, C, POSE_ORI.start, st._Pv, ORI.start)


class InertialMagneticOrientation(_Base):
    """Models 2 (eq 6.20) and 3 (eq 6.21): the orientation ``Xi`` of the ch. 2 filter (and, in
    model 3, the magnetic one beside it); the filter starts from ``Xi``."""

    xi_model = True         #: the compiled evaluate's branch (``ct_fusion_evaluate``)

    def __init__(self, model: int, prm, xi_filter):
        if xi_filter is None:
            raise ValueError("measurement models 2 and 3 need the orientation filter Xi")
        super().__init__(model, prm)
        self._margin = RotationMargin()

    def white(self, prm):
        return (QM, PSI, XI), (prm.qm_sigma ** 2, prm.psi_sigma ** 2, prm.psi_sigma ** 2)

    def ready(self, snap: Snapshot) -> bool:
        return snap.xi

    def evaluate(self, st: InsState, snap: Snapshot, q, R_ms, C, y) -> None:
        self._position(st, snap, q, R_ms, C, y)
        prm = self.prm
        P = st._Pv
        if self._zpsi >= 0:
            _log_diff(self._Ev, st._Thv, y, self._zpsi)
            # the position's margin for the orientation error this solution has (pose.covariance)
            z = self._zpsi
            self._margin.realized_into(C, y[z] * y[z] + y[z + 1] * y[z + 1] + y[z + 2] * y[z + 2], snap.Phiv, P,
                                       QM.start, prm.mag_var_scale)
        _log_diff(snap.Xiv, st._Thv, y, self._zxi)
        x0 = XI.start
        xs = prm.xi_var_scale
        fl = prm.xi_sigma_floor ** 2
        fh = prm.xi_heading_sigma_floor ** 2
        XP = snap.XiPv
        for i in range(3):
            for j in range(3):
                P[x0 + i, x0 + j] = XP[i, j] * xs
            P[x0 + i, x0 + i] += fh if i == 2 else fl
        if self._zpsi < 0:
            # the magnetic orientation is not used: keep its white block inert
            q0, s0 = QM.start, PSI.start
            for i in range(3):
                for j in range(3):
                    P[s0 + i, s0 + j] = (prm.psi_sigma ** 2) if i == j else 0.0
                    P[q0 + i, s0 + j] = 0.0
                    P[s0 + j, q0 + i] = 0.0

    def start_orientation(self, st: InsState, snap: Snapshot, R_ms, C) -> None:
        """``Theta = Xi`` with its covariance and the ch. 2 filter's gyroscope offset."""
        np.copyto(st.Th, snap.Xi)
        np.copyto(st.bg, snap.XiB)
        P = st._Pv
        o0 = ORI.start
        for i in range(3):
            for j in range(3):
                P[o0 + i, o0 + j] = snap.XiPv[i, j]


def make_measurement_model(prm, xi_filter) -> MeasurementModel:
    """The model of ``prm.measurement_model`` (1, 2 or 3), chosen once."""
    if prm.measurement_model == 1:
        return MagneticOrientation(prm)
    return InertialMagneticOrientation(prm.measurement_model, prm, xi_filter)
