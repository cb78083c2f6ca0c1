"""`coiltrack sweep` on the Gietler experiments: the levels table of the JSON document, the
noise level reaching both the emulated noise and the filters, and bad values refused."""
from __future__ import annotations

import json

import pytest

from coiltrack.tools.cli import main

SWEEP = ["sweep", "--scenario", "gietler-air", "--seeds", "1-2", "--duration", "3", "--workers", "1"]


def test_levels_table_per_noise_level(tmp_path):
    """Two levels x two seeds: ``levels`` (iterated EKF) and ``levels_ekf`` (plain EKF) each have
    one row per level with the mean of the runs' MSE, their divergences and the paper's value. Catches the level not reaching the runs, rows grouped
    wrongly, or the MSE of one filter reported under the other's key."""
    out = tmp_path / "t.json"
    assert main([*SWEEP, "--set", "noise.var=1e-2,1e-4", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    for key, suffix in (("levels", ""), ("levels_ekf", "_ekf")):
        rows = doc[key]
        assert [r["noise_var"] for r in rows] == [1e-2, 1e-4]
        assert [r["paper_mse_m2"] for r in rows] == [0.0518, 0.0028]
        for r in rows:
            runs = [x["figures"] for x in doc["runs"] if x["params"]["noise.var"] == r["noise_var"]]
            assert r["runs"] == len(runs) == 2
            ok = [f["mse_m2" + suffix] for f in runs if f["mse_m2" + suffix] is not None]
            assert r["mse_m2"] == pytest.approx(sum(ok) / len(ok), rel=1e-12)
            assert r["divergences"] == sum(f["diverged" + suffix] for f in runs)
        assert rows[1]["mse_m2"] != rows[0]["mse_m2"]
    assert "levels_base" not in doc          # air: one model
    assert doc["paper"]["base"][0] == 0.1210


@pytest.mark.parametrize("extra, word", [
    (["--set", "noise.var=-1"], "noise.var"),
    (["--set", "noise.sigma=1"], "noise.sigma"),
    (["--set", "gietler.gietler_iterations=0"], "gietler.gietler_iterations"),
])
def test_bad_values_refused_before_any_run(extra, word, capsys):
    """A bad noise level or filter key: exit 2 with a message naming it (nothing run)."""
    assert main([*SWEEP, *extra]) == 2
    assert word in capsys.readouterr().err


def test_bench_refuses_a_gietler_scenario(capsys):
    """`coiltrack bench --scenario gietler-air` is refused (exit 2) and points at sweep: the
    scenario has no bench world."""
    assert main(["bench", "--scenario", "gietler-air"]) == 2
    assert "coiltrack sweep" in capsys.readouterr().err
