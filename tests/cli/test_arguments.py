"""Every argument is checked when the command line is parsed: one line naming
the argument and the accepted range, exit status 2, before any work."""
from __future__ import annotations

import pytest

from coiltrack.tools.bench import runner
from coiltrack.tools.cli import main


def _refused(argv, capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize("argv, arg, accepted", [
    (["bench", "--duration", "nan"], "--duration", "(0, 3600]"),
    (["bench", "--duration", "inf"], "--duration", "(0, 3600]"),
    (["bench", "--duration", "1e9"], "--duration", "(0, 3600]"),
    (["bench", "--duration", "-2"], "--duration", "(0, 3600]"),
    (["bench", "--seed", "-1"], "--seed", "[0, 4294967295]"),
    (["bench", "--scenario", "nope"], "--scenario", "static"),
    (["emulator", "--create-pty", "--duration", "0"], "--duration", "(0, 604800]"),
    (["emulator", "--port", "loop://"], "--port", "loop://"),
    (["busload", "--bitrate", "0"], "--bitrate", "[1, 100000000]"),
    (["busload", "--nodes", "49"], "--nodes", "[0, 48]"),
    (["busload", "--cycle-ms", "0"], "--cycle-ms", "(0, 3600000]"),
    (["firmware", "--port", "loop://", "--duration", "-5"], "--duration", "[0, 604800]"),
    (["firmware", "--port", "loop://", "--peer-timeout", "nan"], "--peer-timeout", "[0, 3600]"),
    (["perf", "--warmup", "-1"], "--warmup", "[0, 3600]"),
    (["perf", "--repeat", "0"], "--repeat", "[1, 20]"),
    (["conform", "--port", "x", "--node", "256"], "--node", "[0, 255]"),
    (["bench", "--key", " "], "--key", "the signing key is empty"),
    (["bench", "--key", "@/no/such/key"], "--key", "cannot read the key file"),
    (["firmware", "--port", "loop://", "--key", "@env"], "--key", "COILTRACK_SIGNING_KEY is not set"),
])
def test_bad_values_are_refused_with_the_argument_and_its_range(argv, arg, accepted, capsys, monkeypatch):
    monkeypatch.delenv("COILTRACK_SIGNING_KEY", raising=False)
    line = _refused(argv, capsys)
    assert line.startswith(f"coiltrack {argv[0]}: error: argument {arg}")
    assert accepted in line


@pytest.mark.parametrize("argv", [
    ["bench", "--json"], ["bench", "--log"], ["emulator", "--create-pty", "--json"],
    ["firmware", "--port", "loop://", "--stats-json"], ["perf", "--json"], ["dbc", "-o"],
    ["conform", "--port", "x", "--json"],
])
def test_output_paths_are_checked_before_the_work(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(runner, "run_inproc", lambda *a, **k: pytest.fail("the run started"))
    line = _refused(argv + [str(tmp_path / "no-such-dir" / "out.json")], capsys)
    assert "cannot write" in line and "No such file or directory" in line


def test_an_output_path_that_is_a_directory_is_refused(tmp_path, capsys):
    assert "is a directory" in _refused(["bench", "--json", str(tmp_path)], capsys)


def test_output_path_check_leaves_no_file_behind(tmp_path, capsys):
    out = tmp_path / "r.json"
    _refused(["bench", "--json", str(out), "--seed", "-1"], capsys)
    assert not out.exists()


def test_smooth_out_path_checked(fusion_log, tmp_path, capsys):
    line = _refused(["smooth", str(fusion_log), "--out", str(tmp_path / "nope" / "p.jsonl")], capsys)
    assert "argument --out" in line


def test_missing_input_file_is_refused(tmp_path, capsys):
    line = _refused(["decode", str(tmp_path / "missing.bin")], capsys)
    assert "cannot read" in line


def test_a_fault_on_a_coil_the_source_lacks_is_refused(capsys, monkeypatch):
    monkeypatch.setattr(runner, "run_inproc", lambda *a, **k: pytest.fail("the run started"))
    assert main(["bench", "--scenario", "static", "--faults", "open_circuit=7@2s"]) == 2
    err = capsys.readouterr().err
    assert "--faults" in err and "coil 7" in err and "0..2" in err


def test_a_fault_on_the_last_coil_is_accepted():
    from coiltrack.tools.scenarios import get

    f = runner.parse_faults("open_circuit=2@2s,overheat=0@1s", get("static"))
    assert [x.target for x in f.timed] == [2, 0]
    with pytest.raises(ValueError, match="coil 3"):
        runner.parse_faults("short=3@1s", get("static"))


@pytest.mark.parametrize("text", ["drop=nan", "delay_ms=x", "metal_d=inf@3s", "open_circuit=-1@2s", "sag=0@1s"])
def test_bad_fault_values_are_refused(text, capsys):
    assert main(["bench", "--scenario", "static", "--duration", "1", "--faults", text]) == 2
    assert capsys.readouterr().err.startswith("coiltrack bench: --faults:")


@pytest.mark.parametrize("toml, key", [
    ('[link]\nsensor_ids = ["a"]\n', "link.sensor_ids"),
    ('[[source.coils]]\nradius = "x"\n', "source.coils[0].radius"),
    ('[[source.coils]]\ncurrent = "1"\n', "source.coils[0].current"),
    ('[source]\nhemisphere = ["a", 0, 0]\n', "source.hemisphere"),
    ('[timing]\npulse_us = "x"\n', "timing.pulse_us"),
    ('[timing]\nno_such_key = 1\n', "timing.no_such_key"),
    ('pulse_us = 3\n', "timing.pulse_us"),
    ('[timing]\npulse_us = \n', "line 2: not valid TOML"),     # the file's line, not a key
    ('[signing]\nsigning_link_id = 300\n', "signing.signing_link_id"),
])
@pytest.mark.parametrize("command", [["bench", "--scenario", "static"], ["firmware", "--port", "loop://"]])
def test_config_values_are_refused_naming_the_key(command, toml, key, tmp_path, capsys):
    path = tmp_path / "cfg.toml"
    path.write_text(toml)
    assert main(command + ["--config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    named = f"--config {path}: {key}" if key.startswith("line") else f"config key '{key}'"
    assert len(err.splitlines()) == 1 and named in err, err
