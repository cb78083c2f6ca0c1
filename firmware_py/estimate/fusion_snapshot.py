"""The fusion filter's snapshot at a magnetic solution's reference instant.

A magnetic solution refers to ``t_ref``, the middle of its burst, and arrives
about 170 ms later (thesis ``002_cd7f1fdb7fc67471.txt`` sec 6.2.3). When the
IMU stream crosses ``t_ref`` the filter keeps here its state, the source
orientation ``Phi`` (eq 6.7) and the ch. 2 filter's ``Xi`` with its covariance
and gyroscope offset (eqs 6.19-6.21); the delayed update restores them.

All buffers are created in ``__init__``; taking a snapshot allocates nothing.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.fusion_state import InsState


class Snapshot:
    """The state, ``Phi`` and ``Xi`` at ``t`` (``pending``: scheduled, not taken yet; ``valid``:
    taken and not used; ``initialized``: the inertial state was running when taken; ``xi``:
    ``Xi`` was initialised and kept).

    Parameters
    ----------
    n : int
        State dimension.
    frame : fusion_state.MovingSource or fusion_state.FixedSource
    xi_filter : orientation.OrientationFilter or None
    """

    def _set_t(self, v: int) -> None:
        self._sqv[0] = v

    def _set_pending(self, v: bool) -> None:
        self._sqv[1] = 1 if v else 0

    def _set_valid(self, v: bool) -> None:
        self._sqv[2] = 1 if v else 0

    # the time, pending and valid (0/1) in an int64 array (``sq``) the compiled one-call IMU sample
    # reads (t, pending) and a burst's compiled opening writes (``core/src/burst_open.c``
    # ``ct_schedule``: :meth:`schedule`'s writes)
    t = property(lambda self: self._sqv[0], _set_t)
    pending = property(lambda self: self._sqv[1] != 0, _set_pending)
    valid = property(lambda self: self._sqv[2] != 0, _set_valid)

    def __init__(self, n: int, frame, xi_filter, core=_DEFAULT_CORE):
        self.sq = np.zeros(3, dtype=np.int64)
        self._sqv = memoryview(self.sq)
        self.st = InsState(n, None, core=core)
        self.frame = frame
        self.xi_filter = xi_filter
        self.Phi = np.eye(3)
        self.Xi = np.eye(3)
        self.XiP = np.zeros((3, 3))
        self.XiB = np.zeros(3)
        self.Phiv = memoryview(self.Phi)
        self.Xiv = memoryview(self.Xi)
        self.XiPv = memoryview(self.XiP)
        self.t = 0
        self.pending = False
        self.valid = False
        self.initialized = False
        self.xi = False
        self._ck = None

    def bind(self, imu_d, core=_DEFAULT_CORE) -> None:
        """On the compiled core, :meth:`take_aux` reads the IMU ring's rows ``imu_d`` (the only ring it is
        given) in ``core/src/fusion.c`` ``ct_fusion_snap_aux`` (``ext.SnapAux``, bound once here to the
        ring, this snapshot and the ch. 2 filter's ``R``, covariance and offset); without a ch. 2 filter
        or a compiled core the Python stays."""
        ext = core.ext
        xi = self.xi_filter
        if ext is None or xi is None:
            return
        from coiltrack.firmware.estimate.layout import THETA
        self._ck = ext.SnapAux(self.frame.fixed, xi.P.shape[0], THETA.start, imu_d, self.Phi, self.Xi, self.XiP,
                               self.XiB, xi.R, xi.P, xi.bias)
        self._imu_d = imu_d
        self.take_aux = self._take_aux_compiled

    def _take_aux_compiled(self, d, k: int, full: bool) -> None:
        """:meth:`take_aux` on the compiled core (``d`` is the bound ring's rows): the filter's
        covariance brought up to date (``theta_covariance_global``'s ``propagate``), then one call."""
        xi = self.xi_filter
        ok = xi.initialized
        if ok:
            xi.propagate()
        self._ck.take(k, ok)
        self.xi = ok
        self.pending = False
        self.valid = True
        self.initialized = full

    def schedule(self, t_ref_us: int) -> None:
        """Keep the state at ``t_ref_us`` when the stream reaches it."""
        self.t = int(t_ref_us)
        self.pending = True
        self.valid = False

    def due(self, t0: int, t1: int) -> bool:
        """A pending snapshot falls in the step ``(t0, t1]``."""
        q = self._sqv                    # (t, pending)
        return q[1] != 0 and t0 < q[0] <= t1

    def take_aux(self, d, k: int, full: bool) -> None:
        """Source orientation (IMU ring row ``k`` of ``d``) and Xi at t_ref (all that
        initialisation needs); ``full``: the inertial state was kept with them."""
        self.frame.phi_into(d, k, self.Phiv)
        xi = self.xi_filter
        if xi is not None and xi.initialized:
            np.copyto(self.Xi, xi.R)
            xi.theta_covariance_global(self.XiPv)
            np.copyto(self.XiB, xi.bias)
            self.xi = True
        else:
            self.xi = False
        self.pending = False
        self.valid = True
        self.initialized = full

    aux_kernel = property(lambda self: self._ck)    # ext.SnapAux (bind), or None: the Python take_aux

    def taken(self, xi: bool) -> None:
        """The compiled core took the snapshot at ``t`` (``ext.Replay.replay_take``: the state with
        ``Phi`` and, when ``xi``, the ch. 2 filter's, as :meth:`take`): its time and flags."""
        self.st.set_time(self.t)
        self.xi = xi
        self.pending = False
        self.valid = True
        self.initialized = True

    def take(self, st: InsState, d, k: int) -> None:
        """``st`` (at t_ref) with the source orientation and Xi."""
        self.st.copy_from(st)
        self.take_aux(d, k, True)

    def matches(self, t_ref_us: int) -> bool:
        """A valid snapshot at ``t_ref_us``."""
        return self.valid and self.t == t_ref_us

    def drop(self) -> None:
        """Not offered again (restored for an update, or the stream broke off)."""
        self.valid = False

    def keep(self) -> None:
        """A rejected, not final solution: the snapshot stays for another one of the burst."""
        self.valid = True
