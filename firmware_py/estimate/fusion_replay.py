"""The fusion filter's replay on the compiled core: :meth:`FusionFilter.step
<coiltrack.firmware.estimate.magnetic_inertial.FusionFilter.step>` in one C call per tick.

A delayed magnetic update is applied to the shadow state at ``t_ref`` and the IMU samples since
are replayed on it (thesis ``002_cd7f1fdb7fc67471.txt`` sec 6.2.3; strapdown eqs 6.1-6.4, 6.8,
transition eq 6.17). The reference is the Python loop of ``FusionFilter.step`` and ``_advance``
with ``InertialPrediction.propagate``, ``set_dt``, ``step_compiled`` and ``history``;
``core/src/fusion.c`` ``ct_fusion_replay`` follows it operation by operation, so the shadow,
its pose history and every counter come out the same. The kernel works on the arrays bound
here once (the shadow's with its step scalars ``ws``, the IMU ring's and the shadow history's with
their head and count arrays) and on a small array carrying the Python attributes it reads and
advances (``io``); :meth:`CompiledReplay.run` fills it before the call and hands the results back
to their owners through their methods.
A snapshot falling inside the replay stops the kernel at its instant: the snapshot is taken here
(``Snapshot.take``, which also reads the orientation filter) and the kernel resumes with the rest
of that sample.

All buffers are created in ``__init__``; a call allocates no numpy array.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.estimate.ekf import SYMMETRIZE_EVERY
from coiltrack.firmware.estimate.fusion_state import (HIST_FIELDS, HIST_P, HIST_R, IMU_F, IMU_FIELDS, IMU_FSRC,
                                                     IMU_PHI, IMU_W)

__all__ = ["CompiledReplay", "CompiledUpdate"]


class CompiledReplay:
    """``ct_fusion_replay`` bound to the shadow state ``sh`` (which carries the compiled step,
    ``InsState.ck``), the ``prediction``'s IMU ring, the shadow pose history ``hist``, the
    snapshot ``snap`` and the source ``frame``. :meth:`run` returns the kernel's stop
    (``ext.REPLAY_*``) and leaves the strapdown steps of the call in ``units``."""

    def __init__(self, sh, prediction, hist, snap, frame, ext):
        assert (ext.IMU_F, ext.IMU_W, ext.IMU_FSRC, ext.IMU_PHI, ext.IMU_WIDTH) == (
            IMU_F, IMU_W, IMU_FSRC, IMU_PHI, sum(w for _, w in IMU_FIELDS))
        assert (ext.HIST_P, ext.HIST_R, ext.HIST_WIDTH) == (HIST_P, HIST_R, sum(w for _, w in HIST_FIELDS))
        self.sh, self.pr, self.imu, self.hist, self.snap = sh, prediction, prediction.imu, hist, snap
        self.ext = ext
        self._io = np.zeros(ext.RIO_N, dtype=np.int64)
        self._iov = memoryview(self._io)
        pred = sh.pred
        # the state's step scalars (InsState.ws: dt_last, ka, kg) are the kernel's fo, and the rings'
        # head and count arrays (KernelRing.hc) its ring positions: the kernel reads and writes them
        # in place (InsState.set_step, Ring.advance)
        assert (ext.RFO_DT_LAST, ext.RFO_KA, ext.RFO_KG, ext.RFO_N) == (0, 1, 2, sh.ws.size)
        self._ck = ext.Replay(sh.P.shape[0], sh.p, sh.v, sh.Th, sh.ba, sh.bg, pred.A, sh.P, pred.Q, pred._T,
                              self.imu.t, self.imu.d, hist.t, hist.d, self._io, sh.ws, frame.fixed,
                              prediction._dtk, SYMMETRIZE_EVERY, self.imu.hc, hist.hc)
        self.units = 0
        self._idx = (ext.RIO_T, ext.RIO_SNAP_PENDING, ext.RIO_SNAP_T, ext.RIO_UNITS, ext.RIO_PRED_COUNT,
                     ext.RIO_STEPS, ext.RIO_SPLIT, ext.REPLAY_SNAPSHOT)

    def run(self, budget: int, take: bool = True) -> int:
        """Replay on the shadow, at most ``budget`` strapdown steps started (a sample split at a
        snapshot finishes), as ``FusionFilter.step``'s loop does; the kernel's stop. ``take``: the
        bound state is the authoritative one (``FusionFilter._advance``): a snapshot falling inside
        a sample is taken from it (else the sample is only split there). Bound to the live state
        and its history, one call with ``budget`` 1 is ``_advance`` of the newest sample."""
        T, SP, ST, U, PC, STEPS, SPLIT, SNAPSHOT = self._idx
        io = self._iov
        sh, snap, pr = self.sh, self.snap, self.pr
        pred = sh.pred
        replay = self._ck.replay
        io[U] = 0
        io[SPLIT] = -1
        while True:
            io[T] = sh.t_us
            io[SP] = 1 if snap.pending else 0
            io[ST] = snap.t
            io[PC] = pred.count
            rc = replay(budget)
            sh.set_time(io[T])
            pred.set_count(io[PC])
            pr.add_steps(io[STEPS])
            if rc != SNAPSHOT:
                break
            # FusionFilter._advance: the shadow (the authoritative state in a replay) at the
            # snapshot's instant is kept, then the kernel resumes with the rest of the sample
            if take:
                snap.take(sh, pr._idv, io[SPLIT])
        self.units = io[U]
        return rc

    kernel = property(lambda self: self._ck)      # the bound ext.Replay

    def bind_snapshot(self) -> bool:
        """Let :meth:`split_take` take the snapshot inside the kernel's call (``ext.Replay.replay_take``,
        bound to the snapshot's state and its compiled ``take_aux``); False where the snapshot has no
        compiled ``take_aux`` (no ch. 2 filter)."""
        snap = self.snap
        if snap.aux_kernel is None or snap.st.cs is None:
            return False
        self._ck.bind_snapshot(snap.st.cs, snap.aux_kernel)
        self._take = self._ck.replay_take
        return True

    def split_take(self) -> None:
        """:meth:`run` with ``budget`` 1 of the bound (live, authoritative) state's newest sample, in which
        the pending snapshot falls (``FusionFilter._advance``): the snapshot taken between the step's
        halves inside the one call (``Snapshot.take``'s copies; the ch. 2 filter's covariance brought up
        to date first, as ``take_aux`` does), then its flags (``Snapshot.taken``)."""
        T, SP, ST, U, PC, STEPS, SPLIT, _ = self._idx
        io = self._iov
        sh, snap, pr = self.sh, self.snap, self.pr
        pred = sh.pred
        io[U] = 0
        io[SPLIT] = -1
        io[T] = sh.t_us
        pending = snap.pending
        io[SP] = 1 if pending else 0
        io[ST] = snap.t
        io[PC] = pred.count
        xi = snap.xi_filter.initialized
        if xi:
            snap.xi_filter.propagate()
        self._take(1, xi)
        sh.set_time(io[T])
        pred.set_count(io[PC])
        pr.add_steps(io[STEPS])
        if pending and not io[SP]:
            snap.taken(xi)
        self.units = io[U]


class CompiledUpdate:
    """The delayed magnetic update's two halves on the compiled core, one call each
    (``ext.FusionUpdate``, ``core/src/fusion.c``): :meth:`restore` is ``FusionFilter._restore``
    (``ct_fusion_prepare``: the shadow from the snapshot, its pose history rewound to ``t_ref`` in part as
    ``PoseHistory.rewind_shadow`` does (``ct_hist_sync``), the
    measurement model evaluated; thesis sec 6.2.3) and :meth:`update` is ``FusionFilter._update_shadow``
    (``ct_fusion_update``: the Kalman update of ``ekf.KalmanUpdate``, eqs 6.5-6.6, with its periodic
    symmetrisation, then ``InsState.correct``). Bound once to the filter's measurement kernel, its
    shadow's and snapshot's ``FusState``, its pose histories and its update's buffers; a call allocates
    nothing."""

    @staticmethod
    def fits(fus) -> bool:
        """``fus`` runs on the compiled core throughout (state, update and measurement model)."""
        return fus.sh.cs is not None and fus.upd.core == "compiled" and getattr(fus.meas, "_ck", None) is not None

    def __init__(self, fus, ext):
        live, shadow = fus.history.live, fus.history.shadow
        self.sh, self.snap_st, self.upd = fus.sh, fus.snap.st, fus.upd
        hist = ext.HistCopy(live.t, live.d, live.hc, shadow.t, shadow.d, shadow.hc, fus.history.mark)
        self._ck = ext.FusionUpdate(fus.meas._ck, fus.sh.cs, fus.snap.st.cs, hist, fus.n, fus.m, *fus.upd.buffers())

    def methods(self) -> tuple:
        """(:meth:`restore`, :meth:`update`): the filter's ``_restore`` and ``_update_shadow``."""
        return self.restore, self.update

    def restore(self, t_ref_us: int, q, R_ms, C) -> None:
        self._ck.prepare(t_ref_us, q, R_ms, C)
        self.sh.set_time(self.snap_st.t_us)

    def update(self) -> int:
        upd = self.upd
        return upd.counted(self._ck.update(upd.gate, (upd.count + 1) % SYMMETRIZE_EVERY == 0))
