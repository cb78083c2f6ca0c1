"""Issue 33's criterion on the mean over bench draws (``tools/analyses/adaptive_draws.py``): the
per-seed means and standard errors against hand-computed figures, the verdicts at their edges, the
"done when" items, and bad input refused with status 2."""
import json
import math

import pytest

from coiltrack.tools.analyses import adaptive_draws as ad

SETTING = {"pulse_length": "chosen", "unreached_share": 0.8}


def _run(seed, draw, e, p, o, params=SETTING):
    pr = dict(params)
    if draw:
        pr["bench.noise_draw"] = draw
    return {"seed": seed, "params": pr,
            "figures": {"energy_ratio": e, "position_rms_ratio": p, "orientation_rms_ratio": o}}


def _doc(runs, duration=60.0):
    return {"scenario": ad.SCENARIO, "duration_s": duration, "runs": runs}


def test_mean_and_standard_error_over_draws():
    """Seed 1's orientation ratios 1.0, 1.2, 1.4 over draws 0-2: mean 1.2, sample sd 0.2, se
    0.2 / sqrt 3 = 0.11547; at z 1.645 the interval 1.01-1.39 straddles 1.1: open. Position 0.9,
    0.92, 0.94: se 0.011547, 0.92 + 0.019 <= 1.1: held. Draws read from two files (the draw from
    ``bench.noise_draw``, 0 without)."""
    a = _doc([_run(1, 0, 0.8, 0.9, 1.0), _run(1, 1, 0.82, 0.92, 1.2)])
    b = _doc([_run(1, 2, 0.84, 0.94, 1.4)])
    runs, setting = ad.gather([("a", a), ("b", b)])
    assert sorted(runs[1]) == [0, 1, 2] and setting["params"] == SETTING
    row, = ad.per_seed(runs, 1.645)
    assert row["orientation_rms_ratio"] == pytest.approx(1.2)
    assert row["orientation_rms_ratio_se"] == pytest.approx(0.2 / math.sqrt(3))
    assert row["orientation_rms_ratio_verdict"] == "open"
    assert row["position_rms_ratio_se"] == pytest.approx(0.02 / math.sqrt(3))
    assert row["position_rms_ratio_verdict"] == "held"
    assert row["energy_ratio"] == pytest.approx(0.82)


def test_verdicts_at_their_edges():
    """held when mean + z se <= 1.1, missed when mean - z se > 1.1, else open; one draw on its value."""
    assert ad.verdict(1.0, 0.05, 1.1, 2.0) == "held"          # 1.0 + 0.1 = 1.1 exactly
    assert ad.verdict(1.0, 0.0501, 1.1, 2.0) == "open"
    assert ad.verdict(1.21, 0.05, 1.1, 2.0) == "missed"
    assert ad.verdict(1.2, 0.05, 1.1, 2.0) == "open"          # 1.2 - 0.1 = 1.1: not above it
    assert ad.verdict(1.1, None, 1.1, 1.645) == "held" and ad.verdict(1.1001, None, 1.1, 1.645) == "missed"


def test_done_when_items_on_the_means():
    """Three seeds: energies 0.45, 0.55, 0.61 (median 0.55 > 0.50: not met for chosen lengths;
    for 60 ms pulses 0.55 <= 0.60 but worst 0.61 <= 0.70: met); floors 0.5, 0.5, 0.5 give x0.9,
    x1.1, x1.22: two within 1.15."""
    runs = {s: {0: {"energy_ratio": e, "position_rms_ratio": 1.0, "orientation_rms_ratio": o},
                1: {"energy_ratio": e, "position_rms_ratio": 1.0, "orientation_rms_ratio": o}}
            for s, e, o in ((1, 0.45, 1.0), (2, 0.55, 1.05), (3, 0.61, 1.3))}
    rows = ad.per_seed(runs, 1.645, {1: 0.5, 2: 0.5, 3: 0.5})
    assert [r["x_floor"] for r in rows] == pytest.approx([0.9, 1.1, 1.22])
    s = ad.done_when(rows, "chosen")
    assert s["energy_median"] == pytest.approx(0.55) and s["energy_worst"] == pytest.approx(0.61)
    assert not s["energy_met"] and ad.done_when(rows, "fixed")["energy_met"]
    assert s["floor_within"] == 2
    # equal draws: se 0, so the verdict is the value's
    assert (s["orientation_mean_within"], s["orientation_held"], s["orientation_missed"]) == (2, 2, 1)
    assert s["position_held"] == 3 and not s["accuracy_met"]


def test_inconsistent_sweeps_are_refused(tmp_path, capsys):
    """Another setting, another duration, the same draw twice with other figures: refused, named."""
    a = _doc([_run(1, 0, 0.8, 0.9, 1.0)])
    with pytest.raises(ad.DrawsError, match="not the setting"):
        ad.gather([("a", a), ("b", _doc([_run(1, 1, 0.8, 0.9, 1.0, {"pulse_length": "fixed"})]))])
    with pytest.raises(ad.DrawsError, match="20 s"):
        ad.gather([("a", a), ("b", _doc([_run(1, 1, 0.8, 0.9, 1.0)], 20.0))])
    with pytest.raises(ad.DrawsError, match="twice"):
        ad.gather([("a", a), ("b", _doc([_run(1, 0, 0.7, 0.9, 1.0)]))])
    p = tmp_path / "s.json"
    p.write_text(json.dumps({**a, "scenario": "raab-ac"}))
    assert ad.main(["--from", str(p)]) == 2
    assert "schepers-adaptive" in capsys.readouterr().err
    assert ad.main([]) == 2
    assert ad.main(["--run", "--set", "a=1,2", "--out", str(tmp_path / "o.json")]) == 2
    assert "KEY=VALUE" in capsys.readouterr().err


def test_the_command_prints_the_items(tmp_path, capsys):
    p = tmp_path / "s.json"
    p.write_text(json.dumps(_doc([_run(1, 0, 0.8, 0.9, 1.0), _run(1, 1, 0.8, 0.9, 1.1)])))
    out = tmp_path / "o.json"
    assert ad.main(["--from", str(p), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "orientation within 10 %" in text and "chosen pulse length" in text
    doc = json.loads(out.read_text())
    assert doc["rows"][0]["orientation_rms_ratio"] == pytest.approx(1.05)
