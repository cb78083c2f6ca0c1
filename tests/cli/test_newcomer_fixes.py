"""What stood in a newcomer's way on the command line (issue 32, "Smaller"): each
test failed before its fix.

`--version`; the `sweep --help` example and the figures the swept key moves;
`emulator --create-pty` with a CAN transport; `--interface virtual` between
processes; the emulator's waiting line and its report; `--plot` without a suffix;
the title of a figure drawn from a pose table. All on the simulated clock or
short in-process runs (under a second of emulator wall time).
"""
from __future__ import annotations

import csv
import json
import os
import re
import tomllib
import tty
from pathlib import Path

import pytest

from coiltrack.protocol.codec import MSG
from coiltrack.protocol.framing import encode_frame
from coiltrack.tools.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[2]


def test_version_prints_the_installed_version(capsys):
    """`coiltrack --version`: `coiltrack X.Y.Z`, the version of pyproject.toml (the
    installed metadata comes from it), exit status 0."""
    want = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out == f"coiltrack {want}\n"


# ---------------------------------------------------------------- sweep


def _sweep_help(capsys) -> str:
    with pytest.raises(SystemExit):
        main(["sweep", "--help"])
    return capsys.readouterr().out


def test_sweep_help_example_key_is_accepted(capsys):
    """The key the `--set` help gives as its example is one the sweep accepts (it named
    fusion.mag_sigma_t, which is in [pulse], and was refused)."""
    from coiltrack.tools.commands import sweep as cmd_sweep

    key = re.search(r"e\.g\.\s+([a-z_]+\.[a-z_]+)", " ".join(_sweep_help(capsys).split())).group(1)
    args = build_parser().parse_args(["sweep", "--scenario", "static", "--seeds", "1", "--set",
                                      f"{key}=1e-7,2e-7", "--duration", "1"])
    plan = cmd_sweep._plan(args)                # BadArgument before the fix
    assert [dict(p) for p in plan["grid"]] == [{key: 1e-7}, {key: 2e-7}]


def test_sweep_table_shows_the_figures_the_swept_key_moved(capsys):
    """Sweeping pulse.mag_sigma_t moves only the pose quality figures (none of the
    headline ones): the printed table shows those rows for each grid point, and not a
    figure that no grid point changed. Catches a table where the sweep seems to have
    changed nothing."""
    rc = main(["sweep", "--scenario", "static", "--seeds", "1", "--set", "pulse.mag_sigma_t=1e-7,4e-7",
               "--duration", "2", "--workers", "1"])
    out = capsys.readouterr().out
    assert rc == 0, out
    rows = [line.split() for line in out.splitlines() if line.startswith("  ")]
    quality = [r for r in rows if "quality_mean" in r]
    assert len(quality) == 2, out                 # one per grid point
    medians = {float(r[-3]) for r in quality}
    assert len(medians) == 2                      # it did move
    assert not any("frames_rx" in r for r in rows)     # the same in both: not added


def test_shown_figures_adds_only_what_differs():
    """`shown_figures`: the headline, then the non-headline figures whose medians differ
    between grid points; with one grid point nothing is added."""
    from coiltrack.tools.commands.sweep import shown_figures

    def point(v, q):
        return {"params": {"pulse.mag_sigma_t": v}, "runs": 1,
                "figures": {"position_rms_mm": {"median": 0.85}, "quality_mean": {"median": q},
                            "frames_rx": {"median": 40.0}}}

    assert shown_figures([point(1e-7, 190.2), point(2e-7, 151.4)], ("position_rms_mm",)) == \
        ("position_rms_mm", "quality_mean")
    assert shown_figures([point(1e-7, 190.2)], ("position_rms_mm",)) == ("position_rms_mm",)


# ---------------------------------------------------------------- emulator


def test_emulator_refuses_create_pty_on_can(capsys):
    """`--create-pty` with `--transport can` is refused, naming both (it ran on serial)."""
    rc = main(["emulator", "--transport", "can", "--interface", "slcan", "--create-pty", "--scenario", "static",
               "--duration", "0.2"])
    err = capsys.readouterr().err
    assert rc == 2 and "--create-pty" in err and "--transport can" in err


def test_virtual_interface_is_said_to_be_one_process_only(capsys):
    """`emulator --interface virtual` runs (in one process a virtual bus meets its peers)
    but says on stderr that another process will never hear it; serial and other CAN
    interfaces say nothing."""
    from types import SimpleNamespace

    from coiltrack.tools.bench.links import warn_virtual_bus

    rc = main(["emulator", "--transport", "can", "--interface", "virtual", "--channel", "virtual-warn-test",
               "--scenario", "static", "--duration", "0.2"])
    err = capsys.readouterr().err
    assert rc == 0
    assert "warning: --interface virtual" in err and "socketcan" in err
    assert not warn_virtual_bus(SimpleNamespace(transport="can", interface="socketcan"), "firmware")
    assert not warn_virtual_bus(SimpleNamespace(transport="serial", interface="virtual"), "firmware")
    assert capsys.readouterr().err == ""


def test_firmware_and_conform_warn_on_a_virtual_bus(capsys):
    """The firmware and the conformance tester, the emulator's peers in another process,
    say the same."""
    main(["firmware", "--transport", "can", "--interface", "virtual", "--channel", "virtual-warn-fw",
          "--scenario", "static", "--duration", "0.05", "--peer-timeout", "0", "--stats-json", os.devnull])
    assert "warning: --interface virtual" in capsys.readouterr().err
    main(["conform", "--transport", "can", "--interface", "virtual", "--channel", "virtual-warn-conform",
          "--discover", "0.05", "--observe", "0.05"])
    assert "warning: --interface virtual" in capsys.readouterr().err


def test_emulator_says_what_it_waits_for(capsys):
    """Before its loop the emulator prints, on stderr, one line naming the pty it is on
    (the path it printed on stdout for the firmware) and what it waits for."""
    assert main(["emulator", "--create-pty", "--scenario", "static", "--duration", "0.2"]) == 0
    cap = capsys.readouterr()
    pty = cap.out.splitlines()[0]
    waiting = [line for line in cap.err.splitlines() if "waiting for" in line]
    assert len(waiting) == 1 and f"pty {pty}" in waiting[0] and "TIME_SYNC" in waiting[0]


def test_emulator_report_counts_what_it_received(tmp_path, capsys, monkeypatch):
    """Frames on the emulator's port as it opens it (3 good TIME_SYNCs, one frame with a
    broken CRC): its report counts 3 received and 1 bad, and its table shows no figure
    it cannot know (no pose: no position RMS; no pulse: no battery). It said
    `frames rx / bad 0 / 1`, `position RMS nan mm`, `battery None h`."""
    from coiltrack.tools.bench import links

    master, slave = os.openpty()
    tty.setraw(slave)
    good = [encode_frame(MSG["TIME_SYNC"](1000 * k, k), k, 1) for k in range(3)]
    bad = bytearray(encode_frame(MSG["TIME_SYNC"](5000, 3), 3, 1))
    bad[3] ^= 0x5A                                      # inside the COBS body: the CRC fails
    real_open = links.open_pty_slave

    def open_then_send(path):                           # opening flushes what was pending: send after
        port = real_open(path)
        os.write(master, b"".join(good) + bytes(bad))
        return port

    monkeypatch.setattr(links, "open_pty_slave", open_then_send)
    try:
        rep_path = tmp_path / "emu.json"
        rc = main(["emulator", "--port", os.ttyname(slave), "--scenario", "static", "--duration", "0.15",
                   "--json", str(rep_path)])
    finally:
        os.close(master)
        os.close(slave)
    out = capsys.readouterr().out
    assert rc == 0
    rep = json.loads(rep_path.read_text())
    assert (rep["frames_rx"], rep["frames_bad"]) == (3, 1) and rep["frames_tx"] > 0
    table = {line.split("  ")[1].strip(): line for line in out.splitlines() if line.startswith("  ")}
    assert table["frames rx / bad"].split()[-3:] == ["3", "/", "1"]
    assert "nan" not in out and "None" not in out
    assert "position RMS" not in table and "battery" not in out


# ---------------------------------------------------------------- plot


def _pose_table(path: Path) -> None:
    """A three-pose table (two magnetic, one fused) in the pose-table columns."""
    from coiltrack.tools.outputs.posecsv import COLUMNS

    rows = []
    for k, (kind, err) in enumerate((("magnetic", 3.0), ("fused", 1.0), ("magnetic", 4.0))):
        r = {c: "0" for c in COLUMNS}
        r.update(t_us=str(100_000 * k), t_s=str(0.1 * k), sensor="16", kind=kind,
                 status="3" if kind == "fused" else "1",
                 status_bits="valid", qw="1", true_qw="1", pos_err_mm=str(err), ori_err_deg="0.5",
                 range_mm=str(300 + k), crlb_mm="2", x_mm=str(300 + k))
        rows.append(r)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(COLUMNS))
        w.writeheader()
        w.writerows(rows)


def test_plot_without_suffix_says_the_name_it_wrote(tmp_path, capsys):
    """`plot -o out/noext` writes noext.png (matplotlib's default) and says so; a suffix
    matplotlib cannot write is refused before any work. It said `noext`."""
    table = tmp_path / "run.csv"
    _pose_table(table)
    assert main(["plot", str(table), "-o", str(tmp_path / "noext")]) == 0
    assert capsys.readouterr().out.strip() == f"figure written to {tmp_path / 'noext.png'}"
    assert (tmp_path / "noext.png").is_file() and not (tmp_path / "noext").exists()
    assert main(["plot", str(table), "-o", str(tmp_path / "fig.v2")]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and ".v2" in err


def test_bench_plot_without_suffix_reports_the_name_written(tmp_path, capsys):
    """`bench --plot out/noext` says `figure written to .../noext.png` (and writes it)."""
    rc = main(["bench", "--scenario", "static", "--duration", "1", "--quiet", "--plot", str(tmp_path / "noext")])
    out = capsys.readouterr().out
    assert rc == 0
    assert f"figure written to {tmp_path / 'noext.png'}" in out and (tmp_path / "noext.png").is_file()


def test_plot_title_names_the_file_and_counts(tmp_path, monkeypatch):
    """A figure drawn from a pose table is titled with the file's name and the poses by
    kind with their RMS error (it was "3 poses"); with a report, also the scenario."""
    from matplotlib.figure import Figure

    from coiltrack.tools.outputs.plot import _title

    titles = []
    real = Figure.suptitle
    monkeypatch.setattr(Figure, "suptitle", lambda self, t, **kw: (titles.append(t), real(self, t, **kw))[1])
    table = tmp_path / "run.csv"
    _pose_table(table)
    assert main(["plot", str(table), "-o", str(tmp_path / "f.png")]) == 0
    title = " ".join(titles[0].split())
    assert title.startswith("run.csv: 3 poses: 2 magnetic (3.54 mm RMS), 1 fused (1.00 mm RMS)"), title
    from coiltrack.tools.outputs.posecsv import read_csv

    t = _title({"scenario": "static", "seed": 1, "transport": "inproc", "position_rms_mm": 3.5},
               read_csv(table), "run.csv")
    assert t.startswith("run.csv, static seed 1 (inproc): 3 poses") and "position RMS 3.5 mm" in t
