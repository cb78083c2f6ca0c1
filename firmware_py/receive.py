"""The receive stage: drain the Port, decode frames (a corrupt frame is
counted by the decoder and skipped) and route each message by its schema id:
magnetometer samples into the sensor channels' rings, IMU samples and the
source module's samples to the tracker, coil status to the pulse schedule and
the tracker, heartbeats to the schema check. The supervisor sees every
message first.

The compact samples of protocol v2 become the full ones here, once, for
every link (serial, CAN, in-process), so everything downstream has one
input shape:

* ``MAG_PACKED`` -> a MAG_SAMPLE record: ``t_us`` restored from the stamp's
  14 bits against the tick's clock (:func:`coiltrack.protocol.schema.unwrap_stamp`:
  the one time in ``(now + 16.4 ms - 131.072 ms, now + 16.4 ms]``), ``flip``
  bit 0 the set/reset state, bit 1 saturated;
* an ``IMU_DELTA`` pair (delta angle, then delta velocity, one stamp; each
  the node's running sum wrapped to 16 bits) -> its difference from the
  node's previous pair, ``dtheta`` and ``dv`` over ``T``, the time between
  the two stamps, as ``n = round(T imu_rate_hz)`` IMU_SAMPLE records, each
  the mean rate ``dtheta / T`` and mean specific force ``dv / T`` (in count
  units of GYR_LSB / ACC_LSB, as floats, so nothing is re-quantised), at the
  middles of ``n`` equal steps of ``(t_end - T, t_end]``. A lost pair makes
  ``T`` two intervals and costs only the motion within them; the first pair
  of a node, and one more than ``3.5 / imu_delta_rate_hz`` after its
  predecessor, only anchor the sums. The one strapdown and the filters keep
  their rate ``imu_rate_hz`` and their per-sample noise: ``n`` equal samples
  carry the interval's rotation and velocity change exactly, and the
  integrated noise over the interval, ``sigma T / sqrt(n)``, is what ``n``
  independent samples of noise ``sigma`` give. What the interval's mean
  loses is the motion within it (100 ms at 10 Hz).

Saturation: an IMU sample with an axis at the clip code
(``IMU_CLIP_COUNTS``: the sensor saturated, the value is its full scale, not
the motion) and an ``IMU_DELTA`` pair with the saturated stamp bit on either
frame are not measurements: they go to the supervisor (the node was heard)
but not to the channels or the tracker, and are counted (``imu_saturated``:
samples, the steps of a pair included; ``imu_saturated_pairs``). The pair's
sums still advance the node's anchor, so the next pair's difference covers
its own interval only. Downstream the sample is missing: the strapdown
bridges a short gap between its neighbours' values and restarts from the
magnetic solution past ``imu_timeout_us`` (``estimate.magnetic_inertial``:
the IMU stream broke off).

Calibration: a node with a :class:`coiltrack.firmware.calibration.SensorCalibration`
has its magnetometer ellipsoid and its IMU model inverted here, the one place
every sample enters (before the rings, the pulse windows and the one
strapdown): the stages downstream receive a preallocated view of the message
whose readings are the corrected ones, in the message's own units (counts).
The supervisor sees the raw message (saturation is a property of the
reading).

The records are allocated once (one of each) and reused: every consumer
copies the values it keeps.

Decode: on the Python core the protocol's ``FrameDecoder`` (the reference); on
the compiled core :class:`coiltrack.firmware.rxdecode.CompiledFrameDecoder`
(``core/src/rxdecode.c``: the same frames, counters and resynchronisation),
whose rows already hold the restored MAG_PACKED and the IMU_SAMPLE's clip
check; the routing is the same for both (:meth:`Receiver._route`).

Budget: at most ``frames_per_tick`` frames (``[receive] rx_frames_per_tick``)
are decoded and routed in one tick; the bytes of the others stay in the
receive queue (one bytearray, at most ``queue_bytes``) for the next ticks,
in order, counted in ``rx_deferred``. Sixteen sensors' MAG_PACKED of one
instant (16 frames) thus take two ticks of 8 instead of one of 16; a
sample's time is its stamp, so a tick's delay moves no sample. A queue
that would exceed ``queue_bytes`` is dropped (``rx_queue_overflows``) and
the decoder resynchronises at the next 0x00.
"""
from __future__ import annotations

import numpy as np

from coiltrack.protocol import MSG, PROTOCOL_VERSION, SCHEMA_HASH
from coiltrack.protocol.schema import (ACC_LSB, DANG_LSB_RAD, DVEL_LSB_MPS, EVT_SCHEMA_MISMATCH, GYR_LSB,
                                       IMU_CLIP_COUNTS, MAG_LSB_T, STAMP_DVEL, STAMP_FLIP, STAMP_LEAD_US, STAMP_LSB_US,
                                       STAMP_MASK, STAMP_SATURATED, unwrap_stamp)

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.measure.windows import SensorChannel
from coiltrack.firmware.rxdecode import RXK_IMU as _RXK_IMU, RXK_MAG as _RXK_MAG, RXK_MAG_PACKED as _RXK_MAG_PACKED
from coiltrack.firmware.rxdecode import RXR_CLIP as _RXR_CLIP, RXR_KIND as _RXR_KIND, CompiledFrameDecoder
from coiltrack.firmware.rxdecode import RX_NEW as _NEW, RX_OVER_LIMIT as _OVER, RX_RESUME as _RESUME, RX_TAKEN as _TAKEN

_MAG = MSG["MAG_SAMPLE"].ID
_IMU = MSG["IMU_SAMPLE"].ID
_MAG_PACKED = MSG["MAG_PACKED"].ID
_IMU_DELTA = MSG["IMU_DELTA"].ID
_COIL_STATUS = MSG["COIL_STATUS"].ID
_HEARTBEAT = MSG["HEARTBEAT"].ID
_SYNC_REPLY = MSG["TIME_SYNC_REPLY"].ID
_INV_MAG = 1.0 / MAG_LSB_T
_INV_ACC = 1.0 / ACC_LSB
_INV_GYR = 1.0 / GYR_LSB
# the receiver's IMU counters and the interval start, int64 slots of one array that the compiled
# decode writes too (core/src/imu.c CT_DIO_*)
_T0, _UNPAIRED, _ANCHORS, _SATURATED, _SAT_PAIRS, _DELTAS, _NIO = range(7)
# the compiled route's int64 state (core/include/ct_rxdecode.h CT_RXS_*): its rows, the next row, the
# MAG_PACKED count (:attr:`Receiver.packed_mag`, counted there on either core) and whether the
# supervisor has seen the IMU_SAMPLE handed back
_RS_PACKED, _RS_SEEN, _RS_N = 2, 3, 4


class MagRecord:
    """A MAG_SAMPLE's fields (``node``, ``t_us`` us, ``x, y, z`` counts of MAG_LSB_T, ``flip``): a
    restored MAG_PACKED, or a sample with its calibration applied (counts as floats)."""
    __slots__ = ("node", "t_us", "x", "y", "z", "flip")
    ID = _MAG

    def __init__(self):
        self.node = self.t_us = self.x = self.y = self.z = self.flip = 0


class ImuRecord:
    """An IMU_SAMPLE's fields (``node``, ``t_us`` us, ``ax..az`` in ACC_LSB, ``gx..gz`` in GYR_LSB;
    floats when made from an IMU_DELTA pair)."""
    __slots__ = ("node", "t_us", "ax", "ay", "az", "gx", "gy", "gz")
    ID = _IMU

    def __init__(self):
        self.node = self.t_us = 0
        self.ax = self.ay = self.az = self.gx = self.gy = self.gz = 0.0


class _DeltaState:
    """One node's pending delta-angle sums, its previous pair's sums and stamp time."""
    __slots__ = ("stamp", "x", "y", "z", "pending", "sat", "last_end", "ax", "ay", "az", "vx", "vy", "vz")

    def __init__(self):
        self.stamp = self.x = self.y = self.z = 0
        self.pending = False
        self.sat = False
        self.last_end = None
        self.ax = self.ay = self.az = self.vx = self.vy = self.vz = 0


def _clipped(msg) -> bool:
    """An IMU_SAMPLE with an axis at the clip code (``IMU_CLIP_COUNTS`` or beyond: -32768)."""
    c = IMU_CLIP_COUNTS
    return (msg.ax >= c or msg.ax <= -c or msg.ay >= c or msg.ay <= -c or msg.az >= c or msg.az <= -c
            or msg.gx >= c or msg.gx <= -c or msg.gy >= c or msg.gy <= -c or msg.gz >= c or msg.gz <= -c)


def _d16(a: int, b: int) -> int:
    """``a - b`` of two wrapped 16-bit sums."""
    return ((a - b + 32768) & 0xFFFF) - 32768


def _io_counter(k: int, doc: str):
    return property(lambda self: int(self._io[k]), doc=doc)


def _pushes_here(ch) -> bool:
    """Whether the compiled route may push ``ch``'s samples itself: a plain
    :class:`coiltrack.firmware.measure.windows.SensorChannel` (its ``push`` is ``SampleRing.push_kernel``'s)."""
    return type(ch) is SensorChannel


class Receiver:
    """The receive stage (module docstring); ``core``: the numeric core of the IMU decode
    (``coiltrack.firmware.core.Core``, chosen at composition)."""

    imu_deltas = _io_counter(_DELTAS, "IMU_DELTA pairs turned into IMU steps")
    imu_delta_unpaired = _io_counter(_UNPAIRED, "IMU_DELTA frames without their pair (dropped)")
    imu_delta_anchors = _io_counter(_ANCHORS, "IMU_DELTA pairs that only anchor the sums")
    imu_saturated = _io_counter(_SATURATED, "IMU samples not used: an axis clipped (steps of a pair included)")
    imu_saturated_pairs = _io_counter(_SAT_PAIRS, "IMU_DELTA pairs with the saturated bit")
    packed_mag = property(lambda self: int(self._rsv[_RS_PACKED]), doc="MAG_PACKED samples restored")

    def __init__(self, port, decoder, channels, schedule, tracker, supervisor, tx, other=None,
                 imu_interval_us: float = 1e5, imu_step_us: float = 1e4, calibration=None,
                 frames_per_tick: int = 0, queue_bytes: int = 16384, core=_DEFAULT_CORE):
        self.port = port
        self.decoder = decoder
        self.channels = {ch.node: ch for ch in channels}
        self.schedule = schedule
        self.tracker = tracker
        self.supervisor = supervisor
        self.tx = tx
        self.schema_mismatches = 0
        self.peer_hashes: dict[int, int] = {}
        self.imu_received = 0
        self.other = other            # the pipeline's handler of the messages routed nowhere else
        cal = calibration or {}
        # node -> SensorCalibration, for the nodes whose magnetometer / IMU is calibrated
        self.mag_cal = {n: c for n, c in cal.items() if c.has_mag}
        self.imu_cal = {n: c for n, c in cal.items() if c.has_imu}
        self._magv = MagRecord()              # a sample with its calibration applied
        self._imuv = ImuRecord()
        self.imu_interval_us = float(imu_interval_us)   # nominal IMU_DELTA interval (1 / imu_delta_rate_hz)
        self.imu_step_us = float(imu_step_us)           # the filters' IMU step (1 / imu_rate_hz)
        self._mag = MagRecord()
        self._imu = ImuRecord()
        self._imus = ImuRecord()                # a received IMU_SAMPLE (compiled frame decode)
        self._deltas: dict[int, _DeltaState] = {}
        self._step = 0.0
        self._rs = np.zeros(_RS_N, dtype=np.int64)     # the compiled route's state, the packed count
        self._rsv = memoryview(self._rs)
        self._io = np.zeros(_NIO, dtype=np.int64)      # counters and the interval start (properties)
        self._iov = memoryview(self._io)
        self.frames_per_tick = int(frames_per_tick)
        self.queue_bytes = int(queue_bytes)
        self._queue = bytearray()
        self.deferred = 0               # frames left queued at the end of a tick, summed over ticks
        self.queue_overflows = 0
        self._clipped = _clipped
        self._bind(core)
        self._sup_mag = self._sup_reply = None
        if isinstance(decoder, CompiledFrameDecoder):
            self.step = self._step_rows
            # the supervisor's MAG_SAMPLE work in one compiled call (its rare cases: on_message)
            self._sup_mag = supervisor.mag_kernel(core, decoder.payloads) if hasattr(supervisor, "mag_kernel") else None
            # and a time-sync reply, for a pipeline that takes no other message
            if self._sup_mag is not None and other is None:
                self._sup_reply = supervisor.reply_kernel()
            self._rx_step = self._bind_route(decoder)
            # what _rows_from reads, fixed from here: the decoder, its rows, the supervisor's entry and
            # kernels; a magnetometer sample goes straight to its channel (:meth:`_mag_in` without the
            # call) when no node's magnetometer is calibrated (``chans``), an IMU sample likewise
            # (:meth:`_on_imu`'s steps) when no node's IMU is (``ichans``: the channels that keep
            # its rates, the others' ``push_imu`` does nothing)
            ichans = {n: ch for n, ch in self.channels.items() if not (_pushes_here(ch) and ch.gyro is None)}
            self._rows_b = (decoder, decoder.rows, decoder.width, supervisor.on_message, self._sup_mag,
                            self._sup_reply, None if self.mag_cal else self.channels, None if self.imu_cal else ichans)

    def _bind_route(self, decoder):
        """The compiled decode and routing of a tick's data (:meth:`CompiledFrameDecoder.route_kernel`,
        ``ct_rx_step``): the magnetometer rows of the nodes whose channel it pushes into
        (:func:`_pushes_here`) routed in C as :meth:`_rows_from` routes them (the supervisor's
        ``mag_kernel``, the packed count, the channel's push), when the supervisor has that kernel
        and no node's magnetometer is calibrated; every other row handed to :meth:`_rows_from`, in
        order, an IMU_SAMPLE with the supervisor's part done where the kernel could (``ct_sup_imu``).
        Its ``step`` bound once."""
        nodes = np.full(256, -1, dtype=np.int64)
        pushes = []
        sup = getattr(self._sup_mag, "__self__", None)
        if sup is not None and not self.mag_cal:
            for node, ch in self.channels.items():
                if 0 <= node < 256 and _pushes_here(ch):
                    nodes[node] = len(pushes)
                    pushes.append(ch.ring.push_kernel(decoder.ext, ch.cnt))
        return decoder.route_kernel(sup, nodes, tuple(pushes), self._rs, MAG_LSB_T, self.frames_per_tick).step

    def _bind(self, core) -> None:
        """The IMU decode on the compiled core (``core/src/imu.c``: ``ct_imu_clipped``,
        ``ct_imu_delta``, the same operations as :func:`_clipped` and :meth:`_delta`), bound once:
        every node's pair state in one start-up table (a row per node id)."""
        self.core = "python"
        ext = core.ext
        if ext is None:
            return
        assert (ext.DIO_N, ext.IMU_CLIP, ext.STAMP_LEAD_US, ext.STAMP_DVEL, ext.STAMP_SATURATED, ext.STAMP_MASK,
                ext.STAMP_LSB_US) == (_NIO, IMU_CLIP_COUNTS, STAMP_LEAD_US, STAMP_DVEL, STAMP_SATURATED, STAMP_MASK,
                                      STAMP_LSB_US)
        self._dst = np.zeros((256, ext.DELTA_NST), dtype=np.int64)
        self._dout = np.zeros(7)
        self._doutv = memoryview(self._dout)
        self._ck = ext.ImuDelta(self._dst, self._io, self._dout, self.imu_interval_us, self.imu_step_us)
        self._clipped = ext.imu_clipped
        self._delta = self._delta_compiled
        self.core = "compiled"

    def _take(self, data) -> bytes:
        """The bytes of at most ``frames_per_tick`` frames: from the queue, then ``data`` (the
        port's read)."""
        k = self.frames_per_tick
        q = self._queue
        if not k:
            return data
        if not q:
            if not data:
                return b""
            # the common case: no backlog and fewer than k frames arrived (one count, in C)
            if data.count(b"\x00") < k:
                return data
            end = -1
            for _ in range(k):
                end = data.find(b"\x00", end + 1)
                if end < 0:
                    return data
            if end == len(data) - 1:
                return data
            q += data[end + 1:]
            self._count_left(q)
            return data[:end + 1]
        if data:
            q += data
            if len(q) > self.queue_bytes:
                self.queue_overflows += 1
                q.clear()
                return b""
        end = -1
        for _ in range(k):
            e = q.find(b"\x00", end + 1)
            if e < 0:
                break
            end = e
        if end < 0:
            return b""
        out = bytes(q[:end + 1])
        del q[:end + 1]
        self._count_left(q)
        return out

    def _count_left(self, q) -> None:
        self.deferred += q.count(b"\x00")

    def step(self, now_us: int) -> None:
        data = self.port.read()
        if not data and not self._queue:         # nothing received, nothing queued
            return
        data = self._take(data)
        if not data:
            return
        for msg in self.decoder.feed(data):
            self._route(msg, now_us)

    def _step_rows(self, now_us: int) -> None:
        """:meth:`step` on the compiled frame decode (:class:`coiltrack.firmware.rxdecode.CompiledFrameDecoder`,
        bound at construction): the same messages routed in the same order; the magnetometer rows
        the compiled route takes (:meth:`_bind_route`) in its one call, the others by :meth:`_rows_from`;
        a tick's worth of frames or more (the route's answer ``RX_OVER_LIMIT``) or a backlog through
        :meth:`_take`."""
        data = self.port.read()
        if self._queue:
            data = self._take(data)              # a backlog
            if not data:
                return
            k = self._rx_step(data, _TAKEN, now_us)
        elif not data:
            return
        else:
            k = self._rx_step(data, _NEW, now_us)
            if k == _OVER:                       # a tick's worth of frames or more
                data = self._take(data)
                k = self._rx_step(data, _TAKEN, now_us)
        if k >= 0:
            self._rows_from(k, data, now_us)

    def _rows_from(self, k: int, data, now_us: int) -> None:
        """Row ``k`` of the decoder's rows and each next one the compiled route hands back (until
        -1): the sample messages (MAG_PACKED already restored, MAG_SAMPLE, IMU_SAMPLE with its
        clipped-axis check) read from the rows into the stage's records, the others unpacked by
        protocol.codec."""
        route = self._rx_step
        rs = self._rsv
        dec, q, w, seen, smag, sreply, chans, ichans = self._rows_b
        r = self._mag
        while k >= 0:
            b = k * w
            kind = q[b + _RXR_KIND]
            if kind == _RXK_MAG_PACKED or kind == _RXK_MAG:
                r.node, r.t_us, r.x, r.y, r.z, r.flip = q[b + 1], q[b + 2], q[b + 3], q[b + 4], q[b + 5], q[b + 6]
                if kind == _RXK_MAG_PACKED:
                    rs[_RS_PACKED] += 1
                if smag is None or smag(r.node, r.t_us, r.x, r.y, r.z, r.flip, now_us):
                    seen(r, now_us)
                ch = None if chans is None else chans.get(r.node)
                if ch is not None:
                    ch.push(r, MAG_LSB_T)
                else:
                    self._mag_in(r)
            elif kind == _RXK_IMU:
                ri = self._imus
                ri.node, ri.t_us, ri.ax, ri.ay, ri.az = q[b + 1], q[b + 2], q[b + 3], q[b + 4], q[b + 5]
                ri.gx, ri.gy, ri.gz = q[b + 6], q[b + 7], q[b + 8]
                if not rs[_RS_SEEN]:
                    seen(ri, now_us)
                if q[b + _RXR_CLIP]:
                    self._imu_in(ri, True, now_us)
                elif ichans is None:
                    self._on_imu(ri, now_us)
                else:
                    self.imu_received += 1
                    ch = ichans.get(ri.node)
                    if ch is not None:
                        ch.push_imu(ri)
                    self.tracker.on_imu(ri, now_us)
            elif sreply is None or q[b] != _SYNC_REPLY or sreply(q[b + 1], now_us):
                self._route(dec.raw_message(k), now_us)
            k = route(data, _RESUME, now_us)

    def _route(self, msg, now_us: int) -> None:
        """One decoded message to its stage (module docstring), the supervisor first."""
        mid = msg.ID
        if mid == _MAG_PACKED:
            msg = self._unpack_mag(msg, now_us)
            mid = _MAG
        elif mid == _IMU_DELTA:
            n = self._delta(msg, now_us)
            if n:
                self._push_steps(n, now_us)
            return
        self.supervisor.on_message(msg, now_us)
        if mid == _MAG:
            self._mag_in(msg)
        elif mid == _IMU:
            self._imu_in(msg, self._clipped(msg), now_us)
        elif mid == _COIL_STATUS:
            self.schedule.on_status(msg)
            self.tracker.on_coil_status(msg)
        elif mid == _HEARTBEAT:
            self._on_heartbeat(msg)
        elif self.other is not None:
            self.other(msg, now_us)

    def _mag_in(self, msg) -> None:
        """A magnetometer sample (the supervisor has seen it): calibrated, to its sensor's
        channel, or to the tracker (a node that is not a tracked sensor: the source's module)."""
        c = self.mag_cal.get(msg.node) if self.mag_cal else None
        if c is not None:
            msg = self._correct_mag(msg, c)
        ch = self.channels.get(msg.node)
        if ch is not None:
            ch.push(msg, MAG_LSB_T)
        else:
            self.tracker.on_mag(msg, MAG_LSB_T)

    def _imu_in(self, msg, clipped, now_us: int) -> None:
        """A received IMU sample: ``clipped`` (an axis at the clip code) is the sensor's full
        scale, not the motion: not used, counted; else to the channel and the tracker."""
        if clipped:
            self._iov[_SATURATED] += 1
            self.supervisor.on_imu_saturated(msg.node, now_us)
        else:
            self._on_imu(msg, now_us)

    def _unpack_mag(self, msg, now_us: int) -> MagRecord:
        r = self._mag
        s = msg.stamp
        r.node, r.x, r.y, r.z = msg.node, msg.x, msg.y, msg.z
        r.t_us = unwrap_stamp(s & STAMP_MASK, now_us)
        r.flip = (1 if s & STAMP_FLIP else 0) | (2 if s & STAMP_SATURATED else 0)
        self._rsv[_RS_PACKED] += 1
        return r

    def _push_steps(self, n: int, now_us: int) -> None:
        """The ``n`` steps of a completed interval, through the supervisor to the tracker."""
        r = self._imu
        t0, step = self._iov[_T0], self._step
        sup = self.supervisor
        for i in range(n):
            r.t_us = t0 + int(round((i + 0.5) * step))
            sup.on_message(r, now_us)
            self._on_imu(r, now_us)

    def _on_imu(self, msg, now_us: int) -> None:
        """One IMU sample (received, or a step of a delta pair): calibrated, to the sensor's
        channel (its gyroscope turns the pulse windows) and to the tracker."""
        self.imu_received += 1
        c = self.imu_cal.get(msg.node) if self.imu_cal else None
        if c is not None:
            msg = self._correct_imu(msg, c)
        ch = self.channels.get(msg.node)
        if ch is not None:
            ch.push_imu(msg)
        self.tracker.on_imu(msg, now_us)

    def _delta(self, msg, now_us: int) -> int:
        """The number of IMU steps of a completed pair (the record holds their values), else 0
        (the delta angle waits for its delta velocity; a delta velocity without its angle is
        counted and dropped)."""
        st = self._deltas.get(msg.node)
        if st is None:
            st = self._deltas[msg.node] = _DeltaState()
        s = msg.stamp
        io = self._iov
        if not s & STAMP_DVEL:
            if st.pending:
                io[_UNPAIRED] += 1
            st.stamp, st.x, st.y, st.z, st.pending = s & STAMP_MASK, msg.x, msg.y, msg.z, True
            st.sat = bool(s & STAMP_SATURATED)
            return 0
        if not st.pending or st.stamp != s & STAMP_MASK:
            io[_UNPAIRED] += 1
            st.pending = False
            return 0
        st.pending = False
        t_end = unwrap_stamp(st.stamp, now_us)
        last = st.last_end
        dax, day, daz = _d16(st.x, st.ax), _d16(st.y, st.ay), _d16(st.z, st.az)
        dvx, dvy, dvz = _d16(msg.x, st.vx), _d16(msg.y, st.vy), _d16(msg.z, st.vz)
        st.last_end = t_end
        st.ax, st.ay, st.az, st.vx, st.vy, st.vz = st.x, st.y, st.z, msg.x, msg.y, msg.z
        if last is None or not 0 < t_end - last <= 3.5 * self.imu_interval_us:
            io[_ANCHORS] += 1
            return 0
        T = float(t_end - last)
        n = max(1, int(round(T / self.imu_step_us)))
        if st.sat or s & STAMP_SATURATED:
            # a sample of the interval clipped: the pair's means are not the motion (the sums
            # above still anchor the next pair)
            io[_SAT_PAIRS] += 1
            io[_SATURATED] += n
            self.supervisor.on_imu_saturated(msg.node, now_us)
            return 0
        r = self._imu
        r.node = msg.node
        io[_T0] = t_end - int(round(T))
        self._step = T / n
        ka = DANG_LSB_RAD / (T * 1e-6 * GYR_LSB)       # delta-angle counts -> rate counts
        kv = DVEL_LSB_MPS / (T * 1e-6 * ACC_LSB)       # delta-velocity counts -> specific-force counts
        r.gx, r.gy, r.gz = dax * ka, day * ka, daz * ka
        r.ax, r.ay, r.az = dvx * kv, dvy * kv, dvz * kv
        io[_DELTAS] += 1
        return n

    def _delta_compiled(self, msg, now_us: int) -> int:
        """:meth:`_delta` on the compiled core (``ct_imu_delta``: the node's row of the table,
        the counters and the interval start in ``_io``, the step and the means in ``_dout``)."""
        sat = self._iov[_SAT_PAIRS]
        n = self._ck.feed(msg, now_us)
        if self._iov[_SAT_PAIRS] != sat:                 # a pair with the saturated bit: not used
            self.supervisor.on_imu_saturated(msg.node, now_us)
        if n:
            o = self._doutv
            r = self._imu
            r.node = msg.node
            self._step = o[6]
            r.gx, r.gy, r.gz, r.ax, r.ay, r.az = o[0], o[1], o[2], o[3], o[4], o[5]
        return n

    def _correct_mag(self, msg, c):
        """The sample with its ellipsoid inverted (calibration ``mag_soft``, ``mag_hard_t``)."""
        v = self._magv
        x, y, z = c.correct_mag(msg.x * MAG_LSB_T, msg.y * MAG_LSB_T, msg.z * MAG_LSB_T)
        v.node, v.t_us, v.flip = msg.node, msg.t_us, msg.flip
        v.x, v.y, v.z = x * _INV_MAG, y * _INV_MAG, z * _INV_MAG
        return v

    def _correct_imu(self, msg, c):
        """The sample with the IMU model inverted and rotated into the magnetometer's frame."""
        v = self._imuv
        fx, fy, fz, wx, wy, wz = c.correct_imu(msg.ax * ACC_LSB, msg.ay * ACC_LSB, msg.az * ACC_LSB,
                                               msg.gx * GYR_LSB, msg.gy * GYR_LSB, msg.gz * GYR_LSB)
        v.node, v.t_us = msg.node, msg.t_us
        v.ax, v.ay, v.az = fx * _INV_ACC, fy * _INV_ACC, fz * _INV_ACC
        v.gx, v.gy, v.gz = wx * _INV_GYR, wy * _INV_GYR, wz * _INV_GYR
        return v

    def _on_heartbeat(self, msg) -> None:
        self.peer_hashes[msg.node] = msg.schema_hash
        if msg.schema_hash != SCHEMA_HASH or msg.proto_version != PROTOCOL_VERSION:
            self.schema_mismatches += 1
            self.tx.event(EVT_SCHEMA_MISMATCH, msg.node)

    def counters(self) -> dict:
        d = {"schema_mismatches": self.schema_mismatches, "rx_mag_packed": self.packed_mag,
             "rx_imu_deltas": self.imu_deltas, "rx_imu_delta_unpaired": self.imu_delta_unpaired,
             "rx_imu_delta_anchors": self.imu_delta_anchors, "rx_deferred": self.deferred,
             "imu_saturated": self.imu_saturated, "imu_saturated_pairs": self.imu_saturated_pairs,
             "rx_queue_overflows": self.queue_overflows}
        d.update({"rx_" + k: v for k, v in self.decoder.counters().items()})
        return d
