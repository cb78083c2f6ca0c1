"""What the commands write: strict JSON, logs cut short, captures with bad lines,
and a measurement whose optional reference package is missing."""
from __future__ import annotations

import json
import math
import shutil
import sys

import numpy as np
import pytest

from coiltrack.protocol.golden import GOLDEN_DIR
from coiltrack.tools.outputs import jsonout
from coiltrack.tools.cli import main


def _strict(text: str):
    return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))


def test_sanitize_writes_null_for_every_non_finite_number():
    obj = {"a": math.nan, "b": [1.0, math.inf, np.float64(-np.inf)], "c": np.array([np.nan, 2.5]),
           "d": (np.int64(3), np.bool_(True)), "e": {"f": np.float32(1.5)}}
    assert _strict(jsonout.dumps(obj)) == {"a": None, "b": [1.0, None, None], "c": [None, 2.5],
                                          "d": [3, True], "e": {"f": 1.5}}


def test_a_run_without_a_valid_pose_writes_null_not_nan(tmp_path, capsys):
    out = tmp_path / "r.json"
    # 0.1 s: before the first cycle ends, so no pose and no RMS
    assert main(["bench", "--scenario", "static", "--duration", "0.1", "--quiet", "--json", str(out)]) == 0
    rep = _strict(out.read_text())
    assert rep["poses"] == 0
    assert rep["position_rms_mm"] is None and rep["orientation_rms_deg"] is None


def test_decode_skips_and_counts_malformed_log_lines(tmp_path, capsys):
    src = GOLDEN_DIR / "can" / "POSE.log"
    good = src.read_text().splitlines()
    assert len(good) >= 2
    bad = tmp_path / "bus.log"
    bad.write_text("\n".join([good[0], "(1.0) can0 not-a-frame", *good[1:], "garbage", ""]) + "\n")
    assert main(["decode", str(src)]) == 0
    clean = capsys.readouterr().out.splitlines()
    assert main(["decode", str(bad)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[:-1] == clean[:-1]                       # every message still decoded
    n = len(good) + 2                                    # good[0], the bad line, good[1:], garbage
    assert f"malformed_lines=2, malformed_line_numbers=[2, {n}]" in lines[-1]


def _cut(log, tmp_path, fraction: float):
    """A copy of ``log`` cut in the middle of a line, at ``fraction`` of its size."""
    data = log.read_bytes()
    at = int(len(data) * fraction)
    while data[at - 1:at] == b"\n":
        at += 1
    path = tmp_path / "cut.log"
    path.write_bytes(data[:at])
    return path, data[:at].count(b"\n") + 1


def test_a_cut_frame_log_is_read_up_to_the_cut(fusion_log, tmp_path):
    from coiltrack.tools.bench.framelog import read_log

    header, reads = read_log(fusion_log)
    path, line = _cut(fusion_log, tmp_path, 0.6)
    h2, r2 = read_log(path)
    assert r2 == reads[:len(r2)] and 0.5 * len(reads) < len(r2) < 0.7 * len(reads)
    assert h2["truncated"] == {"line": line, "reads": len(r2), "recorded_duration_s": header["duration_s"],
                               "why": "cut short (no newline at its end)"}
    assert h2["duration_s"] == r2[-1][0] * 1e-6


def test_smooth_and_perf_use_a_cut_log_and_say_where_it_stopped(fusion_log, tmp_path, capsys):
    path, line = _cut(fusion_log, tmp_path, 0.8)
    assert main(["smooth", str(path)]) == 0
    err = capsys.readouterr().err
    assert f"cut short at line {line}" in err and "4.0 s run" in err
    assert main(["perf", "--log", str(path), "--warmup", "0.5", "--json", str(tmp_path / "p.json")]) == 0
    assert f"cut short at line {line}" in capsys.readouterr().err
    assert _strict((tmp_path / "p.json").read_text())["duration_s"] < 4.0


def test_a_log_whose_header_is_cut_is_refused_naming_line_1(fusion_log, tmp_path, capsys):
    path = tmp_path / "h.log"
    path.write_bytes(fusion_log.read_bytes()[:40])
    assert main(["perf", "--log", str(path)]) == 2
    assert f"{path}: line 1: not a coiltrack-frames/1 header" in capsys.readouterr().err


def test_perf_without_filterpy_marks_the_comparison_absent(fusion_log, monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "filterpy", None)
    monkeypatch.setitem(sys.modules, "filterpy.kalman", None)
    out = tmp_path / "p.json"
    assert main(["perf", "--log", str(fusion_log), "--warmup", "1", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "filterpy predict absent (pip install filterpy)" in text
    rep = _strict(out.read_text())
    assert rep["fused_step_us"] > 0 and rep["filter_states"] >= 15
    assert rep["filterpy_step_us"] is None and rep["filterpy"].startswith("absent")


def test_decode_and_schema_into_a_closed_pipe_exit_quietly(tmp_path):
    import os
    import subprocess

    cap = tmp_path / "big.log"
    shutil.copy(GOLDEN_DIR / "can" / "POSE.log", cap)
    for argv in (["schema", "--json"], ["decode", str(cap)]):
        r, w = os.pipe()
        os.close(r)                              # the reader is gone before anything is written
        p = subprocess.run([sys.executable, "-m", "coiltrack.tools.cli", *argv], stdout=w,
                           stderr=subprocess.PIPE, timeout=60)
        os.close(w)
        assert p.returncode == 141 and p.stderr == b"", p.stderr.decode()
