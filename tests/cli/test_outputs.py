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
    """Every message the client received (``igtl_client``: all of them, in arrival order)
    once the bench has ended and ``expected`` have arrived (or the time-out: then the
    assertions say what is missing)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if proc.poll() is not None and len(client.received) >= expected:
            break
        time.sleep(0.005)
    return list(client.received)


def test_igtl_client_receives_the_bench_poses(tmp_path, igtl_client):
    """pyigtl's client on loopback gets one TRANSFORM per valid pose on each of the
    node's devices (a magnetic-only run: Sensor16ToSource, the node's track, and
    Sensor16MagToSource carry the same poses), header version 2, translation
    in mm equal to the pose table's to 0.01 mm, the same rotation, Unix time stamps
    (the master clock plus one offset, the report's, taken within the run) and
    metadata. Catches metres sent as millimetres, a transposed rotation, a wrong
    device name, a time stamp on the run's clock (1970), dropped poses, metadata out
    of step with the pose."""
    import os

    port = _free_port()
    table = tmp_path / "poses.csv"
    rep_path = tmp_path / "rep.json"
    cmd = [sys.executable, "-m", "coiltrack.tools.cli", "bench", "--scenario", "static", "--duration", "3",
           "--quiet", "--igtl", str(port), "--igtl-wait", "60", "--poses", str(table), "--json", str(rep_path)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    client = igtl_client(port)
    try:
        # the static scenario gives a pose every 0.6 s: the client sees each one, twice
        got = _collect(client, proc, expected=10)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    rows = [r for r in _rows(table) if int(r["status"]) & POSE_VALID]
    rep = json.loads(rep_path.read_text())
    assert len(rows) == rep["poses"] >= 4 and rep["igtl_sent"] == 2 * len(rows)
    assert rep["igtl_devices"] == {"Sensor16MagToSource": len(rows), "Sensor16ToSource": len(rows)}
    assert len(got) == 2 * len(rows) and rep["igtl_stale_dropped"] == 0
    # Unix time: master-clock 0 is when the paced run started, before the pose table was written
    origin = rep["igtl_clock_origin_unix_s"]
    assert 0 < os.stat(table).st_mtime - origin - 3.0 < 60.0
    by_t = {int(r["t_us"]): (k, r) for k, r in enumerate(rows)}
    for m in got:
        assert m.message_type == "TRANSFORM" and m.header_version == 2
        assert m.device_name in ("Sensor16ToSource", "Sensor16MagToSource")
        assert m.metadata["Kind"] == "magnetic" and m.metadata[m.device_name + "TransformStatus"] == "OK"
        t_us = int(m.metadata["TimestampUs"])
        assert abs(m.timestamp - (origin + t_us * 1e-6)) < 1e-6
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


# ---------------------------------------------------------------------------
# pose table and figure: one short fused run (magnetic and fused poses)
# ---------------------------------------------------------------------------

FUSION_S = "2"


@pytest.fixture(scope="module")
def fused_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("fused")
    paths = {k: d / f"run.{k}" for k in ("csv", "png", "json")}
    rc = main(["bench", "--scenario", "roetenberg-fusion", "--seed", "1", "--duration", FUSION_S, "--quiet",
               "--poses", str(paths["csv"]), "--plot", str(paths["png"]), "--json", str(paths["json"])])
    assert rc == 0
    return paths, json.loads(paths["json"].read_text())


def _col(rows, name, kind=None):
    return np.array([float(r[name]) for r in rows if kind is None or r["kind"] == kind])


def _angle_deg(q, t) -> np.ndarray:
    """Angle of the rotation between two quaternion arrays (n, 4), from the relative
    quaternion conj(t) * q (atan2 form: accurate for small angles)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    w = np.sum(q * t, axis=1)
    v = (t[:, :1] * q[:, 1:] - q[:, :1] * t[:, 1:]) - np.cross(t[:, 1:], q[:, 1:])
    return np.degrees(2 * np.arctan2(np.linalg.norm(v, axis=1), np.abs(w)))


def test_pose_table_rows_and_errors(fused_run):
    """One row per pose of each kind, as the report counts them; the error columns
    agree with the estimate and truth columns recomputed here, and their RMS with the
    report's. Catches a dropped or doubled kind, truth looked up at the wrong time,
    metres written as millimetres, an orientation error in radians or from a
    transposed rotation."""
    paths, rep = fused_run
    rows = _rows(paths["csv"])
    kinds = collections.Counter(r["kind"] for r in rows)
    assert kinds["fused"] == rep["poses"] > 100
    assert len(rows) == rep["poses"] + rep["magnetic_poses"] + rep["poses_invalid"]
    valid = [r for r in rows if int(r["status"]) & POSE_VALID]
    assert sum(r["kind"] == "magnetic" for r in valid) == rep["magnetic_poses"] >= 2
    est = np.array([[float(r[c]) for c in ("x_mm", "y_mm", "z_mm")] for r in valid])
    true = np.array([[float(r[c]) for c in ("true_x_mm", "true_y_mm", "true_z_mm")] for r in valid])
    np.testing.assert_allclose(_col(valid, "pos_err_mm"), np.linalg.norm(est - true, axis=1), atol=1e-5)
    np.testing.assert_allclose(_col(valid, "range_mm"), np.linalg.norm(true, axis=1), rtol=1e-7)
    q = np.array([[float(r[c]) for c in ("qw", "qx", "qy", "qz")] for r in valid])
    t = np.array([[float(r[c]) for c in ("true_qw", "true_qx", "true_qy", "true_qz")] for r in valid])
    np.testing.assert_allclose(_col(valid, "ori_err_deg"), _angle_deg(q, t), atol=1e-4)
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))  # noqa: E731
    fused = [r for r in valid if r["kind"] == "fused"]
    mag = [r for r in valid if r["kind"] == "magnetic"]
    assert rms(_col(fused, "pos_err_mm")) == pytest.approx(rep["position_rms_mm"], abs=1e-3)
    assert rms(_col(fused, "ori_err_deg")) == pytest.approx(rep["orientation_rms_deg"], abs=1e-3)
    assert rms(_col(mag, "pos_err_mm")) == pytest.approx(rep["magnetic_position_rms_mm"], abs=1e-3)
    assert rms(_col(mag, "crlb_mm")) == pytest.approx(rep["crlb_position_rms_mm"], abs=1e-3)
    assert all(float(r["var_px_m2"]) > 0 for r in valid)
    assert all(("fused" in r["status_bits"]) == (r["kind"] == "fused") for r in rows)


def _png(path):
    import matplotlib.image as mpimg

    img = mpimg.imread(str(path))
    rgb = np.round(img[..., :3] * 255).astype(int)
    colours = {tuple(c) for c in rgb.reshape(-1, 3)[::7]}
    return rgb, colours


def _near(rgb, colour, tol=40) -> int:
    return int(np.sum(np.all(np.abs(rgb - np.array(colour)) < tol, axis=-1)))


def test_bench_plot_and_plot_command(fused_run, tmp_path):
    """bench --plot and `coiltrack plot` of the pose table draw the full figure
    (15 x 9 in at 80 dpi), with the estimate (blue, orange) and the CRLB (red) in
    it, and so does `coiltrack plot` of the report that names the table; of a
    report alone it draws the report's per-range bands. Catches a
    blank or empty figure, a series left out."""
    paths, rep = fused_run
    again, via_report = tmp_path / "again.png", tmp_path / "via-report.png"
    assert main(["plot", str(paths["csv"]), "-o", str(again)]) == 0
    assert main(["plot", str(paths["json"]), "-o", str(via_report)]) == 0     # the report names its table
    for png in (paths["png"], again, via_report):
        rgb, colours = _png(png)
        assert rgb.shape[:2] == (720, 1200)
        assert rgb.var() > 0 and len(colours) > 20
        for c in ((31, 119, 180), (255, 127, 14), (214, 39, 40)):    # tab:blue, tab:orange, tab:red
            assert _near(rgb, c) > 50, c
    only = tmp_path / "rep.json"
    only.write_text(json.dumps({k: v for k, v in rep.items() if k != "poses_csv"}))
    assert main(["plot", str(only)]) == 0
    rgb, colours = _png(tmp_path / "rep.png")
    assert rgb.shape[:2] == (400, 560) and rgb.var() > 0 and len(colours) > 10
    assert _near(rgb, (214, 39, 40)) > 50


# ---------------------------------------------------------------------------
# bus captures, read back by `coiltrack decode`
# ---------------------------------------------------------------------------

CAPTURE_S = 2.0


def _capture_run(d, transport: str, suffix: str):
    cap, rp = d / f"bus{suffix}", d / f"rep-{transport}{suffix}.json"
    assert main(["bench", "--scenario", "static", "--duration", str(CAPTURE_S), "--quiet", "--transport", transport,
                 "--capture", str(cap), "--json", str(rp)]) == 0
    return decode_file(cap), json.loads(rp.read_text())


@pytest.fixture(scope="module")
def raw_capture(tmp_path_factory):
    return _capture_run(tmp_path_factory.mktemp("raw"), "inproc", ".bin")


def _key(it):
    return it.src, it.seq, it.msg.NAME, tuple(it.msg)


def test_raw_capture_holds_both_directions(raw_capture):
    """The raw serial capture decodes without a bad frame into what the firmware
    received (the report's frames_rx) and what it sent (every pose, every pulse
    command). Catches a direction not recorded, frames of the two directions
    interleaved mid-frame, a chunk lost."""
    res, rep = raw_capture
    assert res.kind == "serial" and res.counters["frames_bad"] == 0
    names = collections.Counter((it.src == NODE_FIRMWARE, it.msg.NAME) for it in res.items)
    assert sum(v for (fw, _), v in names.items() if not fw) == rep["frames_rx"] > 100
    assert names[True, "POSE"] == rep["poses"] + rep["poses_invalid"] >= 2
    assert names[True, "COIL_PULSE_CMD"] >= rep["coil_pulses"] > 0      # the last are for after the end


@pytest.mark.parametrize("suffix", (".blf", ".asc", ".log"))
def test_can_capture_formats_decode_to_the_same_messages(raw_capture, tmp_path, suffix):
    """A CAN bench captured as BLF, ASC or a candump log decodes to the same messages
    as the raw capture of the same run on the byte pipe (both transports carry the
    same frames at the same simulated instants), stamped with the simulated clock.
    Catches a writer or reader losing frames, sent frames left out, wall-clock or
    unordered time stamps."""
    res, rep = _capture_run(tmp_path, "can", suffix)
    raw, raw_rep = raw_capture
    assert res.kind == "can" and res.counters["frames_bad"] == 0 and res.counters["incomplete_at_end"] == 0
    assert rep["frames_rx"] == raw_rep["frames_rx"]
    assert collections.Counter(map(_key, res.items)) == collections.Counter(map(_key, raw.items))
    t = np.array([it.t for it in res.items])
    assert np.all(np.diff(t) >= 0) and t[-1] - t[0] <= CAPTURE_S + 0.01


def test_output_arguments_refused_before_work(tmp_path, capsys):
    """Bad output arguments: one line naming the argument, exit status 2, nothing run
    (no report written)."""
    rp = tmp_path / "rep.json"
    bad = [["--igtl", "70000"], ["--igtl", "0", "--igtl-wait", "nan"], ["--capture", str(tmp_path / "c.log")],
           ["--transport", "can", "--capture", str(tmp_path / "c.bin")], ["--poses", str(tmp_path / "no" / "p.csv")],
           ["--plot", str(tmp_path)]]
    for extra in bad:
        with pytest.raises(SystemExit) as exc:
            main(["bench", "--scenario", "static", "--duration", "1", "--quiet", "--json", str(rp), *extra])
        assert exc.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and extra[-2].lstrip("-").split("-")[0] in err[0], err
    assert not rp.exists()


def test_firmware_capture_and_igtl_on_a_serial_port(tmp_path):
    """`coiltrack firmware --capture` on a pseudo-terminal with no peer records what
    the firmware sent (its TIME_SYNC and HEARTBEAT broadcasts, nothing bad), and
    `--igtl 0` serves on a free loopback port and says so in the statistics.
    Catches the firmware command not tapping its port."""
    import os
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    cap, stats = tmp_path / "fw.bin", tmp_path / "fw.json"
    try:
        proc = subprocess.run([sys.executable, "-m", "coiltrack.tools.cli", "firmware", "--port", os.ttyname(slave),
                               "--scenario", "static", "--duration", "0.5", "--capture", str(cap), "--igtl", "0",
                               "--stats-json", str(stats)], capture_output=True, text=True, timeout=60)
    finally:
        os.close(master)
        os.close(slave)
    assert proc.returncode == 0, proc.stderr
    res = decode_file(cap)
    names = collections.Counter(it.msg.NAME for it in res.items)
    assert res.counters["frames_bad"] == 0 and names["TIME_SYNC"] > 0 and names["HEARTBEAT"] > 0
    assert {it.src for it in res.items} == {NODE_FIRMWARE}
    timing = json.loads(stats.read_text())["timing"]
    assert timing["capture"]["kind"] == "serial" and timing["igtl_address"].startswith("127.0.0.1:")
