"""Outputs for other tools: OpenIGTLink, the pose table, bus captures, plots.

Every bench here is short (2-3 s of a scenario) and seeded; the OpenIGTLink
test is the only one on the wall clock (the bench paces itself while it
serves), and its time-outs only bound how long to wait for things to arrive.
"""
from __future__ import annotations

import collections
import csv
import json
import math
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from coiltrack.protocol.capture import decode_file
from coiltrack.protocol.schema import NODE_FIRMWARE, POSE_VALID
from coiltrack.tools.cli import main


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rows(path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _quat_matrix(w, x, y, z) -> np.ndarray:
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _collect(client, proc, expected: int, timeout_s: float = 60.0) -> list:
    """Every message the client hands over until the bench has ended and ``expected``
    have arrived (or the time-out: then the assertions say what is missing)."""
    got = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        got += client.get_latest_messages()
        if proc.poll() is not None and len(got) >= expected:
            break
        time.sleep(0.005)
    return got


def test_igtl_client_receives_the_bench_poses(tmp_path):
    """pyigtl's client on loopback gets one TRANSFORM per valid pose, device
    Sensor16ToSource, header version 2, translation in mm equal to the pose
    table's to 0.01 mm, the same rotation, sensor-clock time stamp and metadata.
    Catches metres sent as millimetres, a transposed rotation, a wrong device
    name or clock, dropped poses, metadata out of step with the pose."""
    import pyigtl

    port = _free_port()
    table = tmp_path / "poses.csv"
    rep_path = tmp_path / "rep.json"
    cmd = [sys.executable, "-m", "coiltrack.tools.cli", "bench", "--scenario", "static", "--duration", "3",
           "--quiet", "--igtl", str(port), "--igtl-wait", "60", "--poses", str(table), "--json", str(rep_path)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
    try:
        # the static scenario gives a pose every 0.6 s: the client sees each one
        got = _collect(client, proc, expected=5)
        out, err = proc.communicate(timeout=60)
    finally:
        client.stop()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    rows = [r for r in _rows(table) if int(r["status"]) & POSE_VALID]
    rep = json.loads(rep_path.read_text())
    assert len(rows) == rep["poses"] >= 4 and rep["igtl_sent"] == len(rows)
    assert len(got) == len(rows)
    by_t = {int(r["t_us"]): (k, r) for k, r in enumerate(rows)}
    for m in got:
        assert m.message_type == "TRANSFORM" and m.device_name == "Sensor16ToSource" and m.header_version == 2
        t_us = int(m.metadata["TimestampUs"])
        assert abs(m.timestamp - t_us * 1e-6) < 1e-6
        k, r = by_t[t_us]
        est = np.array([float(r["x_mm"]), float(r["y_mm"]), float(r["z_mm"])])
        assert np.max(np.abs(m.matrix[:3, 3] - est)) < 0.01
        R = _quat_matrix(*(float(r[c]) for c in ("qw", "qx", "qy", "qz")))
        assert np.max(np.abs(m.matrix[:3, :3] - R)) < 1e-5
        assert m.metadata["Status"] == r["status"] and m.metadata["Sequence"] == str(k)
        cov = [float(v) for v in m.metadata["CovarianceDiagonal"].split()]
        want = [float(r[c]) for c in ("var_px_m2", "var_py_m2", "var_pz_m2", "var_rx_rad2", "var_ry_rad2",
                                      "var_rz_rad2")]
        np.testing.assert_allclose(cov, want, rtol=1e-6)
