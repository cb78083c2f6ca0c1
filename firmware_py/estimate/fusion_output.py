"""The fusion filter's outputs: its pose history and the fused poses waiting to be sent.

:class:`PoseHistory` keeps the inertial poses in the source frame (the live
history and the shadow a replay writes), so the firmware can interpolate the
pose at any recent instant (motion compensation within a burst, thesis
``002_cd7f1fdb7fc67471.txt`` sec 6.5). :class:`PoseOutput` queues the fused
poses (the POSE message's fields) with their variances and status bits.

All buffers are created in ``__init__``; nothing here allocates after.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.fusion_state import HIST_FIELDS, HIST_P, HIST_R, InsState
from coiltrack.firmware.estimate.layout import ORI, POS
from coiltrack.firmware.estimate.fusion_rings import KernelRing
from coiltrack.firmware.ring import Ring, field_slices
from coiltrack.firmware.rotation import quat_from_elements

if TYPE_CHECKING:
    from coiltrack.firmware.transmit import PoseReport

#: named rows of an output entry (the POSE message): p_M, quaternion (w, x, y, z),
#: position variances (source frame), orientation variances (sensor frame), status bits
OUT_FIELDS = (("P", 3), ("Q", 4), ("VAR_P", 3), ("VAR_O", 3), ("STATUS", 1))
_O = field_slices(OUT_FIELDS)
OUT_P, OUT_Q, OUT_VAR_P, OUT_VAR_O, OUT_STATUS = (_O["P"].start, _O["Q"].start, _O["VAR_P"].start,
                                                  _O["VAR_O"].start, _O["STATUS"].start)
#: status bits of ``OUT_STATUS``
OUT_STALE = 1               # no magnetic update for ``stale_us``
OUT_INCONSISTENT = 2        # the last update was not accepted cleanly
OUT_DEAD_RECKONING = 4      # no accepted magnetic update for ``dead_reckon_after_us``: inertial only
OUT_LOST = 8                # ... for ``dead_reckon_limit_us``: not a valid pose
OUT_RECOVERED = 16          # restarted from a magnetic solution, no update accepted since


#: ``PoseHistory.mark`` (int64): whether the live and the shadow history agree, array for array, outside the
#: slots each pushed since they were last made equal (1; 0: the next copy takes them whole), and each one's
#: newest slot and its time at that moment (:meth:`PoseHistory.rewind_shadow`, :meth:`PoseHistory.commit`)
MK_VALID, MK_LIVE_SLOT, MK_LIVE_T, MK_SHADOW_SLOT, MK_SHADOW_T, MK_N = range(6)


class PoseHistory:
    """The live pose history (``live``) and the one a replay writes (``shadow``), source frame.

    A rewind makes the shadow the live history and a commit the live history the shadow
    (``Ring.copy_from``: both arrays, head and count). Only the slots pushed since the two were last
    made equal can differ, so only those are copied (:meth:`_sync`): a ring is written only by its
    pushes (one slot at its head, with a time newer than any it holds; the live one by the fused
    sample's path, the shadow by the replay), so the slots a ring pushed since are the run after its
    newest slot then (``mark``) up to its newest now, unless that slot no longer holds its time then
    (a whole capacity pushed since: the copy is whole). A cleared shadow (a restart) makes the next
    copy whole too. The arrays after a copy are the same bytes as the whole copy's (the compiled core:
    ``core/src/hist_sync.c`` ``ct_hist_sync``)."""

    def __init__(self, capacity: int, core=_DEFAULT_CORE):
        self.live = KernelRing(capacity, HIST_FIELDS)    # (its head and count shared: ext.ImuSample)
        self.shadow = KernelRing(capacity, HIST_FIELDS)   # (its head and count shared: ext.Replay)
        self.mark = np.zeros(MK_N, dtype=np.int64)
        self._mkv = memoryview(self.mark)
        ext = core.ext
        if ext is not None:
            # pose_at on the compiled core (core/src/fusion.c ct_fusion_pose_at), bound to the live ring
            assert (HIST_P, HIST_R, self.live.width) == (ext.HIST_P, ext.HIST_R, ext.HIST_WIDTH)
            assert (MK_VALID, MK_LIVE_SLOT, MK_LIVE_T, MK_SHADOW_SLOT, MK_SHADOW_T, MK_N) == (
                ext.HMK_VALID, ext.HMK_LIVE_SLOT, ext.HMK_LIVE_T, ext.HMK_SHADOW_SLOT, ext.HMK_SHADOW_T, ext.HMK_N)
            # (the kernel's method itself: out_p, out_R C-contiguous float64 buffers)
            self.pose_at = ext.PoseAt(self.live.t, self.live.d, self.live.hc).at
            # rewind_shadow and commit (core/src/hist_sync.c ct_hist_sync: the same copies and drop)
            hc = ext.HistCopy(self.live.t, self.live.d, self.live.hc, self.shadow.t, self.shadow.d, self.shadow.hc,
                              self.mark)
            self.rewind_shadow = hc.rewind
            self.commit = hc.commit

    def rewind_shadow(self, t_ref_us: int) -> None:
        """The shadow starts as the live history up to ``t_ref_us``."""
        self._sync(self.shadow, self.live)
        self.shadow.drop_newer_than(t_ref_us)
        self._marked()

    def restart_shadow(self) -> None:
        """The shadow starts empty (the filter restarted)."""
        self.shadow.clear()
        self._mkv[MK_VALID] = 0

    def commit(self) -> None:
        """The replay caught up: its history becomes the live one."""
        self._sync(self.live, self.shadow)
        self._marked()

    def _sync(self, dst: KernelRing, src: KernelRing) -> None:
        """``dst.copy_from(src)``: the slots either ring pushed since the last copy (:func:`_pushed`), or all."""
        mk = self._mkv
        cap = src.capacity
        if mk[MK_VALID]:
            sl, ss = mk[MK_LIVE_SLOT], mk[MK_SHADOW_SLOT]
            nl = _pushed(self.live, sl, mk[MK_LIVE_T])
            ns = _pushed(self.shadow, ss, mk[MK_SHADOW_T])
            if nl + ns < cap:
                dst.copy_slots_from(src, sl + 1, nl)
                dst.copy_slots_from(src, ss + 1, ns)
                dst.take_position(src)
                return
        dst.copy_from(src)

    def _marked(self) -> None:
        """The two histories are equal (arrays; head and count but for a rewind's drop): each one's newest slot
        and its time (neither empty; else the next copy is whole)."""
        live, sh = self.live, self.shadow
        mk = self._mkv
        if not len(live) or not len(sh):
            mk[MK_VALID] = 0
            return
        mk[MK_VALID] = 1
        k = live.peek(0)
        mk[MK_LIVE_SLOT] = k
        mk[MK_LIVE_T] = live.tv[k]
        k = sh.peek(0)
        mk[MK_SHADOW_SLOT] = k
        mk[MK_SHADOW_T] = sh.tv[k]

    def pose_at(self, t_us: int, out_p, out_R) -> bool:
        """Inertial pose in the source frame at ``t_us`` (linear
        interpolation of the live history; ``out_R`` is not re-orthonormalised,
        which is second order in the step rotation). False when ``t_us`` is
        outside the history."""
        hist = self.live
        n = len(hist)
        if n < 2:
            return False
        i = hist.index_at_or_after(t_us)
        if i >= n:
            return False
        ht = hist.tv
        if i == 0:
            if ht[hist.slot(0)] != t_us:
                return False
            i = 1
        prev = hist.slot(i - 1)
        k = hist.slot(i)
        t0 = ht[prev]
        tk = ht[k]
        a = (t_us - t0) / (tk - t0) if tk > t0 else 1.0
        b = 1.0 - a
        hd = hist.dv
        for c in range(3):
            out_p[c] = b * hd[prev, HIST_P + c] + a * hd[k, HIST_P + c]
        for i2 in range(3):
            for j in range(3):
                c = HIST_R + 3 * i2 + j
                out_R[i2, j] = b * hd[prev, c] + a * hd[k, c]
        return True


class PoseOutput:
    """Fused poses waiting to be sent (rows ``OUT_*``), ``dropped`` when the queue was full.

    ``core``: the numeric core (``coiltrack.firmware.core``). On the compiled one, given the
    state ``st``, the IMU ring ``imu`` and the history ``hist`` that :meth:`queue` is always
    called with (the filter's live ones), a row is written by ``core/src/fusimu.c``
    ``ct_fus_output`` (bound once, ``ext.FusOutput``)."""

    def __init__(self, params, capacity: int, frame, core=_DEFAULT_CORE, st: InsState | None = None,
                 imu: Ring | None = None, hist: Ring | None = None):
        self.prm = params
        self.frame = frame
        self.out = KernelRing(capacity, OUT_FIELDS)      # (its head and count shared: ext.ImuSample)
        self._otv, self._odv = self.out.tv, self.out.dv
        self.dropped = 0
        ext = core.ext
        if ext is not None and st is not None and imu is not None and hist is not None:
            assert (OUT_P, OUT_Q, OUT_VAR_P, OUT_VAR_O, OUT_STATUS, self.out.width) == (0, 3, 7, 10, 13,
                                                                                      ext.FUS_OUT_WIDTH)
            assert (OUT_STALE, OUT_INCONSISTENT, OUT_DEAD_RECKONING, OUT_LOST, OUT_RECOVERED) == (1, 2, 4, 8, 16)
            assert (HIST_P, HIST_R, hist.width) == (0, 3, ext.FUS_HIST_WIDTH)
            self._ck = ext.FusOutput(st.P.shape[0], st.P, st.Th, imu.d, imu.capacity, hist.d, hist.capacity,
                                     self.out.d, capacity, not frame.fixed, params.stale_us,
                                     params.dead_reckon_after_us, params.dead_reckon_limit_us, self.out.t, self.out.hc)
            self.queue = self._queue_compiled
            self.into_report = self._into_report_compiled
            self.take_report = self._take_report_compiled
            self.send_plain = self._send_plain_compiled

    def send_plain(self, tx, node: int, status: int, quality: int, range_m: float) -> bool:
        """Send the queued poses, oldest first, that need nothing but their frame: no ``OUT_*``
        bit and within ``range_m`` of the source, sent with ``status`` (``tx.fused_pose``); stops
        at the first other one (left queued). True when none is left. The Python core sends
        none here: every pose goes through :meth:`take_report` (the reference)."""
        return not len(self.out)

    def _send_plain_compiled(self, tx, node: int, status: int, quality: int, range_m: float) -> bool:
        """:meth:`send_plain` on the compiled core (``ext.FusOutput.pose_next``: the POSE frame straight
        from the oldest output row, ``ct_pose_frame``, and the row off the queue)."""
        send = tx.fused_pose
        while True:
            r = send(self._ck, node, status, quality, range_m)
            if r <= 0:
                return r == 0

    def _queue_compiled(self, t_us: int, hist: Ring, st: InsState, d, k: int, last_update_t: int,
                        recovering: bool, inconsistent: bool) -> None:
        """:meth:`queue` on the compiled core (``ct_fus_output``; ``hist``, ``st`` and ``d`` are
        the bound ones)."""
        out = self.out
        if out.full:
            self.dropped += 1
            return
        self._ck.queue(out.push(t_us), hist.peek(0), k, t_us - last_update_t, recovering, inconsistent)

    def queue(self, t_us: int, hist: Ring, st: InsState, d, k: int, last_update_t: int, recovering: bool,
              inconsistent: bool) -> None:
        """Queue the fused pose (source frame, the newest of ``hist``) with its variances:
        position ``diag(Phi^T P_pp Phi)`` (Phi of IMU row ``k`` of ``d``), orientation in the
        sensor frame ``diag(R^T P_oo R)`` with ``R = Theta`` (as the POSE message defines)."""
        out = self.out
        if out.full:
            self.dropped += 1
            return
        slot = out.push(t_us)
        od = self._odv
        h = hist.peek(0)
        hd = hist.dv
        od[slot, OUT_P], od[slot, OUT_P + 1], od[slot, OUT_P + 2] = hd[h, HIST_P], hd[h, HIST_P + 1], hd[h, HIST_P + 2]
        _quat_into(hd, h, od, slot)
        P = st._Pv
        Th = st._Thv
        o0 = ORI.start
        # orientation: diag(Theta^T P_oo Theta) = sum_i Theta[i, c] (P_oo Theta)[i, c]
        o00, o01, o02 = P[o0, o0], P[o0, o0 + 1], P[o0, o0 + 2]
        o11, o12, o22 = P[o0 + 1, o0 + 1], P[o0 + 1, o0 + 2], P[o0 + 2, o0 + 2]
        for c in range(3):
            x, y, z = Th[0, c], Th[1, c], Th[2, c]
            od[slot, OUT_VAR_O + c] = (x * (o00 * x + o01 * y + o02 * z) + y * (o01 * x + o11 * y + o12 * z)
                                       + z * (o02 * x + o12 * y + o22 * z))
        self.frame.position_var(d, k, P, POS.start, od, slot, OUT_VAR_P)
        od[slot, OUT_STATUS] = self._status(t_us - last_update_t, recovering, inconsistent)

    def _status(self, age: int, recovering: bool, inconsistent: bool) -> int:
        prm = self.prm
        status = 0
        if age > prm.stale_us:
            status |= OUT_STALE
        if age > prm.dead_reckon_after_us:
            status |= OUT_DEAD_RECKONING
            if age > prm.dead_reckon_limit_us:
                status |= OUT_LOST
        if recovering:
            status |= OUT_RECOVERED
        if inconsistent:
            status |= OUT_INCONSISTENT
        return status

    def time_us(self, k: int) -> int:
        """The time of output row ``k`` (master clock, us)."""
        return self._otv[k]

    def into_report(self, k: int, r) -> int:
        """Output row ``k``'s position, quaternion and variances into the POSE record ``r``
        (``transmit.PoseReport``; its time is :meth:`time_us`); the row's ``OUT_*`` status bits."""
        d = self._odv
        rp, rq, v = r.p, r.q, r.var
        rp[0], rp[1], rp[2] = d[k, OUT_P], d[k, OUT_P + 1], d[k, OUT_P + 2]
        rq[0], rq[1], rq[2], rq[3] = d[k, OUT_Q], d[k, OUT_Q + 1], d[k, OUT_Q + 2], d[k, OUT_Q + 3]
        v[0], v[1], v[2] = d[k, OUT_VAR_P], d[k, OUT_VAR_P + 1], d[k, OUT_VAR_P + 2]
        v[3], v[4], v[5] = d[k, OUT_VAR_O], d[k, OUT_VAR_O + 1], d[k, OUT_VAR_O + 2]
        return int(d[k, OUT_STATUS])

    def _into_report_compiled(self, k: int, r) -> int:
        """:meth:`into_report` on the compiled core (``ext.FusOutput.report``)."""
        return self._ck.report(k, r.p, r.q, r.var)

    def take_report(self, r: PoseReport) -> int:
        """The oldest queued pose into the POSE record ``r`` (``transmit.PoseReport``: its time
        and :meth:`into_report`'s fields) and off the queue (:meth:`pop`, :meth:`time_us`,
        :meth:`into_report` and :meth:`release` in one call); its ``OUT_*`` status bits, or -1
        when none is queued."""
        k = self.out.pop()                     # (the row stays as it is until the next queue)
        if k < 0:
            return -1
        r.t_us = self._otv[k]
        return self.into_report(k, r)

    def _take_report_compiled(self, r: PoseReport) -> int:
        """:meth:`take_report` on the compiled core (``ext.FusOutput.report``)."""
        k = self.out.pop()
        if k < 0:
            return -1
        r.t_us = self._otv[k]
        return self._ck.report(k, r.p, r.q, r.var)

    def pop(self) -> int:
        """Slot of the oldest queued pose, or -1."""
        return self.out.slot(0) if len(self.out) else -1

    def release(self) -> None:
        self.out.pop()


def _quat_into(hd, h, od, slot) -> None:
    """Unit quaternion (w, x, y, z), w >= 0, of the rotation in history row
    ``h`` into the output row ``slot``."""
    r = HIST_R
    w, x, y, z = quat_from_elements(hd[h, r], hd[h, r + 1], hd[h, r + 2], hd[h, r + 3], hd[h, r + 4],
                                    hd[h, r + 5], hd[h, r + 6], hd[h, r + 7], hd[h, r + 8])
    o = OUT_Q
    od[slot, o], od[slot, o + 1], od[slot, o + 2], od[slot, o + 3] = w, x, y, z


def _pushed(ring: KernelRing, k: int, t: int) -> int:
    """Slots ``ring`` pushed since its newest slot was ``k``, at time ``t``: the run from ``k + 1`` to its
    newest slot now; the capacity when it may have pushed that many (slot ``k`` holds a newer time) or
    holds nothing."""
    cap = ring.capacity
    if ring.tv[k] != t or not len(ring):
        return cap
    n = ring.peek(0) - k
    return n + cap if n < 0 else n
