"""The transmit stage: every frame the firmware sends leaves through here.

:class:`Transmitter` owns the frame encoder and the Port's write side. It
builds the one ``POSE`` message shape (:meth:`Transmitter.pose`, with the
covariance diagonal clamped to the f32 range of the wire format), the
``FAULT_EVENT`` reports and the periodic ``HEARTBEAT``, and counts what it
sent. A full or broken link never stops the loop: a failed write is counted
in ``tx_errors``.

With a signer (``signing_key`` in the configuration) the signable messages
(``COIL_PULSE_CMD``, ``CONFIG_SET``) leave signed (MAVLink 2 style,
:mod:`coiltrack.protocol.signing`): the timestamp is the one taken at boot
(``sign_ts0``, 10 us units since 2015) plus the master clock, so it increases
strictly within a run and across restarts of the firmware.
"""
from __future__ import annotations

from coiltrack.protocol import MSG, PROTOCOL_VERSION, SCHEMA_HASH, FrameEncoder, SignedFrameEncoder, Signer
from coiltrack.protocol.framing import _EXTRA as _CRC_EXTRA
from coiltrack.protocol.framing import encode_frame
from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID, ROLE_FIRMWARE, STATE_RUNNING

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.port import Port

_HEARTBEAT = MSG["HEARTBEAT"]
_POSE = MSG["POSE"]
_FAULT = MSG["FAULT_EVENT"]
_WINDOW = MSG["PULSE_WINDOW"]
_FLIP = MSG["MAG_FLIP_CMD"]
_SYNC = MSG["TIME_SYNC"]
_PULSE_CMD = MSG["COIL_PULSE_CMD"]
_SYNC = MSG["TIME_SYNC"]
#: the largest finite f32 (POSE covariance fields): larger variances are sent as this
F32_MAX = 3.0e38


def _f32(v: float) -> float:
    return v if v < F32_MAX else F32_MAX


class PoseReport:
    """One POSE as a tracker fills it, in place (one record per tracker or sensor, made at
    start-up): ``node``, ``t_us`` (master clock), position ``p`` (3, m, source frame), orientation
    quaternion ``q`` (w, x, y, z), the variances ``var`` (position x, y, z in m^2, then
    orientation in rad^2), the ``POSE_*`` bits ``status`` and the quality 0-255 ``quality``
    (``track.quality``; 255 when the tracker does not grade its poses)."""
    __slots__ = ("node", "t_us", "p", "q", "var", "status", "quality")

    def __init__(self, node: int = 0):
        self.node = node
        self.t_us = 0
        self.p = [0.0, 0.0, 0.0]
        self.q = [1.0, 0.0, 0.0, 0.0]
        self.var = [0.0] * 6
        self.status = 0
        self.quality = 255


def fill_pose(r: PoseReport, p, q, P, b: int, o: int) -> None:
    """Position ``p``, quaternion ``q`` (4) and the diagonal variances of the covariance ``P``
    (position block at row ``b``, orientation at ``o``) into the record ``r``."""
    rp, rq, v = r.p, r.q, r.var
    rp[0], rp[1], rp[2] = float(p[0]), float(p[1]), float(p[2])
    rq[0], rq[1], rq[2], rq[3] = q
    v[0], v[1], v[2] = float(P[b, b]), float(P[b + 1, b + 1]), float(P[b + 2, b + 2])
    v[3], v[4], v[5] = float(P[o, o]), float(P[o + 1, o + 1]), float(P[o + 2, o + 2])


class Transmitter:
    """Encoder, write side of the Port and the counters of what was sent."""

    def __init__(self, port: Port, node_id: int, heartbeat_us: int, decoder, signer: Signer | None = None,
                 sign_ts0: int = 0, core=_DEFAULT_CORE):
        self.port = port
        self.node_id = node_id
        self.signer = signer
        self.sign_ts0 = int(sign_ts0)
        self.encoder = SignedFrameEncoder(node_id, signer) if signer is not None else FrameEncoder(node_id)
        self.heartbeat_us = heartbeat_us
        self.next_heartbeat_us = 0
        self.boot_us = 0
        self.now_us = 0
        self._ticked = False    # begin_tick has set boot_us
        self.tx_errors = 0
        self.poses = 0          # POSEs sent with POSE_VALID
        self.fused_poses = 0    # ... of which fused (POSE_FUSED)
        self.decoder = decoder  # the receiver's: the frames it dropped go into the heartbeat
        self._own = PoseReport()  # the record of pose_cov6 and pose_unknown
        self._bind(core)
        self._bind_window(core)

    def send(self, msg) -> None:
        try:
            if self.signer is None:
                self.port.write(self.encoder.encode(msg))
            else:
                self.port.write(self.encoder.encode(msg, self.sign_ts0 + self.now_us // 10))
        except Exception:  # a full or broken link must not stop the loop
            self.tx_errors += 1

    def event(self, code: int, detail: int) -> None:
        self.send(_FAULT(self.node_id, self.now_us, code, detail & 0xFFFFFFFF))

    def time_sync(self, master_time_us: int, seq: int) -> None:
        """Send one ``TIME_SYNC`` (``supervise.timesync.TimeSyncMaster.step``: the master time at
        transmission, the broadcast's sequence number)."""
        self.send(_SYNC(master_time_us, seq))

    def pulse_window(self, node: int, coil: int, pulse_id: int, first_us: int, last_us: int, n_used: int,
                     n_base: int, flags: int) -> None:
        """Send one ``PULSE_WINDOW`` (which samples a window's amplitude used: ``measure.windows``)."""
        self.send(_WINDOW(node, coil, pulse_id, first_us, last_us, n_used, n_base, flags))

    def pulse_window_run(self, send, coil: int, pulse_id: int, c0: int, c1: int) -> bool:
        """A run of channels' PULSE_WINDOWs (channels ``c0 .. c1 - 1`` of a closer's run:
        ``measure.windows.WindowCloser.close_run``) built and written by ``send`` (``ext.WindowFrames``'s,
        bound to the channels: the frames :meth:`pulse_window` sends, in order), numbered with this
        transmitter's sequence and their errors counted as :meth:`_write_numbered` does; False (nothing
        sent: the caller sends each through :meth:`pulse_window`) on the Python core, a signed link,
        or while :meth:`pulse_window` is not this transmitter's own."""
        return False

    def _pulse_window_run_compiled(self, send, coil: int, pulse_id: int, c0: int, c1: int) -> bool:
        if self.pulse_window is not self._pw_own:
            return False
        r = send(self.port.write, self._seq, self.node_id, coil, pulse_id, c0, c1)
        if r is None:
            return False
        self._seq = r & 0xFF
        self.tx_errors += r >> 8
        return True

    def mag_flip(self, node: int, at_us: int, state: int) -> None:
        """Send one ``MAG_FLIP_CMD`` (``supervise.flips``: ``node`` to set/reset ``state`` at ``at_us``)."""
        self.send(_FLIP(node, at_us, state))

    def coil_pulse(self, coil: int, pulse_id: int, current_ma: int, start_us: int, length_us: int) -> None:
        """Send one ``COIL_PULSE_CMD`` (``actuate.schedule.PulseSchedule.command``)."""
        self.send(_PULSE_CMD(coil, pulse_id, current_ma, start_us, length_us))

    def pose(self, r: PoseReport) -> None:
        """Send one POSE (:class:`PoseReport`); variances beyond the f32 range go as :data:`F32_MAX`."""
        p, q, v, status = r.p, r.q, r.var, r.status
        self.send(_POSE(r.node, r.t_us, p[0], p[1], p[2], q[0], q[1], q[2], q[3], _f32(v[0]), _f32(v[1]),
                        _f32(v[2]), _f32(v[3]), _f32(v[4]), _f32(v[5]), status, r.quality))
        self._count_pose(status)

    def _count_pose(self, status: int) -> None:
        """A sent POSE counted: ``poses`` when valid, ``fused_poses`` when fused too."""
        if status & POSE_VALID:
            self.poses += 1
            if status & POSE_FUSED:
                self.fused_poses += 1

    def fused_pose(self, kernel, node: int, status: int, quality: int, range_m: float) -> int:
        """The queued fused poses, oldest first, sent straight from their output rows
        (``estimate.fusion_output.PoseOutput``'s compiled kernel ``kernel``) with ``status`` and
        ``quality``, as :meth:`pose` sends each, and off the queue: 0 when none is left queued; -1
        when the next one needs the reference path (an ``OUT_*`` bit, beyond ``range_m``, a value
        the wire format refuses: left queued), and always (nothing sent) on the Python core or a
        signed link."""
        return -1

    def _fused_pose_compiled(self, kernel, node: int, status: int, quality: int, range_m: float) -> int:
        """:meth:`fused_pose` on the compiled core (``ext.FusOutput.send``: each queued pose's frame,
        ``ct_pose_frame``, numbered from this transmitter's sequence and written through the port in
        one call, which counts the writes that failed); the sequence and the counts as
        :meth:`_write_numbered` and :meth:`_count_pose` keep them. While :meth:`pose` is not this
        transmitter's own (a recorder wraps it) every pose goes through it."""
        if self.pose is not self._pose_own:
            return -1
        r = kernel.send(self._seq, self.node_id, node, status, quality, range_m, self.port.write)
        sent = r >> 32
        if sent:
            self._seq = (self._seq + sent) & 0xFF
            self.tx_errors += (r >> 1) & 0x7FFFFFFF
            if status & POSE_VALID:
                self.poses += sent
                if status & POSE_FUSED:
                    self.fused_poses += sent
        return -(r & 1)

    def pose_cov6(self, node: int, t_us: int, p, q, cov, status: int, quality: int = 255) -> None:
        """:meth:`pose` from a position 3-vector, a quaternion 4-tuple and the
        diagonal of a 6x6 covariance (``cov[i, i]``)."""
        r = self._own
        r.node, r.t_us, r.status, r.quality = node, t_us, status, quality
        r.p[0], r.p[1], r.p[2] = float(p[0]), float(p[1]), float(p[2])
        r.q[0], r.q[1], r.q[2], r.q[3] = q[0], q[1], q[2], q[3]
        v = r.var
        v[0], v[1], v[2] = float(cov[0, 0]), float(cov[1, 1]), float(cov[2, 2])
        v[3], v[4], v[5] = float(cov[3, 3]), float(cov[4, 4]), float(cov[5, 5])
        self.pose(r)

    def _pose_cov6_compiled(self, node: int, t_us: int, p, q, cov, status: int, quality: int = 255) -> None:
        """:meth:`pose_cov6` on the compiled core: the same values into ``ct_pose_frame`` as
        :meth:`pose_cov6` hands :meth:`_pose_compiled` (read as ``float()`` reads them: the same
        bytes); while :meth:`pose` is not
        the one bound at start-up (a recorder wraps it) every pose goes through it."""
        if self.pose is not self._pose_own:
            Transmitter.pose_cov6(self, node, t_us, p, q, cov, status, quality)
            return
        frame = self._pose_frame(self._seq, self.node_id, node, t_us, p[0], p[1], p[2], q[0], q[1], q[2], q[3],
                                 cov[0, 0], cov[1, 1], cov[2, 2], cov[3, 3], cov[4, 4], cov[5, 5], status, quality)
        self._write_numbered(frame)
        self._count_pose(status)

    def pose_built(self, send, node: int, t_us: int, status: int, quality: int) -> bool:
        """A POSE whose frame ``send(write, seq, src, node, t_us, status, quality)`` makes and writes on
        the compiled core (a report's bound kernel: ``ext.ReportChain.send``, the bytes :meth:`pose_cov6`
        sends, numbered from ``seq`` and written through ``write`` as :meth:`_write_numbered` does:
        ``errors << 8 | the next seq``), counted as :meth:`pose_cov6`'s; False (nothing sent: the
        caller sends through :meth:`pose_cov6`) on the Python core, a signed link, or while
        :meth:`pose` is not this transmitter's own."""
        return False

    def _pose_built_compiled(self, send, node: int, t_us: int, status: int, quality: int) -> bool:
        if self.pose is not self._pose_own:
            return False
        r = send(self.port.write, self._seq, self.node_id, node, t_us, status, quality)
        self._seq = r & 0xFF
        self.tx_errors += r >> 8
        self._count_pose(status)
        return True

    def pose_unknown(self, node: int, t_us: int, p, q, status: int) -> None:
        """A POSE whose covariance is unknown (every variance at the f32 maximum, quality 0)."""
        r = self._own
        r.node, r.t_us, r.status, r.quality = node, t_us, status, 0
        r.p[0], r.p[1], r.p[2] = float(p[0]), float(p[1]), float(p[2])
        r.q[0], r.q[1], r.q[2], r.q[3] = q[0], q[1], q[2], q[3]
        v = r.var
        v[0] = v[1] = v[2] = v[3] = v[4] = v[5] = F32_MAX
        self.pose(r)

    def begin_tick(self, now_us: int) -> None:
        """The tick's time (us, master clock): what is sent in the tick is stamped with it (events,
        signatures); the first tick's is the boot time (``boot_us``)."""
        if not self._ticked:
            self._ticked = True
            self.boot_us = now_us
        self.now_us = now_us

    def _bind(self, core) -> None:
        """The numeric core of :meth:`pose` (``coiltrack.firmware.core``), bound once: on the
        compiled core an unsigned link's POSE frame is built by ``core/src/frame.c``
        (``ct_pose_frame``: the same bytes as ``encode_frame``), and this transmitter numbers its
        frames itself (``seq``, as ``FrameEncoder`` does) so POSEs and the other messages share
        one sequence. A signed link keeps the Python encoder."""
        ext = core.ext
        self.core = "python"
        self._seq = 0
        if ext is None or self.signer is not None:
            return
        assert (ext.POSE_ID, ext.POSE_PAYLOAD, ext.POSE_CRC_EXTRA) == (_POSE.ID, 64, _CRC_EXTRA[_POSE.ID][0])
        self._pose_frame = ext.pose_frame
        self.send = self._send_numbered
        self.pose = self._pose_own = self._pose_compiled
        self.fused_pose = self._fused_pose_compiled
        self.pose_cov6 = self._pose_cov6_compiled    # the frame from the arguments, no record between
        self.pose_built = self._pose_built_compiled
        self.core = "compiled"

    def _bind_window(self, core) -> None:
        """:meth:`pulse_window` on the compiled core (as :meth:`_bind` binds :meth:`pose`): the frame
        built by ``core/src/multi.c`` (``ct_window_frame``: the same bytes as ``encode_frame``),
        numbered with this transmitter's sequence. A signed link or the Python core keeps
        :meth:`send`."""
        if self.core != "compiled":
            return
        ext = core.ext
        assert (ext.WINDOW_ID, ext.WINDOW_PAYLOAD, ext.WINDOW_CRC_EXTRA) == (_WINDOW.ID, 23, _CRC_EXTRA[_WINDOW.ID][0])
        self._window_frame = ext.window_frame
        self.pulse_window = self._pw_own = self._pulse_window_compiled
        self.pulse_window_run = self._pulse_window_run_compiled
        assert (ext.FLIP_ID, ext.FLIP_PAYLOAD, ext.FLIP_CRC_EXTRA) == (_FLIP.ID, 10, _CRC_EXTRA[_FLIP.ID][0])
        self._flip_frame = ext.flip_frame
        self.mag_flip = self._mag_flip_compiled
        assert (ext.PCMD_ID, ext.PCMD_PAYLOAD, ext.PCMD_CRC_EXTRA) == (_PULSE_CMD.ID, 17, _CRC_EXTRA[_PULSE_CMD.ID][0])
        self._pulse_cmd_frame = ext.pulse_cmd_frame
        self.coil_pulse = self._coil_pulse_compiled
        self._bind_periodic(ext)

    def _bind_periodic(self, ext) -> None:
        """The periodic frames on the compiled core (``core/src/periodic.c``: the same bytes as
        ``encode_frame``): :meth:`time_sync`, the heartbeat of :meth:`step` and :meth:`event`, each
        one call numbered with this transmitter's sequence. (A cold ``encode_frame`` took 20-50 us
        of CPU in a tick: the supervisor's TIME_SYNC, four a burst and the periodic ones, set a class
        of idle ticks at roetenberg-fusion's p99.9.)"""
        for name, m, size in (("SYNC", _SYNC, 10), ("HEARTBEAT", _HEARTBEAT, 10), ("EVENT", _FAULT, 15)):
            assert (getattr(ext, name + "_ID"), getattr(ext, name + "_PAYLOAD"), getattr(ext, name + "_CRC_EXTRA")) == (
                m.ID, size, _CRC_EXTRA[m.ID][0])
        self._sync_frame = ext.sync_frame
        self._heartbeat_frame = ext.heartbeat_frame
        self._event_frame = ext.event_frame
        self.time_sync = self._time_sync_compiled
        self.event = self._event_compiled
        self.step = self._step_compiled

    def _time_sync_compiled(self, master_time_us: int, seq: int) -> None:
        """:meth:`time_sync` on the compiled core (``ct_sync_frame``)."""
        self._write_numbered(self._sync_frame(self._seq, self.node_id, master_time_us, seq))

    def _event_compiled(self, code: int, detail: int) -> None:
        """:meth:`event` on the compiled core (``ct_event_frame``)."""
        self._write_numbered(self._event_frame(self._seq, self.node_id, self.node_id, self.now_us, code,
                                               detail & 0xFFFFFFFF))

    def _step_compiled(self, now_us: int) -> None:
        """:meth:`step` on the compiled core (``ct_heartbeat_frame``)."""
        if now_us >= self.next_heartbeat_us:
            self._write_numbered(self._heartbeat_frame(self._seq, self.node_id, self.node_id, ROLE_FIRMWARE,
                                                       STATE_RUNNING, PROTOCOL_VERSION, SCHEMA_HASH,
                                                       min(self.decoder.frames_bad, 0xFFFF)))
            self.next_heartbeat_us = now_us + self.heartbeat_us

    def _coil_pulse_compiled(self, coil: int, pulse_id: int, current_ma: int, start_us: int, length_us: int) -> None:
        """:meth:`coil_pulse` on the compiled core (``ct_pulse_cmd_frame``, ``core/src/sc_policy.c``: the same
        bytes as ``encode_frame``), numbered with this transmitter's sequence."""
        self._write_numbered(self._pulse_cmd_frame(self._seq, self.node_id, coil, pulse_id, current_ma, start_us,
                                                   length_us))

    def _mag_flip_compiled(self, node: int, at_us: int, state: int) -> None:
        """:meth:`mag_flip` on the compiled core (``ct_flip_frame``, ``core/src/multi.c``: the same bytes
        as ``encode_frame``), numbered with this transmitter's sequence."""
        frame = self._flip_frame(self._seq, self.node_id, node, at_us, state)
        self._write_numbered(frame)

    def _pulse_window_compiled(self, node: int, coil: int, pulse_id: int, first_us: int, last_us: int, n_used: int,
                               n_base: int, flags: int) -> None:
        """:meth:`pulse_window` on the compiled core (a field out of its range: a tx error, as
        ``struct.pack``'s refusal in :meth:`_send_numbered`)."""
        frame = self._window_frame(self._seq, self.node_id, node, coil, pulse_id, first_us, last_us, n_used, n_base,
                                   flags)
        self._write_numbered(frame)

    def _write_numbered(self, frame) -> None:
        """A frame built on the compiled core written with this transmitter's sequence; ``None`` (a
        value the wire format refuses, as ``struct.pack``'s error in :meth:`_send_numbered`): a tx error."""
        if frame is None:
            self.tx_errors += 1
            return
        self._seq = (self._seq + 1) & 0xFF
        try:
            self.port.write(frame)
        except Exception:  # a full or broken link must not stop the loop
            self.tx_errors += 1

    def _send_numbered(self, msg) -> None:
        """:meth:`send` on the compiled core: ``encode_frame`` with this transmitter's sequence."""
        try:
            frame = encode_frame(msg, self._seq, self.node_id)
            self._seq = (self._seq + 1) & 0xFF
            self.port.write(frame)
        except Exception:  # a full or broken link must not stop the loop
            self.tx_errors += 1

    def _pose_compiled(self, r: PoseReport) -> None:
        """:meth:`pose` on the compiled core (``ct_pose_frame`` clamps the variances as ``_f32``)."""
        p, q, v, status = r.p, r.q, r.var, r.status
        frame = self._pose_frame(self._seq, self.node_id, r.node, r.t_us, p[0], p[1], p[2], q[0], q[1], q[2], q[3],
                                 v[0], v[1], v[2], v[3], v[4], v[5], status, r.quality)
        self._write_numbered(frame)
        self._count_pose(status)

    def step(self, now_us: int) -> None:
        """The periodic HEARTBEAT."""
        if now_us >= self.next_heartbeat_us:
            self.send(_HEARTBEAT(self.node_id, ROLE_FIRMWARE, STATE_RUNNING, PROTOCOL_VERSION, SCHEMA_HASH,
                                 min(self.decoder.frames_bad, 0xFFFF)))
            self.next_heartbeat_us = now_us + self.heartbeat_us
