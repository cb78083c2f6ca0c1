"""The documentation's generated parts: the reference pages hold every command, option,
scenario and configuration key of the code, and the committed results pages and the README's
headline table are what docs/results/results.json renders to."""
from __future__ import annotations

import argparse
import json
from dataclasses import fields
from pathlib import Path

import pytest

from coiltrack.firmware import config as C
from coiltrack.tools.cli import build_parser
from coiltrack.tools.docsgen import reference as ref
from coiltrack.tools.docsgen import results as R
from coiltrack.tools.scenarios import SCENARIOS

ROOT = Path(__file__).resolve().parents[1]


def _subparsers():
    return next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_commands_page_has_every_command_and_option():
    page = ref.commands_page()
    for name, p in _subparsers().items():
        assert f"\n## coiltrack {name}\n" in page, name
        section = page.split(f"\n## coiltrack {name}\n")[1].split("\n## coiltrack ")[0]
        for a in p._actions:
            for opt in a.option_strings:
                if opt not in ("-h", "--help"):
                    assert opt in section, f"{name} {opt}"
        assert "exit status:" in section


def test_scenarios_page_has_every_scenario_with_its_overrides():
    page = ref.scenarios_page()
    for name in SCENARIOS:
        assert f"\n## {name}\n" in page and f"coiltrack bench --scenario {name} --seed 1" in page
    # a scenario known to change the defaults shows the key it sets (adaptive actuation)
    section = page.split("\n## schepers-adaptive\n")[1].split("\n## ")[0]
    assert "adaptive.actuation = adaptive" in section


def test_configuration_page_has_every_key_with_default_and_range():
    page = ref.configuration_page()
    default = C.FirmwareConfig()
    for sec, keys in C.SECTIONS.items():
        section = page.split(f"\n## {sec}\n")[1].split("\n## ")[0]
        for k in keys:
            assert f"| `{k}` |" in section, f"{sec}.{k}"
    for f in fields(C.CoilConfig):
        assert f"| `{f.name}` |" in page
    row = next(line for line in page.splitlines() if line.startswith("| `pulse_us` |"))
    assert "| 60000 | us |" in row and "must be a positive integer" in row
    # a range written in a loop of validate() reaches every key of the loop
    row = next(line for line in page.splitlines() if line.startswith("| `imu_sample_evals` |"))
    assert "0..1000000" in row
    assert default.timing.pulse_us == 60000


def test_field_comments_read_the_trailing_and_continued_comments():
    meaning = ref.section_meanings()
    assert meaning["timing"]["spacing_us"] == "pulse j starts at cycle start + j * spacing"
    assert meaning["budget"]["windows_budget"].startswith("pulse windows closed per tick")
    assert "16 sensors: 1.2 ms" in meaning["budget"]["windows_budget"]      # the continuation line
    assert meaning["pose"]["working_range_m"].startswith("the working volume")   # the block above


def test_unit_of_reads_the_suffix():
    assert [ref.unit_of(k) for k in ("pulse_us", "mag_sigma_t", "max_current_a", "working_range_m", "fusion")] \
        == ["us", "T", "A", "m", ""]


def test_pages_are_deterministic():
    for make in ref.PAGES.values():
        assert make() == make()


def test_committed_results_render_to_the_committed_pages():
    data = json.loads((ROOT / "docs" / "results" / "results.json").read_text())
    assert data["format"] == R.FORMAT
    assert (ROOT / "docs" / "results" / "index.md").read_text() == R.render_page(data), (
        "docs/results/index.md is out of date: run `coiltrack results --publish --render`")
    table = R.headline_table(data)
    for name in ("README.md", "docs/index.md"):
        assert R.readme_block((ROOT / name).read_text()) == table, (
            f"{name}'s headline table is out of date: run `coiltrack results --publish --render`")
    assert all(f"`{n}`" in table for n in R.HEADLINE)


def test_headline_table_rows_come_from_the_data():
    data = {"runs": [{"scenario": "roetenberg-bench", "seed": 1, "duration_s": 60.0,
                      "command": "coiltrack bench --scenario roetenberg-bench --seed 1",
                      "report": {"position_rms_mm": 12.345, "orientation_rms_deg": 1.5,
                                 "crlb_position_rms_mm": 10.0, "coil_energy_j": 3.0,
                                 "paper": {"source": "T", "position_rms_mm": 7.6}}}]}
    rows = R.headline_table(data).splitlines()
    assert len(rows) == 3
    assert rows[2].startswith("| `roetenberg-bench` | 12.3 mm | 1.50 deg | 10.0 mm | 3.0 J | 7.6 mm (T) |")


def test_update_readme_replaces_only_the_block():
    text = f"a\n{R.BEGIN}\nold\n{R.END}\nb\n"
    assert R.update_readme(text, "new\n") == f"a\n{R.BEGIN}\nnew\n{R.END}\nb\n"
    with pytest.raises(ValueError):
        R.update_readme("no block", "x")


def test_results_command_refuses_bad_arguments(tmp_path, capsys, monkeypatch):
    from coiltrack.tools.cli import main

    with pytest.raises(SystemExit) as e:
        main(["results", "--scenarios", "no-such-scenario"])
    assert e.value.code == 2 and "no-such-scenario" in capsys.readouterr().err
    monkeypatch.chdir(tmp_path)                       # no README.md with its block here
    assert main(["results", "--publish", "--render"]) == 2
    assert "--publish" in capsys.readouterr().err
    (tmp_path / "f").write_text("")
    assert main(["results", "--out", "f", "--scenarios", "static"]) == 2


def test_protocol_table_is_brought_up_to_date():
    from coiltrack.protocol.docgen import BEGIN, END, extract_generated, markdown_table
    from coiltrack.tools.docsgen.__main__ import protocol_text

    stale = f"# spec\n\ntext before\n\n{BEGIN}\n| old | table |\n{END}\n\ntext after\n"
    new = protocol_text(stale)
    assert extract_generated(new) == markdown_table()
    assert new.startswith("# spec\n\ntext before\n\n") and new.endswith(f"{END}\n\ntext after\n")
    assert protocol_text(new) == new
    with pytest.raises(ValueError):
        protocol_text("no block here")


@pytest.mark.parametrize("scenario", ["roetenberg-fusion", "raab-ac", "schepers-adaptive"])
def test_results_core_option_runs_that_core_with_the_same_figures(scenario, tmp_path):
    """`coiltrack results --core python` runs every firmware on the Python reference and the
    page's command says so; the compiled core gives the same figures (every report key but
    ``core`` equal, floats to 1e-9 relative). Fails if the option is dropped on the way to the
    run (both reports would name one core) or if a compiled kernel drifts from its reference."""
    from coiltrack.firmware import core

    if not core.available():
        pytest.skip("the compiled core is not built here")
    from coiltrack.tools.cli import main

    reps = {}
    for impl in ("python", "compiled"):
        out = tmp_path / impl
        assert main(["results", "--scenarios", scenario, "--duration", "2", "--core", impl,
                     "--out", str(out)]) == 0
        run = json.loads((out / "results.json").read_text())["runs"][0]
        assert run["command"].endswith(f"--core {impl}")
        assert run["report"]["core"] == impl
        reps[impl] = run["report"]

    def same(a, b, path):
        if isinstance(a, dict):
            assert set(a) == set(b), path
            for k in a:
                if k != "core":
                    same(a[k], b[k], f"{path}.{k}")
        elif isinstance(a, list):
            assert len(a) == len(b), path
            for i, (x, y) in enumerate(zip(a, b)):
                same(x, y, f"{path}[{i}]")
        elif isinstance(a, float) and isinstance(b, float):
            assert a == pytest.approx(b, rel=1e-9, abs=1e-300), path
        else:
            assert a == b, path

    same(reps["python"], reps["compiled"], scenario)


def test_results_command_refuses_bad_overrides(capsys, monkeypatch, tmp_path):
    """``coiltrack results --set``: an unknown key, a key given twice, several values (a sweep's
    form), an out-of-range value, a firmware key on a Gietler experiment and an override of the
    published results are each refused before anything runs, exit 2, naming what is wrong."""
    from coiltrack.tools.cli import main

    monkeypatch.chdir(tmp_path)                       # nothing written into the checkout if one is run
    for argv, word in ((["--set", "no_such_key=1"], "no_such_key"),
                       (["--set", "track_budget_evals=9", "--set", "budget.track_budget_evals=9"], "twice"),
                       (["--set", "track_budget_evals=9,18"], "one value"),
                       (["--set", "track_budget_evals=0"], "positive"),
                       (["--scenarios", "gietler-air", "--set", "track_budget_evals=18"], "gietler-air"),
                       (["--publish", "--set", "track_budget_evals=18"], "--publish")):
        if "--scenarios" not in argv:
            argv = ["--scenarios", "static", *argv]
        assert main(["results", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert "--set" in err and word in err, (argv, err)


def test_results_override_reaches_the_run_and_its_command():
    """``coiltrack results --set solve_ahead=false --set track_budget_evals=3``
    (``docsgen.results.run_one`` with overrides): the run is made with the overrides (the
    acquisition solved in its turn, not ahead: 1 ms later than solved ahead; at a ninth of the
    default's field evaluations per tick, 8 ms later still; the accuracy is the same, the solves
    being the same), the run records them, and its command is the ``coiltrack sweep`` that gives
    the same figures, the core as ``--set core.impl``. Catches an override dropped on the way to
    the firmware (the same latency) and a command that cannot reproduce the run."""
    base = R.run_one(("static", 1, 1.0, None))
    turn = R.run_one(("static", 1, 1.0, None, (("solve_ahead", False),)))
    low = R.run_one(("static", 1, 1.0, None, (("solve_ahead", False), ("track_budget_evals", 3))))
    assert low["overrides"] == {"solve_ahead": False, "track_budget_evals": 3} and "overrides" not in base
    assert low["report"]["latency_ms_p99"] > turn["report"]["latency_ms_p99"] > base["report"]["latency_ms_p99"]
    assert low["report"]["position_rms_mm"] == turn["report"]["position_rms_mm"] == base["report"]["position_rms_mm"]
    assert low["command"] == ("coiltrack sweep --scenario static --seeds 1 --duration 1 --set solve_ahead=false "
                              "--set track_budget_evals=3")
    assert R.command("static", 1, 1.0, 2.0, core="python", overrides=(("pose.raab_refresh", True),)) == \
        "coiltrack sweep --scenario static --seeds 1 --duration 1 --set pose.raab_refresh=true --set core.impl=python"
    assert R.command("static", 1, 2.0, 2.0, core="python") == "coiltrack bench --scenario static --seed 1 --core python"
