"""What a new user finds: scenarios in --help, exit codes in --help and
docs/cli.md, which extra to install, the example configuration, the emulator
on a CAN bus."""
from __future__ import annotations

import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from coiltrack.tools import commands, scenarios
from coiltrack.tools.cli import build_parser, exit_codes, main, subcommands

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "firmware.toml"


def _help(command: str, capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    return capsys.readouterr().out


def test_bench_help_lists_every_scenario_on_one_line(capsys):
    text = _help("bench", capsys)
    listed = text.split("scenarios:\n")[1].split("\n\n")[0].splitlines()
    assert [line.split()[0] for line in listed] == sorted(scenarios.SCENARIOS)
    for line in listed:
        name, summary = line.split(None, 1)
        assert len(summary) > 20 and summary == (scenarios.SCENARIOS[name].summary or
                                                 scenarios.SCENARIOS[name].description)


@pytest.mark.parametrize("command", subcommands())
def test_every_command_documents_its_exit_codes(command, capsys):
    mod = commands.load(command)
    name = commands.name_of(mod)
    text = _help(name, capsys).split("exit status:\n")[1]
    doc = (ROOT / "docs" / "cli.md").read_text()
    section = doc.split(f"## coiltrack {name}\n")[1].split("\n## ")[0]
    for code in exit_codes(mod):
        assert f"  {code:>3}  " in text
        assert f"| {code} |" in section, f"docs/cli.md: exit status {code} of {name}"


def test_every_command_is_in_the_parser():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert sorted(sub.choices) == sorted(commands.name_of(commands.load(c)) for c in subcommands())


def test_the_registry_lists_every_command_module_and_nothing_else():
    """A command is found by the registry (``commands.COMMANDS``), not by its file name: a
    module of the package left out of it (or a name in it with no module) is caught here."""
    here = ROOT / "tools" / "commands"
    modules = sorted(p.stem for p in here.glob("*.py") if p.stem != "__init__")
    assert sorted(commands.COMMANDS) == modules
    for m in modules:
        mod = commands.load(m)
        assert callable(mod.run) and callable(mod.add_arguments) and mod.HELP, m
    with pytest.raises(KeyError, match="not a command module"):
        commands.load("cli")


def test_without_the_bench_extra_the_commands_name_it(tmp_path):
    """magpylib and cantools missing (as after ``pip install coiltrack``): a one-line message
    naming the extra, exit 2, no traceback; one subprocess runs the four commands."""
    log = tmp_path / "x.log"
    log.write_text('{"format": "coiltrack-frames/1"}\n')
    code = ("import sys; sys.modules['magpylib'] = None; sys.modules['cantools'] = None\n"
            "from coiltrack.tools.cli import main\n"
            f"for argv in (['bench', '--duration', '1'], ['emulator', '--create-pty'], ['smooth', {str(log)!r}], "
            "['dbc']):\n"
            "    print(main(argv))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.stdout.split() == ["2", "2", "2", "2"], p.stderr
    err = p.stderr.strip().splitlines()
    assert len(err) == 4 and "Traceback" not in p.stderr
    for line, cmd, pkg in zip(err, ("bench", "emulator", "smooth", "dbc"), ("magpylib", "magpylib", "magpylib", "cantools")):
        assert line == (f"coiltrack {cmd}: needs the package '{pkg}', which is not installed: "
                        "pip install 'coiltrack[bench]'")


def test_the_example_configuration_runs_a_bench(tmp_path, capsys):
    from coiltrack.firmware.config import FirmwareConfig
    from coiltrack.tools.inputs.userconfig import load_over

    cfg = load_over(EXAMPLE, FirmwareConfig())
    assert cfg == FirmwareConfig()            # the example spells out the thesis bench
    out = tmp_path / "r.json"
    assert main(["bench", "--scenario", "static", "--duration", "2", "--quiet", "--config", str(EXAMPLE),
                 "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["poses"] >= 2 and rep["poses_invalid"] == 0 and rep["position_rms_mm"] < 5.0


def test_a_config_file_goes_over_the_scenarios_configuration(tmp_path):
    from coiltrack.tools.inputs.userconfig import load_over

    path = tmp_path / "c.toml"
    path.write_text("[timing]\nlead_us = 40000\n[pulse]\nmag_sigma_t = 1e-7\n")
    base = scenarios.get("roetenberg-fusion").firmware_config()
    cfg = load_over(path, base)
    assert cfg.timing.lead_us == 40_000 and cfg.pulse.mag_sigma_t == 1e-7
    assert cfg.imu.imu_rate_hz == base.imu.imu_rate_hz == 120.0          # the scenario's, not the default 100


def test_bench_config_changes_the_run(tmp_path):
    """Twice the cycle: cycles start at 0.2 s + k * cycle, so in 3 s five of 0.6 s and three
    of 1.2 s, each of three pulses."""
    path = tmp_path / "c.toml"
    path.write_text("[timing]\ncycle_us = 1200000\n")
    reps = []
    for extra in ([], ["--config", str(path)]):
        out = tmp_path / f"r{len(reps)}.json"
        assert main(["bench", "--scenario", "static", "--duration", "3", "--quiet", "--json", str(out), *extra]) == 0
        reps.append(json.loads(out.read_text()))
    assert (reps[0]["coil_pulses"], reps[1]["coil_pulses"]) == (15, 9)


def test_the_emulator_talks_on_a_can_bus(capsys):
    """``emulator --transport can``: the nodes' heartbeats reach another station on the bus."""
    import can

    from coiltrack.protocol.can import CanReassembler

    listener = can.Bus(interface="virtual", channel="emulator-test", receive_own_messages=False)
    try:
        assert main(["emulator", "--transport", "can", "--interface", "virtual", "--channel", "emulator-test",
                     "--scenario", "static", "--duration", "0.3"]) == 0
        r = CanReassembler()
        senders = set()
        while (f := listener.recv(timeout=0)) is not None:
            senders |= {hdr.src for hdr, msg in r.feed_with_headers(f) if msg.NAME == "HEARTBEAT"}
    finally:
        listener.shutdown()
    assert {2, 16} <= senders
    assert ["transport", "can"] in [line.split() for line in capsys.readouterr().out.splitlines()]
