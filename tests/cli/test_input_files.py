"""Every file the tools read is parsed defensively (``tools/inputs/infile.py`` and its readers).

Example tests: each damaged-file case (a configuration or calibration file saved as
latin-1 or UTF-16, an empty one, a key twice, a ``nan``, a value of the wrong type; a pose
table cut mid-line or empty; a frame log cut short or with a bad header; a capture cut
short or empty; a sweep file of the wrong shape) run through ``coiltrack``'s ``main``:
exit status 2 and one line naming the file (and the line or key), no traceback; or, for a
file good up to its damage, exit 0 with a warning line naming the file and where it stops.

Property tests (hypothesis, derandomized): arbitrary bytes and every truncation of a valid
file never raise anything but the one clean error (or, for a line-oriented file, give the
good prefix of the whole file's rows)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from coiltrack.firmware.config import ConfigError, FirmwareConfig
from coiltrack.tools.cli import main
from coiltrack.tools.inputs.infile import InputFileError, decode_utf8, load_json, load_toml, loads_json, text_lines

PROPERTY = settings(derandomize=True, max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

CONFIG = "# the pulse, 20 \u00b0C\n[timing]\npulse_us = 50000\n"
CALIBRATION = """[meta]
method = "grid"
residual_rms = 1e-09
poses = 49

[source]
coil_moment = [[1.01, 0, 0], [0, 0.99, 0.01], [0, 0, 1.0]]
coil_offset_m = [[0.001, 0, 0], [0, 0, 0], [0, 0, -0.001]]

[sensor.32]
mag_soft = [[1.02, 0, 0], [0, 0.98, 0], [0, 0, 1.0]]
mag_hard_t = [1e-06, 0, -2e-06]
"""


def _refused(argv, capsys, *named):
    """``coiltrack argv`` exits 2 with one line on stderr naming each of ``named`` (after the
    warning lines of a damaged file, if any)."""
    assert main(argv) == 2
    *warnings, err = capsys.readouterr().err.strip().split("\n")
    assert all(w.startswith(f"coiltrack {argv[0]}: warning: ") for w in warnings), warnings
    assert err.startswith(f"coiltrack {argv[0]}: ") and "Traceback" not in err, err
    for n in named:
        assert str(n) in err, (n, err)
    return err


RUN_S = 6.0


@pytest.fixture(scope="module")
def run_files(tmp_path_factory):
    """A 6 s bench run's pose table (ten poses) and frame log, and a serial and a CAN (.asc, .log, .blf)
    capture."""
    d = tmp_path_factory.mktemp("run")
    assert main(["bench", "--scenario", "static", "--duration", str(RUN_S), "--quiet", "--poses", str(d / "poses.csv"),
                 "--log", str(d / "frames.log"), "--capture", str(d / "cap.bin")]) == 0
    for suffix in ("asc", "log", "blf"):
        assert main(["bench", "--scenario", "static", "--duration", "1.0", "--quiet", "--transport", "can",
                     "--capture", str(d / f"cap.{suffix}")]) == 0
    return d


# ---------------------------------------------------------------- the shared reader

def test_latin1_and_utf16_are_named_as_such_with_the_line():
    with pytest.raises(InputFileError) as e:
        decode_utf8("[a]\n# 20 \u00b0C\n".encode("latin-1"), "f.toml")
    assert e.value.line == 2 and "0xb0 at column 6 is not UTF-8" in str(e.value) and str(e.value).startswith("f.toml:")
    for enc in ("utf-16", "utf-16-be", "utf-32"):
        with pytest.raises(InputFileError, match="UTF-16|UTF-32|NUL"):
            decode_utf8("# 20 \u00b0C\n".encode(enc), "f.toml")
    assert decode_utf8("\ufeff# 20 \u00b0C".encode("utf-8"), "f") == "# 20 \u00b0C"   # a UTF-8 BOM is fine


def test_strict_json_refuses_nan_and_a_key_twice():
    with pytest.raises(InputFileError, match="NaN is not a finite number"):
        loads_json('{"a": NaN}', "r.json")
    with pytest.raises(InputFileError) as e:
        loads_json('{"a": 1, "b": {"c": 1, "c": 2}}', "r.json")
    assert e.value.key == "c" and "given twice" in str(e.value)
    with pytest.raises(InputFileError, match="line 3"):
        loads_json('{"a": 1,\n"b": 2,\n}', "r.json")


def test_strict_toml_names_the_line_of_a_key_twice_and_the_key_of_a_nan(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[timing]\npulse_us = 1\n\npulse_us = 2\n")
    with pytest.raises(InputFileError) as e:
        load_toml(p)
    assert e.value.line == 4 and "given twice" in str(e.value)
    p.write_text("[fusion]\nsigma = [1.0, inf]\n")
    with pytest.raises(InputFileError) as e:
        load_toml(p)
    assert e.value.key == "fusion.sigma[1]" and "finite" in str(e.value)


@PROPERTY
@given(data=st.binary(max_size=300))
def test_any_bytes_are_text_toml_json_or_the_one_error(data):
    for parse in (lambda: decode_utf8(data, "f"), lambda: load_toml_bytes(data), lambda: load_json_bytes(data)):
        try:
            parse()
        except InputFileError as exc:
            assert str(exc).startswith("f:") and "\n" not in str(exc)
    try:
        lines, damage = text_lines(data, "f")
    except InputFileError as exc:            # a UTF-16 or UTF-32 byte-order mark
        assert "UTF-" in str(exc)
        return
    assert all("\n" not in t for _, t in lines) and (damage is None or isinstance(damage[0], int))
    assert b"\n".join(t.encode() for _, t in lines) == data.replace(b"\r\n", b"\n")[:len(
        b"\n".join(t.encode() for _, t in lines))] or data.startswith(b"\xef\xbb\xbf")


def load_toml_bytes(data: bytes):
    from coiltrack.tools.inputs.infile import loads_toml

    return loads_toml(decode_utf8(data, "f"), "f")


def load_json_bytes(data: bytes):
    return loads_json(decode_utf8(data, "f"), "f")


# ---------------------------------------------------------------- configuration

@pytest.mark.parametrize("encoding", ["latin-1", "utf-16"])
@pytest.mark.parametrize("option", ["--config", "--calibration"])
def test_bench_refuses_a_file_not_in_utf8(option, encoding, tmp_path, capsys):
    p = tmp_path / "f.toml"
    p.write_bytes((CONFIG if option == "--config" else "# \u00b0C\n" + CALIBRATION).encode(encoding))
    err = _refused(["bench", "--scenario", "static", "--duration", "0.1", option, str(p)], capsys, option, p)
    assert ("line 1" in err and "0xb0" in err) if encoding == "latin-1" else "UTF-16" in err


def test_calibrate_merge_refuses_latin1_before_any_work(tmp_path, capsys, monkeypatch):
    from coiltrack.tools.calibration import fits as calibrate

    monkeypatch.setitem(calibrate.RECORDERS, "grid", lambda *a: pytest.fail("work started"))
    p = tmp_path / "old.toml"
    p.write_bytes(("# 20 \u00b0C\n" + CALIBRATION).encode("latin-1"))
    _refused(["calibrate", "--method", "grid", "--record", "--merge", str(p), "--out", str(tmp_path / "o.toml")],
             capsys, "--merge", p, "line 1")


@pytest.mark.parametrize("text,named", [
    ("", "is empty"), (" \n\n", "is empty"),
    ("[timing]\npulse_us = 1\npulse_us = 2\n", "line 3"),
    ("[fusion]\nmag_sigma_t = nan\n", "fusion.mag_sigma_t"),
    ("[timing]\npulse_us = \"long\"\n", "timing.pulse_us"),
    ("[timing]\npulse_us = 50000", None),                 # cut before its newline, still whole TOML: taken
    ("[timing]\npulse_us = 5", "timing.pulse_us"),       # cut inside the number: the range check refuses it
    ("[timing]\npulse_", "line 2"),                                  # cut mid-key
])
def test_bench_config_damage_is_refused_naming_the_file_and_the_line_or_key(text, named, tmp_path, capsys,
                                                                              monkeypatch):
    from coiltrack.tools.commands import bench as cmd_bench

    monkeypatch.setattr(cmd_bench, "_run", lambda *a: pytest.fail("work started") if named else {"stop": 1})
    p = tmp_path / "c.toml"
    p.write_text(text, encoding="utf-8")
    argv = ["bench", "--scenario", "static", "--duration", "0.1", "--config", str(p)]
    if named is None:
        from coiltrack.tools.scenarios import get
        from coiltrack.tools.inputs.userconfig import load_over

        assert load_over(p, get("static").firmware_config()).timing.pulse_us == 50000
        return
    _refused(argv, capsys, "--config", p, named)


def test_an_empty_calibration_file_is_refused_not_taken_as_none(tmp_path, capsys):
    for text, named in (("", "is empty"), ("# nothing yet\n", "no calibration table")):
        p = tmp_path / "cal.toml"
        p.write_text(text)
        _refused(["bench", "--scenario", "static", "--duration", "0.1", "--calibration", str(p)], capsys,
                 "--calibration", p, named)


@PROPERTY
@given(data=st.data())
def test_truncated_or_mangled_config_is_a_config_or_the_clean_error(data, tmp_path_factory):
    from coiltrack.tools.inputs.userconfig import load_over

    good = (open_example("firmware.toml")).encode()
    cut = data.draw(st.integers(0, len(good)))
    blob = good[:cut]
    if data.draw(st.booleans()):
        at = data.draw(st.integers(0, len(blob)))
        blob = blob[:at] + data.draw(st.binary(min_size=1, max_size=4)) + blob[at:]
    p = tmp_path_factory.mktemp("cfg") / "c.toml"
    p.write_bytes(blob)
    try:
        assert isinstance(load_over(p, FirmwareConfig()), FirmwareConfig)
    except (InputFileError, ConfigError) as exc:
        assert "\n" not in str(exc)


def open_example(name: str) -> str:
    from pathlib import Path

    return (Path(__file__).resolve().parents[2] / "examples" / name).read_text()


@PROPERTY
@given(cut=st.integers(0, len(CALIBRATION.encode())))
def test_every_truncation_of_a_calibration_file_is_a_calibration_or_a_one_line_refusal(cut, tmp_path_factory):
    from coiltrack.tools.inputs.calibfile import with_calibration

    p = tmp_path_factory.mktemp("cal") / "cal.toml"
    p.write_bytes(CALIBRATION.encode()[:cut])
    out = with_calibration(p, FirmwareConfig())
    assert isinstance(out, FirmwareConfig) or (isinstance(out, str) and str(p) in out and "\n" not in out)


# ---------------------------------------------------------------- pose table and plot

def test_plot_uses_a_pose_table_cut_mid_line_up_to_the_cut(run_files, tmp_path, capsys):
    data = (run_files / "poses.csv").read_bytes()
    n_rows = data.count(b"\n") - 1
    cut = tmp_path / "cut.csv"
    cut.write_bytes(data[:data.index(b"\n", len(data) // 2) + 20])        # mid-line, about half the rows
    assert main(["plot", str(cut), "-o", str(tmp_path / "x.png")]) == 0
    err = capsys.readouterr().err
    line = data[:data.index(b"\n", len(data) // 2) + 20].count(b"\n") + 1
    assert f"warning: {cut}: line {line}: cut short" in err and f"using the {line - 2} rows" in err
    assert 0 < line - 2 < n_rows


@pytest.mark.parametrize("edit,named", [
    (lambda d: b"", "is empty"),
    (lambda d: d[:d.index(b"\n") + 1], "no pose row"),
    (lambda d: d[:40], "line 1"),
    (lambda d: d.replace(b"t_us,", b"time,", 1), "no column t_us"),
    (lambda d: "\u00b0".encode("latin-1") + d, "line 1"),
    (lambda d: d.decode().encode("utf-16"), "UTF-16"),
])
def test_plot_refuses_a_pose_table_with_nothing_usable(edit, named, run_files, tmp_path, capsys, monkeypatch):
    from coiltrack.tools.outputs import plot

    monkeypatch.setattr(plot, "plot_run", lambda *a, **k: pytest.fail("drawn"))
    p = tmp_path / "p.csv"
    p.write_bytes(edit((run_files / "poses.csv").read_bytes()))
    _refused(["plot", str(p), "-o", str(tmp_path / "x.png")], capsys, p, named)


@pytest.mark.parametrize("column,value,why", [("true_x_mm", "inf", "finite"), ("t_us", "nan", "finite"),
                                              ("sensor", "x", "not a number"), ("kind", "both", "kind"),
                                              ("status", "1.5", "whole number"), ("pos_err_mm", "-inf", "infinite")])
def test_a_bad_value_ends_the_pose_table_at_its_row(column, value, why, run_files, tmp_path):
    from coiltrack.tools.outputs.posecsv import COLUMNS, read_csv

    lines = (run_files / "poses.csv").read_text().splitlines(keepends=True)
    cells = lines[3].rstrip("\r\n").split(",")
    cells[COLUMNS.index(column)] = value
    lines[3] = ",".join(cells) + "\r\n"
    p = tmp_path / "p.csv"
    p.write_text("".join(lines))
    said = []
    table = read_csv(p, said.append)
    assert len(table["t_us"]) == 2 and said == [f"line 4: {said[0].split(': ', 1)[1]}"] and why in said[0]
    with pytest.raises(InputFileError, match=f"line 4: .*{why}"):
        read_csv(p)


@PROPERTY
@given(data=st.data())
def test_a_truncated_pose_table_gives_a_prefix_of_its_rows(data, run_files, tmp_path_factory):
    from coiltrack.tools.outputs.posecsv import read_csv

    good = (run_files / "poses.csv").read_bytes()
    whole = read_csv(run_files / "poses.csv")
    blob = good[:data.draw(st.integers(0, len(good)))]
    p = tmp_path_factory.mktemp("pc") / "p.csv"
    p.write_bytes(blob)
    try:
        t = read_csv(p, lambda m: None)
    except InputFileError as exc:
        assert str(exc).startswith(str(p))
        return
    n = len(t["t_us"])
    assert 1 <= n <= len(whole["t_us"])
    for c in ("t_us", "x_mm", "true_qz", "var_rz_rad2"):
        np.testing.assert_array_equal(t[c], whole[c][:n])


@PROPERTY
@given(blob=st.binary(max_size=400))
def test_arbitrary_bytes_as_a_pose_table_are_a_table_or_the_clean_error(blob, tmp_path_factory):
    from coiltrack.tools.outputs.posecsv import COLUMNS, read_csv

    p = tmp_path_factory.mktemp("pa") / "p.csv"
    p.write_bytes(",".join(COLUMNS).encode() + b"\r\n" + blob)
    try:
        t = read_csv(p, lambda m: None)
    except InputFileError:
        return
    assert all(np.isfinite(t["t_us"])) and set(t["kind"]) <= {"magnetic", "fused"}


def test_plot_of_a_damaged_report_names_the_file_and_the_key(tmp_path, capsys):
    p = tmp_path / "r.json"
    for text, named in (('{"scenario": "static", "by_range": {"10-15cm": {"position_rms_mm": "x"}}}',
                         "by_range.10-15cm.position_rms_mm"),
                        ('{"scenario": "static", "scenario": "x"}', "scenario"),
                        ('{"scenario": "static", "position_rms_mm": NaN}', "NaN"),
                        ('{"scenario": "sta', "line 1"), ("", "is empty"), ("[1, 2]", "not a bench report")):
        p.write_text(text)
        _refused(["plot", str(p), "-o", str(tmp_path / "x.png")], capsys, p, named)


# ---------------------------------------------------------------- frame logs

def test_perf_on_a_log_cut_before_its_warmup_is_refused_not_a_keyerror(run_files, tmp_path, capsys):
    data = (run_files / "frames.log").read_bytes()
    p = tmp_path / "cut.log"
    p.write_bytes(data[:len(data) // 2])
    err = _refused(["perf", "--log", str(p), "--warmup", "5"], capsys, p, "--warmup 5 s", "no tick to measure")
    assert "p999" not in err


@pytest.mark.parametrize("edit,named", [
    (lambda h: dict(h, tick_us="1000"), "tick_us"),
    (lambda h: dict(h, tick_us=0), "tick_us"),
    (lambda h: dict(h, duration_s=-1), "duration_s"),
    (lambda h: dict(h, config=[]), "config"),
    (lambda h: dict(h, config=dict(h["config"], timing={"pulse_us": "x"})), "config.timing.pulse_us"),
    (lambda h: dict(h, format="other/1"), "line 1"),
])
def test_a_frame_log_header_of_the_wrong_types_is_refused_naming_the_key(edit, named, run_files, tmp_path, capsys):
    lines = (run_files / "frames.log").read_text().splitlines(keepends=True)
    p = tmp_path / "f.log"
    p.write_text(json.dumps(edit(json.loads(lines[0]))) + "\n" + "".join(lines[1:]))
    _refused(["perf", "--log", str(p), "--warmup", "0.1"], capsys, p, named)


def test_a_frame_log_header_with_nan_or_a_key_twice_is_refused(run_files, tmp_path, capsys):
    lines = (run_files / "frames.log").read_text().splitlines(keepends=True)
    p = tmp_path / "f.log"
    for head, named in ((lines[0].replace(f'"duration_s": {RUN_S}', '"duration_s": NaN'), "NaN"),
                        (lines[0].replace('"seed": 1', '"seed": 1, "seed": 2'), "'seed' given twice")):
        assert head != lines[0]
        p.write_text(head + "".join(lines[1:]))
        _refused(["perf", "--log", str(p), "--warmup", "0.1"], capsys, p, "line 1", named)


@pytest.mark.parametrize("bad,why", [(b'{"t": 1.5, "rx": "AA=="}', "tick time"), (b'{"t": T, "rx": "!!"}', "base64"),
                                     (b'{"t": T, "rx": "AA==", "t": T}', "given twice"),
                                     (b'{"t": 0, "rx": "AA=="}', "not before the read above"),
                                     (b"\xb0\n", "not UTF-8"), (b'{"t": NaN, "rx": "AA=="}', "NaN")])
def test_a_bad_read_ends_a_frame_log_with_the_reason(bad, why, run_files, tmp_path):
    from coiltrack.tools.bench.framelog import read_log

    lines = (run_files / "frames.log").read_bytes().splitlines(keepends=True)
    p = tmp_path / "f.log"
    t = str(json.loads(lines[4])["t"]).encode()           # the time of the read before the bad line
    p.write_bytes(b"".join(lines[:5]) + bad.replace(b"T", t).rstrip(b"\n") + b"\n" + b"".join(lines[5:]))
    header, reads = read_log(p)
    assert len(reads) == 4 and header["truncated"]["line"] == 6 and why in header["truncated"]["why"]


@PROPERTY
@given(data=st.data())
def test_a_truncated_or_flipped_frame_log_gives_a_prefix_of_its_reads(data, run_files, tmp_path_factory):
    from coiltrack.tools.bench.framelog import read_log

    good = (run_files / "frames.log").read_bytes()
    _, whole = read_log(run_files / "frames.log")
    blob = bytearray(good[:data.draw(st.integers(0, len(good)))])
    if blob and data.draw(st.booleans()):
        blob[data.draw(st.integers(0, len(blob) - 1))] ^= 1 << data.draw(st.integers(0, 7))
    p = tmp_path_factory.mktemp("fl") / "f.log"
    p.write_bytes(bytes(blob))
    try:
        header, reads = read_log(p)
    except InputFileError as exc:
        assert str(exc).startswith(str(p)) and "\n" not in str(exc)
        return
    # a flipped bit inside a base64 payload may still decode (to other bytes): compare the times
    assert [t for t, _ in reads] == [t for t, _ in whole[:len(reads)]]
    assert math.isfinite(header["duration_s"]) and header["duration_s"] <= RUN_S


# ---------------------------------------------------------------- captures

@pytest.mark.parametrize("suffix", ["bin", "asc", "log", "blf"])
def test_decode_uses_a_cut_capture_up_to_the_cut_and_says_so(suffix, run_files, tmp_path, capsys):
    from coiltrack.protocol.capture import decode_file

    whole = decode_file(run_files / f"cap.{suffix}")
    data = (run_files / f"cap.{suffix}").read_bytes()
    p = tmp_path / f"cut.{suffix}"
    at = len(data) * 2 // 3
    while data[at - 1:at] in (b"\n", b"\x00"):
        at += 1
    p.write_bytes(data[:at])
    assert main(["decode", str(p)]) == 0
    err = capsys.readouterr().err
    assert f"warning: {p}: " in err and "cut short" in err and "\n" == err[-1] and err.count("\n") == 1
    part = decode_file(p)
    assert 0 < len(part.items) < len(whole.items)
    assert [it.msg for it in part.items][:-2] == [it.msg for it in whole.items][:len(part.items) - 2]


@pytest.mark.parametrize("suffix", ["bin", "asc", "log", "blf", "trc", "csv"])
def test_decode_refuses_an_empty_capture(suffix, tmp_path, capsys):
    p = tmp_path / f"e.{suffix}"
    p.write_bytes(b"")
    _refused(["decode", str(p)], capsys, p, "is empty")


def test_decode_refuses_a_blf_with_nothing_readable(run_files, tmp_path, capsys):
    p = tmp_path / "h.blf"
    p.write_bytes((run_files / "cap.blf").read_bytes()[:100])
    _refused(["decode", str(p)], capsys, p, "cut short", "nothing readable")
    p.write_bytes(b"LOGG" + bytes(40))
    _refused(["decode", str(p)], capsys, p)


@PROPERTY
@given(data=st.data())
def test_a_truncated_or_mangled_capture_decodes_or_is_refused_cleanly(data, run_files, tmp_path_factory):
    from coiltrack.protocol.capture import CaptureFileError, CaptureResult, decode_file

    suffix = data.draw(st.sampled_from(["bin", "asc", "log", "blf"]))
    good = (run_files / f"cap.{suffix}").read_bytes()
    blob = bytearray(good[:data.draw(st.integers(0, len(good)))])
    for _ in range(data.draw(st.integers(0, 3))):
        if blob:
            blob[data.draw(st.integers(0, len(blob) - 1))] = data.draw(st.integers(0, 255))
    p = tmp_path_factory.mktemp("cap") / f"c.{suffix}"
    p.write_bytes(bytes(blob))
    try:
        res = decode_file(p)
    except CaptureFileError as exc:
        assert str(exc).startswith(str(p)) and "\n" not in str(exc)
        return
    assert isinstance(res, CaptureResult) and (res.damage is None or "\n" not in res.damage)


# ---------------------------------------------------------------- sweep files

RUNS = [{"seed": s, "params": {"pulse_us": p}, "figures": {"position_rms_mm": 1.0 + s / 10 + p / 1e5,
                                                           "poses": 10 + s, "crlb_mm": None}}
        for p in (40000, 60000) for s in (1, 2, 3)]


@pytest.fixture
def sweep_files(tmp_path):
    from coiltrack.tools.commands.sweep import write_csv

    doc = {"scenario": "static", "interrupted": False, "runs": RUNS, "summary": []}
    (tmp_path / "s.json").write_text(json.dumps(doc))
    write_csv(RUNS, tmp_path / "s.csv")
    return tmp_path


def test_sweep_files_read_back_as_written(sweep_files):
    from coiltrack.tools.inputs.sweepfile import read_csv, read_json

    assert read_json(sweep_files / "s.json")["runs"] == RUNS
    assert read_csv(sweep_files / "s.csv") == RUNS


@pytest.mark.parametrize("edit,key", [
    (lambda d: d.update(runs={}), "runs"), (lambda d: d["runs"][2].update(seed="3"), "runs[2].seed"),
    (lambda d: d["runs"][1].update(figures=[1]), "runs[1].figures"), (lambda d: d.pop("scenario"), "scenario"),
    (lambda d: d["runs"][0]["figures"].update(poses="ten"), "runs[0].figures.poses"),
])
def test_a_sweep_json_of_the_wrong_shape_is_refused_naming_the_key(edit, key, sweep_files, capsys):
    from coiltrack.tools.analyses import pareto

    p = sweep_files / "s.json"
    d = json.loads(p.read_text())
    edit(d)
    p.write_text(json.dumps(d))
    assert pareto.main([str(p)]) == 2
    err = capsys.readouterr().err
    assert f"{p}: key '{key}'" in err and err.count("\n") == 1


@PROPERTY
@given(data=st.data())
def test_a_truncated_sweep_csv_gives_a_prefix_of_its_runs_and_its_json_the_clean_error(data, tmp_path_factory):
    from coiltrack.tools.commands.sweep import write_csv
    from coiltrack.tools.inputs.sweepfile import read_csv, read_json

    d = tmp_path_factory.mktemp("sw")
    write_csv(RUNS, d / "s.csv")
    good = (d / "s.csv").read_bytes()
    (d / "c.csv").write_bytes(good[:data.draw(st.integers(0, len(good)))])
    try:
        runs = read_csv(d / "c.csv", lambda m: None)
        assert runs == RUNS[:len(runs)] and runs
    except InputFileError as exc:
        assert str(exc).startswith(str(d / "c.csv"))
    text = json.dumps({"scenario": "static", "runs": RUNS}).encode()
    (d / "c.json").write_bytes(text[:data.draw(st.integers(0, len(text) - 1))])
    with pytest.raises(InputFileError):
        read_json(d / "c.json")


def test_load_json_names_a_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="cannot read it"):
        load_json(tmp_path / "none.json")


def test_a_config_naming_a_damaged_calibration_file_is_refused_naming_both(tmp_path, capsys):
    cal = tmp_path / "cal.toml"
    cal.write_bytes(("# 20 \u00b0C\n" + CALIBRATION).encode("latin-1"))
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[calibration]\ncalibration_file = "{cal}"\n')
    _refused(["bench", "--scenario", "static", "--duration", "0.1", "--config", str(cfg)], capsys,
             f"--config {cfg}: key 'calibration.calibration_file': {cal}: line 1")
