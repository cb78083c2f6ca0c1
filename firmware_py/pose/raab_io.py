"""A solve's inputs into Raab's tracker and its published pose (``pose.raab.RaabTracker``).

Raab et al. 1979 (``seeds/004_86267342cd7488ce.txt``): the tracker works on the
signal matrix ``S``, the coil moments at the measured currents and their
pseudo-inverse ``M^+`` (eq 7's ``F = S M^+``), from a start that is the tracked
pose in Raab's coordinates ``(alpha, beta, rho, psi, theta, phi)`` (Table II)
or, without one, an acquisition on the configured hemisphere.
:class:`RaabIO` takes one solve's arguments into the tracker's buffers:

* the signals ``S`` (3, n) T, their weights ``1 / sigma`` and the currents (n,)
  A (``StagedSolve._load``: every value finite, every ``sigma`` positive);
* the hemisphere (3,) (finite, not zero) or ``(1, 0, 0)`` without one;
* the warm start's rotation (``raab_update.load_rotation``: as it is when it is
  a rotation to ``raab_update._ORTHO_TOL``, else its nearest rotation) and Raab's
  angles of its position about the coils' centre (``angles_from_pose``);
* the moments at the currents and ``M^+`` (``raab_update.moment_pseudo_inverse``).

On the compiled core (``coiltrack.firmware.core``) :meth:`RaabIO.load` is
one call of ``ct_raab_io`` (``core/src/raab.c``, the same operations in
the same order; inputs that are no float64 arrays, and a warm start's matrix
that is no rotation, go through the Python here, the reference).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.linalg import Rot3, nearest_rotation
from coiltrack.firmware.pose.raab_update import (_ORTHO_TOL, C_RAAB, angles_from_pose, load_rotation, point,
                                                 residual_cost, sync_rotation)
from coiltrack.firmware.pose.staged import StagedSolve

#: :meth:`RaabIO.load`'s results (``core/include/ct_ac.h``: CT_RIN_*): the first check that failed
#: (a bad load, hemisphere or warm start), the moments without a pseudo-inverse, or all taken
BAD_LOAD, BAD_HEMI, BAD_X0, PROJECT, NO_START, OK = range(6)


class RaabIO:
    """``begin``'s inputs into the buffers of a Raab tracker with ``n`` coils (module docstring).

    ``cbar`` the coils' centre; ``Sv``, ``wv`` (3 n), ``cur`` (n), ``x`` (6), ``Rn`` (3, 3),
    ``mpa``, ``mom``, ``Sc`` (3 n): the tracker's buffers (memoryviews of float64 arrays, ``Rn``
    an array), ``pm`` (3) the point of its last evaluation; ``update`` its ``raab_update.Update``
    (the pseudo-inverse); ``results`` its ``(position, rotation, angles)`` (arrays (3,), (3, 3)
    and a memoryview (6,)); ``acq_hemi`` the acquisition's hemisphere and ``margin`` the sine of
    the elevation beyond it that :meth:`behind` tests. After
    :meth:`load`: ``check_hemi`` (a hemisphere was given), ``hemi`` (3,), ``warm`` (a warm start
    was given).
    """

    def __init__(self, n: int, cbar, Sv, wv, cur, x, Rn, mpa, mom, Sc, pm, update, results, acq_hemi,
                 margin: float, core=_DEFAULT_CORE):
        self.n = n
        self._cbar = tuple(float(c) for c in cbar)
        # the names StagedSolve._load reads and writes
        self._Sv, self._wv, self._curv = Sv, wv, cur
        self._sigma_rms = 0.0
        self._x, self._Rn, self._R = x, Rn, memoryview(Rn)
        self._mpa, self._mom, self._Sc, self._pm = mpa, mom, Sc, pm
        self._acq = np.array([float(v) for v in acq_hemi])
        self._acqv = memoryview(self._acq)
        self._margin = float(margin)
        self._upd = update
        self._pos, self._rot, self._ang = results
        self._hemi = np.array([1.0, 0.0, 0.0])
        self.hemi = memoryview(self._hemi)
        self.check_hemi = False
        self.warm = False
        self._m9 = memoryview(np.zeros(9))
        self._rot3 = Rot3()
        self.core = "python"
        if core.ext is not None and 3 <= n <= 64:
            self._bind_compiled(core.ext)

    def _bind_compiled(self, ext) -> None:
        """:meth:`load` on ``ct_raab_io``, the buffers bound once."""
        self._cb = np.array(self._cbar)
        self._srms = np.zeros(1)
        self._srmsv = memoryview(self._srms)
        self._ck = ext.RaabIO(self.n, _ORTHO_TOL, C_RAAB, self._margin,
                              (self._cb, self._Sv, self._wv, self._curv, self._srms, self._hemi, self._m9, self._Rn,
                               self._x, self._mpa, self._mom, self._upd.mp, self._Sc, self._pos, self._rot,
                               self._ang, self._pm, self._acq))
        self.moved = self._ck.moved
        self.behind = self._ck.behind
        self.load = self._load_compiled
        self.residual_cost = self._ck.residual_cost
        self.finish_pose = self._ck.finish_pose
        self.core = "compiled"

    def load(self, S, currents, sigma, hemisphere, x0_position, x0_rotation) -> int:
        """The inputs of one solve (arguments as ``PoseSolver.begin``): ``OK``, ``NO_START`` (the
        moments do not span 3-D) or the first of ``BAD_LOAD``, ``BAD_HEMI``, ``BAD_X0`` that failed."""
        if not StagedSolve._load(self, S, currents, sigma):
            return BAD_LOAD
        if not self._load_hemisphere(hemisphere):
            return BAD_HEMI
        if not self._load_x0(x0_position, x0_rotation):
            return BAD_X0
        return OK if self._upd.pseudo_inverse(self._mpa, self._mom) else NO_START

    def _load_compiled(self, S, currents, sigma, hemisphere, x0_position, x0_rotation) -> int:
        r = self._ck.inputs(S, sigma, currents, hemisphere, x0_position, x0_rotation)
        if r is None:                                # inputs of another kind: the reference takes them
            return RaabIO.load(self, S, currents, sigma, hemisphere, x0_position, x0_rotation)
        self._sigma_rms = self._srmsv[0]
        if r >= BAD_HEMI:
            self.check_hemi = hemisphere is not None
        if r >= BAD_X0:
            self.warm = x0_position is not None
        if r == PROJECT:                             # the warm start's matrix is no rotation: projected here
            nearest_rotation(self._m9, self._Rn, self._rot3)
            if not self._angles(x0_position):
                return BAD_X0
            return OK if self._upd.pseudo_inverse(self._mpa, self._mom) else NO_START
        return r

    def _load_hemisphere(self, hemisphere) -> bool:
        self.check_hemi = hemisphere is not None
        h = self.hemi
        if hemisphere is None:
            h[0], h[1], h[2] = 1.0, 0.0, 0.0
            return True
        hx, hy, hz = hemisphere[0], hemisphere[1], hemisphere[2]
        h[0], h[1], h[2] = hx, hy, hz
        return math.isfinite(hx) and math.isfinite(hy) and math.isfinite(hz) and (hx * hx + hy * hy + hz * hz) > 0.0

    def _load_x0(self, x0_position, x0_rotation) -> bool:
        self.warm = x0_position is not None
        if (x0_position is None) != (x0_rotation is None):
            return False
        if x0_position is None:
            return True
        m9 = self._m9
        for i in range(3):
            if not math.isfinite(x0_position[i]):
                return False
            for j in range(3):
                m9[3 * i + j] = x0_rotation[i, j]
                if not math.isfinite(m9[3 * i + j]):
                    return False
        load_rotation(m9, self._R, self._Rn, self._rot3)
        return self._angles(x0_position)

    def _angles(self, x0_position) -> bool:
        """Raab's angles of the warm start (its rotation in ``R``); False at the coils' centre."""
        c = self._cbar
        px, py, pz = x0_position[0] - c[0], x0_position[1] - c[1], x0_position[2] - c[2]
        if px * px + py * py + pz * pz <= 0.0:
            return False
        x = self._x
        x[0], x[1], x[2], x[3], x[4], x[5] = angles_from_pose(px, py, pz, self._R)
        return True

    def moved(self, refresh: float) -> bool:
        """The estimate's point is more than ``refresh`` x range from ``pm`` (the last evaluation)."""
        x = self._x
        px, py, pz = point(x, self._cbar)
        pm = self._pm
        dx, dy, dz = px - pm[0], py - pm[1], pz - pm[2]
        return dx * dx + dy * dy + dz * dz > (refresh * x[2]) ** 2

    def behind(self, acquiring: bool) -> bool:
        """The estimate's direction is more than ``margin`` (the sine of its elevation) behind the
        plane of the hemisphere: the acquisition's while ``acquiring``, else the last ``begin``'s."""
        x = self._x
        hx, hy, hz = self._acqv if acquiring else self.hemi
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        ux, uy, uz = cb * ca, cb * sa, -sb
        hn = math.sqrt(hx * hx + hy * hy + hz * hz)
        return ux * hx + uy * hy + uz * hz < -self._margin * hn

    def residual_cost(self) -> float:
        """``raab_update.residual_cost`` of the corrected signals ``Sc`` (weights ``wv``, the moments
        ``mom``) at the estimate ``x``, ``R`` (the caller corrects the signals first)."""
        return residual_cost(self.n, self._x, self._R, self._Sc, self._wv, self._mom)

    def finish_pose(self) -> bool:
        """The estimate published: ``position`` its point about the coils' centre, ``R = A^T`` of
        its angles (``sync_rotation``) and ``rotation`` a copy, ``angles`` = ``x``; False when the
        position is not finite."""
        x = self._x
        px, py, pz = point(x, self._cbar)
        pos = self._pos
        pos[0], pos[1], pos[2] = px, py, pz
        sync_rotation(x, self._R)
        np.copyto(self._rot, self._Rn)
        ang = self._ang
        for i in range(6):
            ang[i] = x[i]
        return math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)
