"""Stochastic clones of the pose for delayed single-coil measurements.

A pulse is averaged over tens of milliseconds and its window closes a
baseline later, about 0.1 s after the instant it describes (Schepers &
Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt`` sec. 2.1, eq 4 applied at
the pulse's own time). The filter clones the pose error at that instant: the
clone rows and columns of ``P`` are copied from ``POS``/``ORI`` and then
propagate with an identity transition, so their cross-covariance with the
live state carries the correlation. :class:`PoseClones` owns the cloned
nominal poses and their bookkeeping; the covariance stays its filter's, passed
in to each method (as ``ekf.KalmanUpdate.update`` takes it). All arrays are
allocated in ``__init__``.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.estimate.layout import GYR, ORI, POS, POSE_ORI, POSE_POS, VEL

__all__ = ["PoseClones"]


class PoseClones:
    """``n`` clone slots of a filter whose layout names ``C{k}P`` and ``C{k}O``."""

    def __init__(self, layout, n: int):
        self.n = int(n)
        nx = layout.n
        self.cp = tuple(getattr(layout, f"C{k}P") for k in range(self.n))
        self.co = tuple(getattr(layout, f"C{k}O") for k in range(self.n))
        self.p = np.zeros((self.n, 3))
        self.R = np.zeros((self.n, 3, 3))
        self.R[:] = np.eye(3)
        self.t = np.zeros(self.n, dtype=np.int64)
        self.due = np.zeros(self.n, dtype=bool)      # scheduled, not yet taken
        self.taken = np.zeros(self.n, dtype=bool)
        # column and row buffers (copies between columns of P would otherwise be buffered)
        self._cols = np.zeros((nx, 3))
        self._rows = np.zeros((3, nx))
        self._Tb = np.zeros((6, nx))
        self._TP = np.zeros((6, nx))
        self._TPT = np.zeros((6, 6))

    def clear(self) -> None:
        self.due.fill(False)
        self.taken.fill(False)

    def schedule(self, k: int, t_us: int) -> None:
        self.t[k] = int(t_us)
        self.due[k] = True
        self.taken[k] = False

    def take(self, k: int, P, p, R, initialized: bool) -> None:
        """Clone ``k`` is the pose ``(p, R)`` now; its rows and columns of ``P`` those of
        ``POS`` and ``ORI``."""
        self.p[k] = p
        self.R[k] = R
        self.due[k] = False
        self.taken[k] = True
        if not initialized:
            return
        cp, co = self.cp[k], self.co[k]
        for dst, src in ((cp, POS), (co, ORI)):
            np.copyto(self._rows, P[src, :])
            np.copyto(P[dst, :], self._rows)
        for dst, src in ((cp, POS), (co, ORI)):
            np.copyto(self._cols, P[:, src])
            np.copyto(P[:, dst], self._cols)

    def back(self, k: int, dt: float, G, P, p, v, R, initialized: bool) -> None:
        """Clone k as the pose ``dt`` seconds before the filter's state ``(p, v, R, P)``,
        predicted backwards: ``G`` (3, 3) is the orientation increment ``R_now^T R_then``
        the gyroscope integration gave. Constant velocity back over ``dt``: nominal
        ``p_then = p - v dt``, ``R_then = R G``; error::

            dp_then  = dp - dt dv
            dori_then = G^T (dori + dt dgyr)

        (the inverse of the filter's transition without the specific-force terms)."""
        cp, co = self.cp[k], self.co[k]
        cpk = self.p[k]
        for i in range(3):
            cpk[i] = float(p[i]) - float(v[i]) * dt
        np.matmul(R, G, out=self.R[k])
        self.due[k] = False
        self.taken[k] = True
        if not initialized:
            return
        T = self._Tb
        T.fill(0.0)
        for i in range(3):
            T[POSE_POS.start + i, POS.start + i] = 1.0
            T[POSE_POS.start + i, VEL.start + i] = -dt
            for j in range(3):
                T[POSE_ORI.start + i, ORI.start + j] = float(G[j, i])
                T[POSE_ORI.start + i, GYR.start + j] = dt * float(G[j, i])
        # the clone's rows and columns: T P, and T P T^T
        TP, TPT = self._TP, self._TPT
        np.matmul(T, P, out=TP)
        np.matmul(TP, T.T, out=TPT)
        np.copyto(P[cp, :], TP[POSE_POS])
        np.copyto(P[co, :], TP[POSE_ORI])
        np.copyto(self._rows, TP[POSE_POS])
        np.copyto(P[:, cp], self._rows.T)
        np.copyto(self._rows, TP[POSE_ORI])
        np.copyto(P[:, co], self._rows.T)
        np.copyto(P[cp, cp], TPT[POSE_POS, POSE_POS])
        np.copyto(P[cp, co], TPT[POSE_POS, POSE_ORI])
        np.copyto(P[co, cp], TPT[POSE_ORI, POSE_POS])
        np.copyto(P[co, co], TPT[POSE_ORI, POSE_ORI])

    def release(self, k: int, P) -> None:
        cp, co = self.cp[k], self.co[k]
        P[cp, :].fill(0.0)
        P[co, :].fill(0.0)
        P[:, cp].fill(0.0)
        P[:, co].fill(0.0)
        self.due[k] = False
        self.taken[k] = False

    def next_due(self, t: int, until: int) -> int:
        """The clone due in ``(t, until]`` soonest (-1: none)."""
        nxt = until
        kk = -1
        for k in range(self.n):
            if self.due[k] and t < self.t[k] <= nxt:
                nxt = int(self.t[k])
                kk = k
        return kk

    def inject(self, dx, rotate) -> None:
        """Apply the error estimate ``dx`` to the taken clones (``rotate(R, x, y, z)``: the
        filter's right-multiplication by ``exp([x y z]x)``)."""
        for k in range(self.n):
            if self.taken[k]:
                self.p[k] += dx[self.cp[k]]
                c = self.co[k].start
                rotate(self.R[k], float(dx[c]), float(dx[c + 1]), float(dx[c + 2]))
