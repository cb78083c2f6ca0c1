"""``--igtl PORT``: every valid pose as an OpenIGTLink TRANSFORM message, for
3D Slicer (OpenIGTLinkIF), PLUS or any OpenIGTLink client.

One device per sensor node, ``Sensor<node>ToSource`` (node 16:
``Sensor16ToSource``): the 4x4 transform from the sensor frame to the
source frame, rotation from the POSE quaternion, translation in
millimetres. Header version 2, with metadata (strings, as the standard
has them): ``Status`` (POSE_* bits, decimal), ``StatusBits`` (their names),
``Kind`` (``fused`` or ``magnetic``), ``CovarianceDiagonal`` (var_px var_py
var_pz in m^2, var_rx var_ry var_rz in rad^2), ``Sequence`` (the sensor's
pose count from 0), ``TimestampUs`` and, as PLUS writes it,
``<device>TransformStatus`` = ``OK``. The message time stamp is the pose's
time on the sensor clock (the firmware's master clock the nodes are
synchronised to), in seconds. Poses without ``POSE_VALID`` are not sent
(counted as ``igtl_invalid_skipped``).

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


def device_name(node: int) -> str:
    return f"Sensor{node}ToSource"


def transform_message(msg, sequence: int) -> pyigtl.TransformMessage:
    """The TRANSFORM message of one POSE message."""
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(np.array([msg.qw, msg.qx, msg.qy, msg.qz]))
    T[:3, 3] = np.array([msg.px, msg.py, msg.pz]) * 1e3
    name = device_name(msg.node)
    out = pyigtl.TransformMessage(T, timestamp=msg.t_us * 1e-6, device_name=name)
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


class IgtlOutput:
    """``feed(bytes)`` is a sink for :class:`tools.linktap.TapPort`: it decodes the
    frames and queues a TRANSFORM for every valid POSE."""

    def __init__(self, host: str, port: int):
        self.server = _Server(host, port)
        self.decoder = FrameDecoder(on_frame=self._on_frame)
        self.feed = self.decoder.feed
        self.sequence: dict[int, int] = {}
        self.sent = 0
        self.invalid_skipped = 0
        self.stopped = False

    @property
    def address(self) -> str:
        return f"{self.server.host}:{self.server.port}"

    def _on_frame(self, hdr, msg) -> None:
        if msg.NAME != "POSE":
            return
        if not msg.status & POSE_VALID:
            self.invalid_skipped += 1
            return
        k = self.sequence.get(msg.node, 0)
        self.sequence[msg.node] = k + 1
        self.server.send_message(transform_message(msg, k), wait=False)
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
        return {"igtl_address": self.address, "igtl_sent": self.sent,
                "igtl_invalid_skipped": self.invalid_skipped}
