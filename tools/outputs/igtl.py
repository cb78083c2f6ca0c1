"""``--igtl PORT``: every valid pose as an OpenIGTLink TRANSFORM message, for
3D Slicer (OpenIGTLinkIF), PLUS or any OpenIGTLink client.

Devices (one per track, so a client never sees two estimators interleaved
on one transform; names in PLUS's ``<From>To<To>`` form):

* ``Sensor<node>ToSource`` (node 16: ``Sensor16ToSource``), the node's
  track: its fused poses (``POSE_FUSED``, the magnetic-inertial filter);
  on a node that has sent no fused pose yet (no IMU, or before its filter
  has started) its magnetic poses. Once a fused pose has gone out, the
  magnetic ones stay off this device. This is the transform to follow in
  Slicer or to name in a PLUS configuration.
* ``Sensor<node>MagToSource`` (``Sensor16MagToSource``): every
  magnetic-only pose of the node (the solve of each pulse cycle), for a
  comparison or a recording of the raw magnetic track.

OpenIGTLink device names are at most 20 bytes; the longest here, node 255's
``Sensor255MagToSource``, is 20.

Each is the 4x4 transform from the sensor frame to the source frame,
rotation from the POSE quaternion, translation in millimetres. Header
version 2, with metadata (strings, as the standard has them): ``Status``
(POSE_* bits, decimal), ``StatusBits`` (their names), ``Kind`` (``fused``
or ``magnetic``), ``CovarianceDiagonal`` (var_px var_py var_pz in m^2,
var_rx var_ry var_rz in rad^2), ``Sequence`` (the count of that device's
messages from 0), ``TimestampUs`` (the pose's time on the master clock,
microseconds since the run started) and, as PLUS writes it,
``<device>TransformStatus`` = ``OK``.

Time stamps: the header's time stamp is Unix time (seconds since 1970, UTC,
as the OpenIGTLink standard and PLUS's ``UseReceivedTimestamps`` read it):
the pose's time on the firmware's master clock (the clock the nodes are
synchronised to) plus the one offset from that clock to the host's wall
clock, taken once when the run starts (:meth:`IgtlOutput.anchor`), so the
stamps keep the master clock's spacing and are never shifted by a later
change of the wall clock. On each device the stamps strictly increase: a
pose not newer than the last one sent on its device is not sent (counted as
``igtl_stale_dropped``). Sending it re-stamped would date an old pose as a
new one; sent with its own stamp, PLUS drops it anyway (its time-stamped
buffer refuses an item not newer than the last) and Slicer would show it
after a newer one. Poses without ``POSE_VALID`` are not sent (counted as
``igtl_invalid_skipped``).

The server is pyigtl's (``OpenIGTLinkServer`` and its queue), bound to the
address given and without the signal handlers pyigtl installs, so the
command's own handling of SIGINT and SIGTERM stays in charge; a client that
goes away ends its connection quietly and the next one is served.
"""
from __future__ import annotations

import socketserver
import time

import numpy as np
import pyigtl
from pyigtl.comm import OpenIGTLinkBase

from coiltrack.firmware.rotation import matrix_from_quat
from coiltrack.protocol import FrameDecoder
from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID

from .posecsv import pose_bit_names


def device_name(node: int, magnetic: bool = False) -> str:
    """``Sensor<node>ToSource`` (the node's track) or ``Sensor<node>MagToSource``."""
    return f"Sensor{node}{'Mag' if magnetic else ''}ToSource"


def transform_message(msg, sequence: int, name: str | None = None,
                      unix_s: float | None = None) -> pyigtl.TransformMessage:
    """The TRANSFORM message of one POSE message on device ``name`` (default: the
    node's track), time stamp ``unix_s`` (default: the master clock's seconds)."""
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(np.array([msg.qw, msg.qx, msg.qy, msg.qz]))
    T[:3, 3] = np.array([msg.px, msg.py, msg.pz]) * 1e3
    name = name or device_name(msg.node)
    stamp = msg.t_us * 1e-6 if unix_s is None else unix_s
    out = pyigtl.TransformMessage(T, timestamp=stamp, device_name=name)
    out.header_version = 2
    out.message_id = sequence & 0xFFFFFFFF
    cov = (msg.var_px, msg.var_py, msg.var_pz, msg.var_rx, msg.var_ry, msg.var_rz)
    out.metadata = {
        "Status": str(msg.status),
        "StatusBits": "+".join(pose_bit_names(msg.status)),
        "Kind": "fused" if msg.status & POSE_FUSED else "magnetic",
        "CovarianceDiagonal": " ".join(f"{v:.9g}" for v in cov),
        "Sequence": str(sequence),
        "TimestampUs": str(msg.t_us),
        f"{name}TransformStatus": "OK",
    }
    return out


class _Handler(socketserver.BaseRequestHandler):
    """One client: what it sends is read (and kept by pyigtl), the queued transforms
    are sent, until the server stops or the client goes away."""

    def handle(self) -> None:
        srv = self.server
        srv._connected = True
        self.request.settimeout(0.01)
        try:
            while not srv.communication_thread_stop_requested:
                while srv._receive_message_from_socket(self.request):
                    pass
                while srv._send_queued_message_from_socket(self.request):
                    pass
        except OSError:             # broken pipe, reset: the client left
            pass
        finally:
            srv._connected = False


class _Server(pyigtl.OpenIGTLinkServer):
    """pyigtl's server on (host, port); port 0 takes a free one (see ``port``)."""

    allow_reuse_address = True

    def __init__(self, host: str, port: int):           # noqa: D107 - pyigtl's __init__ is bypassed on purpose
        OpenIGTLinkBase.__init__(self)
        socketserver.TCPServer.__init__(self, (host, port), _Handler)
        self.host, self.port = self.server_address[:2]
        self.start()


class PoseRouter:
    """Which device each POSE goes out on, with which Unix time stamp, or none (the
    rules of the module docstring). No socket: :class:`IgtlOutput` sends what
    :meth:`route` returns. ``wall_clock()``: Unix seconds now (injected in tests)."""

    def __init__(self, wall_clock=time.time):
        self.wall_clock = wall_clock
        self.unix0: float | None = None       # Unix time of master-clock 0
        self.fused_seen: set[int] = set()
        self.last_us: dict[str, int] = {}     # the last time stamp sent on each device
        self.sequence: dict[str, int] = {}
        self.invalid_skipped = 0
        self.stale_dropped = 0

    def anchor(self, master_us: int, unix_s: float | None = None) -> None:
        """Map the master clock to Unix time, once: ``master_us`` on the master clock is
        ``unix_s`` (default: the wall clock now). Later calls change nothing."""
        if self.unix0 is None:
            self.unix0 = (self.wall_clock() if unix_s is None else unix_s) - master_us * 1e-6

    def unix_time(self, t_us: int) -> float:
        """Unix seconds of master-clock time ``t_us`` (anchored at the first call if not yet)."""
        self.anchor(t_us)
        return self.unix0 + t_us * 1e-6

    def route(self, msg) -> list[tuple[str, int, float]]:
        """(device, sequence, Unix time stamp) for each message ``msg`` (a POSE) goes out as."""
        if not msg.status & POSE_VALID:
            self.invalid_skipped += 1
            return []
        if msg.status & POSE_FUSED:
            self.fused_seen.add(msg.node)
            names = [device_name(msg.node)]
        else:
            names = [device_name(msg.node, magnetic=True)]
            if msg.node not in self.fused_seen:
                names.append(device_name(msg.node))
        out = []
        for name in names:
            if msg.t_us <= self.last_us.get(name, -1):
                self.stale_dropped += 1
                continue
            self.last_us[name] = msg.t_us
            k = self.sequence.get(name, 0)
            self.sequence[name] = k + 1
            out.append((name, k, self.unix_time(msg.t_us)))
        return out


class IgtlOutput:
    """``feed(bytes)`` is a sink for :class:`tools.bench.linktap.TapPort`: it decodes the
    frames and queues a TRANSFORM for every valid POSE, on the devices
    :class:`PoseRouter` gives it."""

    def __init__(self, host: str, port: int, wall_clock=time.time):
        self.server = _Server(host, port)
        self.router = PoseRouter(wall_clock)
        self.anchor = self.router.anchor
        self.decoder = FrameDecoder(on_frame=self._on_frame)
        self.feed = self.decoder.feed
        self.sent = 0
        self.stopped = False

    @property
    def address(self) -> str:
        return f"{self.server.host}:{self.server.port}"

    def _on_frame(self, hdr, msg) -> None:
        if msg.NAME != "POSE":
            return
        for name, k, unix_s in self.router.route(msg):
            self.server.send_message(transform_message(msg, k, name, unix_s), wait=False)
            self.sent += 1

    def wait_for_client(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a client to connect; True if one did."""
        end = time.monotonic() + timeout_s
        while not self.server.is_connected() and time.monotonic() < end:
            time.sleep(0.02)
        return self.server.is_connected()

    def close(self, flush_s: float = 2.0) -> None:
        """Let a connected client have what is queued (up to ``flush_s``), then stop (once)."""
        if self.stopped:
            return
        self.stopped = True
        end = time.monotonic() + flush_s
        while self.server.is_connected() and self.server.outgoing_messages and time.monotonic() < end:
            time.sleep(0.01)
        self.server.stop()

    def counters(self) -> dict:
        r = self.router
        return {"igtl_address": self.address, "igtl_sent": self.sent,
                "igtl_devices": {name: r.sequence[name] for name in sorted(r.sequence)},
                "igtl_clock_origin_unix_s": r.unix0,
                "igtl_invalid_skipped": r.invalid_skipped, "igtl_stale_dropped": r.stale_dropped}
