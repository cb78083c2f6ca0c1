"""OpenIGTLink as 3D Slicer and PLUS expect it (``tools.outputs.igtl``): one device per
track, Unix time stamps, never a step back in time on a device.

The router's rules run on hand-made POSE messages with an injected wall
clock; one short fused bench (3 s, paced to the wall clock while it serves)
is received by pyigtl's client over loopback, every message kept in arrival
order.
"""
from __future__ import annotations

import csv
import json
import socket
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID

pytest.importorskip("pyigtl")

from coiltrack.tools.outputs.igtl import PoseRouter, device_name, transform_message  # noqa: E402

MAG = POSE_VALID
FUSED = POSE_VALID | POSE_FUSED
UNIX0 = 1_780_000_000.25        # an injected wall clock's "now"


def _pose(t_us: int, status: int, node: int = 16, p=(0.1, -0.2, 0.3)):
    return SimpleNamespace(NAME="POSE", node=node, t_us=t_us, status=status, px=p[0], py=p[1], pz=p[2],
                           qw=1.0, qx=0.0, qy=0.0, qz=0.0, var_px=1e-6, var_py=2e-6, var_pz=3e-6,
                           var_rx=1e-4, var_ry=2e-4, var_rz=3e-4)


def test_device_names_fit_the_20_byte_field():
    """OpenIGTLink's device name is 20 bytes: every node id (u8) fits on both devices.
    Catches a name that a client receives cut short (``Sensor16MagneticToSo``)."""
    assert device_name(16) == "Sensor16ToSource" and device_name(16, magnetic=True) == "Sensor16MagToSource"
    assert max(len(device_name(n, m).encode()) for n in range(256) for m in (False, True)) == 20


def test_fused_and_magnetic_poses_go_out_on_their_own_devices():
    """Magnetic poses before the node's first fused pose are its track (and on the
    magnetic device); from the first fused pose on, the track carries only fused
    poses and the magnetic ones go on the magnetic device alone; another node keeps
    its own devices. Catches the two kinds interleaved on one device (the 10 cm
    jumps Slicer showed)."""
    r = PoseRouter(wall_clock=lambda: UNIX0)
    names = lambda msg: [d for d, _, _ in r.route(msg)]  # noqa: E731
    assert names(_pose(330_000, MAG)) == ["Sensor16MagToSource", "Sensor16ToSource"]
    assert names(_pose(512_000, FUSED)) == ["Sensor16ToSource"]
    assert names(_pose(520_000, FUSED)) == ["Sensor16ToSource"]
    assert names(_pose(930_000, MAG)) == ["Sensor16MagToSource"]
    assert names(_pose(940_000, MAG, node=17)) == ["Sensor17MagToSource", "Sensor17ToSource"]
    assert names(_pose(945_000, POSE_FUSED)) == []          # not valid: not sent
    assert r.sequence == {"Sensor16MagToSource": 2, "Sensor16ToSource": 3, "Sensor17MagToSource": 1,
                          "Sensor17ToSource": 1}
    assert r.invalid_skipped == 1 and r.stale_dropped == 0


def test_a_pose_not_newer_than_its_devices_last_is_dropped():
    """A magnetic pose whose time is older than the node's last fused pose (the
    magnetic solve comes out after the fused poses of the same interval) goes on the
    magnetic device but not on the track; an equal or older stamp on one device is
    dropped and counted. Catches a device's stamps stepping back (PLUS refuses such
    an item; Slicer shows it after a newer one)."""
    # node 16 sends a magnetic pose (no fused yet) at 0.50 s, then a fused one at 0.40 s
    r2 = PoseRouter(wall_clock=lambda: UNIX0)
    r2.route(_pose(500_000, MAG))
    out = r2.route(_pose(400_000, FUSED))
    assert out == [] and r2.stale_dropped == 1
    out = r2.route(_pose(500_000, FUSED))                       # equal: not newer either
    assert out == [] and r2.stale_dropped == 2
    out = r2.route(_pose(508_333, FUSED))
    assert [d for d, _, _ in out] == ["Sensor16ToSource"]
    # the magnetic device has its own history: 0.49 s is older than its 0.50 s
    assert r2.route(_pose(490_000, MAG)) == [] and r2.stale_dropped == 3
    assert [d for d, _, _ in r2.route(_pose(1_100_000, MAG))] == ["Sensor16MagToSource"]


def test_time_stamps_are_unix_time_from_one_mapping():
    """The master clock is mapped to Unix time once (the first ``anchor`` wins; without
    one, the first pose anchors it at the wall clock's now); every stamp is that origin
    plus the pose's master-clock time, so the spacing is the master clock's whatever
    the wall clock does later. Catches seconds since the run started (read as 1970), a
    mapping taken again at every pose (the wall clock's jitter in the stamps)."""
    wall = [UNIX0]
    r = PoseRouter(wall_clock=lambda: wall[0])
    r.anchor(250_000)                           # master clock 0.25 s at Unix UNIX0
    r.anchor(0, unix_s=0.0)                     # a second mapping changes nothing
    wall[0] += 123.0                            # the wall clock steps later on
    (_, _, a), _ = r.route(_pose(1_250_000, MAG))   # magnetic device and track: the same stamp
    (_, _, b), = r.route(_pose(1_850_000, FUSED))
    assert a == pytest.approx(UNIX0 + 1.0, abs=1e-6) and b - a == pytest.approx(0.6, abs=1e-6)
    r2 = PoseRouter(wall_clock=lambda: UNIX0)  # no anchor: the first pose is "now"
    (_, _, c), = r2.route(_pose(2_000_000, FUSED))
    assert c == pytest.approx(UNIX0, abs=1e-6) and r2.unix0 == pytest.approx(UNIX0 - 2.0, abs=1e-6)


def test_transform_message_packs_the_unix_stamp_and_device():
    """The packed message, unpacked by pyigtl, keeps the device, the Unix stamp (to the
    32.32 fixed point's resolution, well under a microsecond) and the master-clock time
    in ``TimestampUs``. Catches the stamp lost in packing (seconds overflowing 32 bits)."""
    import pyigtl
    from pyigtl.messages import MessageBase

    msg = transform_message(_pose(1_234_567, FUSED), 7, "Sensor16ToSource", UNIX0 + 1.234567)
    head = msg.pack()
    fields = MessageBase.parse_header(head[:MessageBase.IGTL_HEADER_SIZE])
    back = pyigtl.TransformMessage()
    back.unpack(fields, head[MessageBase.IGTL_HEADER_SIZE:])
    assert back.device_name == "Sensor16ToSource" and back.metadata["TimestampUs"] == "1234567"
    assert back.timestamp == pytest.approx(UNIX0 + 1.234567, abs=1e-6)
    assert back.metadata["Sequence"] == "7" and back.metadata["Kind"] == "fused"
    np.testing.assert_allclose(back.matrix[:3, 3], [100.0, -200.0, 300.0], atol=1e-4)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_fused_bench_on_two_devices_received_by_pyigtl(tmp_path, igtl_client):
    """`bench --scenario roetenberg-fusion --igtl PORT` for 3 s, received by pyigtl:
    the fused poses on Sensor16ToSource, the magnetic ones on Sensor16MagToSource
    (each device exactly its track of the pose table, in order), the stamps strictly
    increasing on each device and Unix time (one origin, the report's), and on the
    track no step between a magnetic and a fused pose once the filter runs. Catches
    the kinds interleaved on one device, stamps stepping back, a run-relative clock."""
    port = _free_port()
    table, rep_path = tmp_path / "poses.csv", tmp_path / "rep.json"
    cmd = [sys.executable, "-m", "coiltrack.tools.cli", "bench", "--scenario", "roetenberg-fusion", "--duration",
           "3", "--quiet", "--igtl", str(port), "--igtl-wait", "60", "--poses", str(table), "--json", str(rep_path)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    client = igtl_client(port)
    try:
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    rep = json.loads(rep_path.read_text())
    end = time.monotonic() + 60                 # a hang guard only: the server flushes before it stops
    while len(client.received) < rep["igtl_sent"] and time.monotonic() < end:
        time.sleep(0.01)
    got = list(client.received)
    assert len(got) == rep["igtl_sent"] and rep["igtl_stale_dropped"] == 0
    with open(table, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if int(r["status"]) & POSE_VALID]
    fused = [r for r in rows if r["kind"] == "fused"]
    mag = [r for r in rows if r["kind"] == "magnetic"]
    assert len(fused) > 200 and len(mag) >= 4
    by_dev: dict[str, list] = {}
    for m in got:
        by_dev.setdefault(m.device_name, []).append(m)
    assert set(by_dev) == {"Sensor16ToSource", "Sensor16MagToSource"}
    track, magnetic = by_dev["Sensor16ToSource"], by_dev["Sensor16MagToSource"]
    assert [m.metadata["Kind"] for m in magnetic] == ["magnetic"] * len(mag)
    kinds = [m.metadata["Kind"] for m in track]
    first = kinds.index("fused")
    assert kinds[first:] == ["fused"] * len(fused) and set(kinds[:first]) <= {"magnetic"}
    # each device is its track of the pose table, in order
    pre = [r for r in mag if int(r["t_us"]) < int(fused[0]["t_us"])]
    for msgs, want in ((magnetic, mag), (track, pre + fused)):
        assert [int(m.metadata["TimestampUs"]) for m in msgs] == [int(r["t_us"]) for r in want]
        xyz = np.array([[float(r[c]) for c in ("x_mm", "y_mm", "z_mm")] for r in want])
        np.testing.assert_allclose([m.matrix[:3, 3] for m in msgs], xyz, atol=0.01)
        assert [m.metadata["Sequence"] for m in msgs] == [str(k) for k in range(len(msgs))]
    origin = rep["igtl_clock_origin_unix_s"]
    assert origin > 1.6e9                       # Unix time (after 2020), not seconds since the run started
    for msgs in by_dev.values():
        stamps = np.array([m.timestamp for m in msgs])
        assert np.all(np.diff(stamps) > 0)
        t_us = np.array([int(m.metadata["TimestampUs"]) for m in msgs])
        np.testing.assert_allclose(stamps - t_us * 1e-6, origin, atol=1e-6)
