"""The fusion filter's inertial state and the frame of its source.

:class:`InsState` is one copy of the state of the thesis ch. 6 error filter
(``002_cd7f1fdb7fc67471.txt`` eqs 6.1-6.4 nominal, eq 6.9 errors,
``layout.fusion_layout``) with its propagation workspace; the filter
(:mod:`coiltrack.firmware.estimate.magnetic_inertial`) keeps three of them.

The source frame ``Phi = R_GM`` (eq 6.7) comes in two kinds, chosen once when
the filter is built: :class:`MovingSource` takes ``Phi`` with every IMU sample
(the source's own orientation filter, sec 6.2.3) and turns the poses and
variances into the source frame with it; :class:`FixedSource` is ``Phi = I``
(no frame change, the IMU ring's ``PHI`` columns unused).

All buffers are created by the constructors; nothing here allocates after.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import CovariancePredict
from coiltrack.firmware.estimate.layout import ACC, GYR, ORI, POS, VEL
from coiltrack.firmware.linalg import exp_rotvec, rotvec_from_matrix
from coiltrack.firmware.ring import field_slices

#: named rows of an IMU ring entry: specific force, rate (sensor frame), the
#: source's specific force in G, the source orientation Phi (row-major)
IMU_FIELDS = (("F", 3), ("W", 3), ("FSRC", 3), ("PHI", 9))
#: named rows of a pose-history entry: p_M, R_MS (row-major), source frame
HIST_FIELDS = (("P", 3), ("R", 9))
_I, _H = field_slices(IMU_FIELDS), field_slices(HIST_FIELDS)
IMU_F, IMU_W, IMU_FSRC, IMU_PHI = _I["F"].start, _I["W"].start, _I["FSRC"].start, _I["PHI"].start
HIST_P, HIST_R = _H["P"].start, _H["R"].start


class InsState:
    """One copy of the inertial state: nominal position ``p``, velocity ``v``,
    orientation ``Th`` (Theta), offsets ``ba``, ``bg`` at ``t_us``, the error
    covariance ``P``, and its propagation workspace (``pred``: ``A``, ``Q`` of
    eq 6.17, written for the step ``dt_last``; ``white``: the rows of the white
    states, zero in ``A``). The filter holds three: the live state, the shadow
    (a replay in progress) and the snapshot at t_ref, which is only copied
    (``white=None``: no workspace)."""

    def __init__(self, n: int, white: tuple[slice, ...] | None, white_q: tuple[float, ...] = (),
                 core=_DEFAULT_CORE):
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.Th = np.eye(3)
        self.ba = np.zeros(3)
        self.bg = np.zeros(3)
        self.P = np.zeros((n, n))
        self.ts = np.zeros(1, dtype=np.int64)    # the time (``t_us``) in place for the one-call IMU sample
        self._tsv = memoryview(self.ts)
        self._pv = memoryview(self.p)
        self._vv = memoryview(self.v)
        self._Thv = memoryview(self.Th)
        self._bav = memoryview(self.ba)
        self._bgv = memoryview(self.bg)
        self._Pv = memoryview(self.P)
        # the step the workspace is written for and the offsets' decay over it (set_step): in an
        # array, which the compiled per-sample step shares (fusion_prediction, ``ext.FusPred``)
        self.ws = np.array([-1.0, 1.0, 1.0])
        self._wsv = memoryview(self.ws)
        self._E = np.zeros((3, 3))          # scratch of the correction
        self._Ev = memoryview(self._E)
        self._T = np.zeros((3, 3))
        #: the compiled strapdown and covariance step bound to this state's buffers, or None
        #: (``coiltrack.firmware.core``; ``InertialPrediction.step_compiled``)
        self.ck = None
        #: :meth:`correct` and :meth:`copy_from` on the compiled core (``core/src/fusion.c``
        #: ``ct_fusion_correct``, ``ct_fusion_copy``), bound here once, or None
        self.cs = None
        if core.ext is not None:
            self.cs = core.ext.FusState(n, self.p, self.v, self.Th, self.ba, self.bg, self.P)
            self.correct = self._correct_compiled
            self.copy_from = self._copy_from_compiled
        if white is None:
            self.pred = None
            return
        self.pred = CovariancePredict(n, core)
        self._Av = memoryview(self.pred.A)
        self._Qf = memoryview(self.pred.Q.reshape(-1))     # flat: element (i, j) at i n + j
        ext = core.ext
        if ext is not None and self.pred.core == "compiled":
            assert (POS.start, VEL.start, ORI.start, ACC.start, GYR.start) == (ext.POS, ext.VEL, ext.ORI,
                                                                             ext.ACC, ext.GYR)
            self.ck = ext.InsStep(n, self.p, self.v, self.Th, self.ba, self.bg, self.pred.A, self.P,
                                  self.pred.Q, self.pred._T)
        # the white states: no transition, their noise (``white_q``, one variance per block) has no
        # step in it, so it is written once here
        for s, q in zip(white, white_q, strict=True):
            for i in range(s.start, s.stop):
                self._Av[i, i] = 0.0
                self.pred.Q[i, i] = q

    def copy_from(self, other: "InsState") -> None:
        """Take ``other``'s nominal state, covariance and time (not its workspace)."""
        np.copyto(self.p, other.p)
        np.copyto(self.v, other.v)
        np.copyto(self.Th, other.Th)
        np.copyto(self.ba, other.ba)
        np.copyto(self.bg, other.bg)
        np.copyto(self.P, other.P)
        self.t_us = other.t_us

    def _copy_from_compiled(self, other: "InsState") -> None:
        """:meth:`copy_from` on the compiled core (both states bound to it)."""
        self.cs.copy_from(other.cs)
        self.t_us = other.t_us

    def _correct_compiled(self, dx) -> None:
        """:meth:`correct` on the compiled core (``dx``: a float64 buffer; the orientation
        product summed in order where the reference calls BLAS: equal to rounding)."""
        self.cs.correct(dx)

    def correct(self, dx) -> None:
        """Feed the error estimate ``dx`` (``layout.fusion_layout`` rows) back into the nominal
        state: ``p, v, b_a, b_g`` added, ``Theta <- exp([ori]x) Theta`` (global-frame error)."""
        p = self._pv
        v = self._vv
        ba = self._bav
        bg = self._bgv
        for i in range(3):
            p[i] += dx[POS.start + i]
            v[i] += dx[VEL.start + i]
            ba[i] += dx[ACC.start + i]
            bg[i] += dx[GYR.start + i]
        o = ORI.start
        exp_rotvec(dx[o], dx[o + 1], dx[o + 2], self._Ev)
        np.matmul(self._E, self.Th, out=self._T)
        np.copyto(self.Th, self._T)

    def velocity_sigma(self) -> float:
        """rms velocity uncertainty per axis, m/s."""
        P = self._Pv
        v0 = VEL.start
        return math.sqrt(max(P[v0, v0] + P[v0 + 1, v0 + 1] + P[v0 + 2, v0 + 2], 0.0) / 3.0)

    def speed_squared(self) -> float:
        v = self._vv
        return v[0] * v[0] + v[1] * v[1] + v[2] * v[2]

    def nees(self, p_true_g, R_true_g, v_true_g=None) -> float:
        """Normalised estimation error squared of position, orientation (and
        velocity) against a truth in the global frame (tests; allocates)."""
        e = []
        idx = []
        e.extend(np.asarray(p_true_g) - self.p)
        idx.extend(range(POS.start, POS.stop))
        if v_true_g is not None:
            e.extend(np.asarray(v_true_g) - self.v)
            idx.extend(range(VEL.start, VEL.stop))
        M = np.asarray(R_true_g) @ self.Th.T
        e.extend(rotvec_from_matrix(*M.reshape(9)))
        idx.extend(range(ORI.start, ORI.stop))
        e = np.array(e)
        Ps = self.P[np.ix_(idx, idx)]
        return float(e @ np.linalg.solve(Ps, e))

    def set_time(self, t_us: int) -> None:
        """The state now refers to ``t_us``."""
        self._tsv[0] = t_us

    t_us = property(lambda self: self._tsv[0], set_time)    # the time the state refers to (us)

    dt_last = property(lambda self: self._wsv[0])    # the step (s) the workspace is written for
    ka = property(lambda self: self._wsv[1])         # the offsets' decay factors over it
    kg = property(lambda self: self._wsv[2])

    def set_step(self, dt: float, ka: float, kg: float) -> None:
        """The step ``dt`` (s) the workspace's ``A`` and ``Q`` are written for, and the offsets'
        decay factors over it (eqs 6.13-6.14)."""
        w = self._wsv
        w[0] = dt
        w[1] = ka
        w[2] = kg


class MovingSource:
    """``Phi`` from the IMU ring (the source's orientation filter, sec 6.2.3)."""

    fixed = False

    def store(self, d, k: int, Phi) -> None:
        """Keep ``Phi`` (3x3) in IMU ring row ``k`` of ``d``."""
        for i in range(3):
            for j in range(3):
                d[k, IMU_PHI + 3 * i + j] = Phi[i, j]

    def phi_into(self, d, k: int, S) -> None:
        """``S`` (3x3) = the ``Phi`` of IMU ring row ``k``."""
        for i in range(3):
            for j in range(3):
                S[i, j] = d[k, IMU_PHI + 3 * i + j]

    def to_source(self, d, k: int, p, Th, hd, h: int) -> None:
        """History row ``h`` of ``hd``: ``p_M = Phi^T p``, ``R_MS = Phi^T Theta`` (Phi of IMU row ``k``)."""
        P0, R0, F = HIST_P, HIST_R, IMU_PHI
        for i in range(3):
            f0, f1, f2 = d[k, F + i], d[k, F + 3 + i], d[k, F + 6 + i]     # column i of Phi
            hd[h, P0 + i] = f0 * p[0] + f1 * p[1] + f2 * p[2]
            for j in range(3):
                hd[h, R0 + 3 * i + j] = f0 * Th[0, j] + f1 * Th[1, j] + f2 * Th[2, j]

    def position_var(self, d, k: int, P, p0: int, od, slot: int, col: int) -> None:
        """``od[slot, col:col+3] = diag(Phi^T P_pp Phi)`` (``P_pp`` at rows ``p0``; Phi of IMU row ``k``)."""
        q00, q01, q02 = P[p0, p0], P[p0, p0 + 1], P[p0, p0 + 2]
        q11, q12, q22 = P[p0 + 1, p0 + 1], P[p0 + 1, p0 + 2], P[p0 + 2, p0 + 2]
        F = IMU_PHI
        for c in range(3):
            x, y, z = d[k, F + c], d[k, F + 3 + c], d[k, F + 6 + c]      # column c of Phi
            od[slot, col + c] = (x * (q00 * x + q01 * y + q02 * z) + y * (q01 * x + q11 * y + q12 * z)
                                 + z * (q02 * x + q12 * y + q22 * z))


class FixedSource:
    """A fixed source, ``Phi = I``: no frame change (the ring's ``PHI`` columns are unused)."""

    fixed = True

    def store(self, d, k: int, Phi) -> None:
        """Nothing kept: ``Phi`` is the identity."""

    def phi_into(self, d, k: int, S) -> None:
        for i in range(3):
            for j in range(3):
                S[i, j] = 1.0 if i == j else 0.0

    def to_source(self, d, k: int, p, Th, hd, h: int) -> None:
        P0, R0 = HIST_P, HIST_R
        hd[h, P0], hd[h, P0 + 1], hd[h, P0 + 2] = p[0], p[1], p[2]
        for i in range(3):
            hd[h, R0 + 3 * i], hd[h, R0 + 3 * i + 1], hd[h, R0 + 3 * i + 2] = Th[i, 0], Th[i, 1], Th[i, 2]

    def position_var(self, d, k: int, P, p0: int, od, slot: int, col: int) -> None:
        od[slot, col], od[slot, col + 1], od[slot, col + 2] = P[p0, p0], P[p0 + 1, p0 + 1], P[p0 + 2, p0 + 2]
