"""The energy-accuracy front with the bound (``tools/analyses/front_plot.py``) on hand-made files."""
import json

import pytest

from coiltrack.tools.analyses import front_plot as fp


def _sweep(path, scenario, runs):
    path.write_text(json.dumps({"scenario": scenario, "interrupted": False, "runs": runs}))
    return str(path)


def _run(seed, params, e, p, o, fixed=None):
    f = {"coil_energy_j": e, "position_rms_mm": p, "orientation_rms_deg": o}
    if fixed:
        f.update(fixed_coil_energy_j=fixed[0], fixed_position_rms_mm=fixed[1], fixed_orientation_rms_deg=fixed[2])
    return {"seed": seed, "params": params, "figures": f}


def test_ratios_per_seed_then_median_and_worst(tmp_path):
    """Adaptive runs are divided by their own fixed cycle, fixed-cycle runs by the --fixed-json run of the
    same seed; medians and worst over the seeds by hand. Catches a ratio of medians instead of a median of
    ratios and a fixed cycle of another seed."""
    ad = _sweep(tmp_path / "adaptive.json", "schepers-adaptive", [
        _run(1, {"adaptive_policy.pulse_length": "fixed"}, 6.0, 5.5, 0.50, (10.0, 5.0, 0.5)),
        _run(2, {"adaptive_policy.pulse_length": "fixed"}, 10.0, 4.0, 0.60, (20.0, 4.0, 0.4)),
        _run(3, {"adaptive_policy.pulse_length": "fixed"}, 12.0, 3.0, 0.45, (15.0, 3.0, 0.5)),
        _run(1, {"adaptive_policy.pulse_length": "chosen"}, 4.0, 5.0, 0.50, (10.0, 5.0, 0.5))])
    ref = {1: {"coil_energy_j": 30.0, "position_rms_mm": 4.0, "orientation_rms_deg": 0.5},
           2: {"coil_energy_j": 20.0, "position_rms_mm": 5.0, "orientation_rms_deg": 0.4}}
    fx = _sweep(tmp_path / "fixed-640.json", "schepers-fixed-640", [_run(1, {}, 15.0, 5.0, 0.55), _run(2, {}, 10.0, 5.5, 0.5)])
    pts = {p["label"]: p for p in fp.sweep_points(ad, None) + fp.sweep_points(fx, ref)}
    a = pts["adaptive pulse_length=fixed"]
    assert a["energy"] == pytest.approx(0.6)                        # median of 0.6, 0.5, 0.8
    assert a["position"] == pytest.approx((1.0, 1.1))               # 1.1, 1.0, 1.0
    assert a["orientation"] == pytest.approx((1.0, 1.5))            # 1.0, 1.5, 0.9
    assert pts["adaptive pulse_length=chosen"]["energy"] == pytest.approx(0.4)
    f = pts["fixed-640"]
    assert f["energy"] == pytest.approx(0.5) and f["position"] == pytest.approx((1.175, 1.25))
    # the reference is the first grid point of a swept fixed cycle, not the last run of the seed
    f910 = _sweep(tmp_path / "fixed-910.json", "schepers-fixed-910", [
        _run(1, {"timing.cycle_us": 600000}, 30.0, 4.0, 0.5), _run(1, {"timing.cycle_us": 900000}, 20.0, 9.0, 0.9)])
    assert fp.reference(f910) == {1: ref[1]}


def test_bound_files_become_lines_and_the_png_is_written(tmp_path):
    """Two bound files at ratios 1.3 and 1.1 give each column's points sorted by ratio; the command
    writes the figure and a bad file is refused with exit status 2."""
    paths = []
    for r, m in ((1.3, 0.30), (1.1, 0.45)):
        p = tmp_path / f"bound-{r}.json"
        p.write_text(json.dumps({"ratio": r, "summary": {"fixed": {"median": m, "worst": m + 0.05, "best": m - 0.05},
                                                         "chosen": {"median": m - 0.02, "worst": m, "best": m - 0.1}}}))
        paths.append(str(p))
    b = fp.bound_points(paths)
    assert b["fixed"] == [(1.1, 0.45, 0.5), (1.3, 0.30, 0.35)]
    png = tmp_path / "front.png"
    assert fp.main(["--bound", paths[0], "--bound", paths[1], "--png", str(png)]) == 0
    assert png.stat().st_size > 1000
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"ratio": 1.1}))
    assert fp.main(["--bound", str(bad), "--png", str(tmp_path / "x.png")]) == 2
    assert not (tmp_path / "x.png").exists()


def test_timed_bound_has_its_own_column_and_shared_settings_leave_the_labels(tmp_path):
    """A bound of pulses timed to the samples (``--sample-phase aligned``) is a column of its own beside
    the one at an arbitrary phase (the chosen policy starts its pulses on the sample clock, the fixed one
    does not: two different floors); settings every sweep point shares are left out of the labels, so the
    fixed and chosen modes read apart."""
    p1, p2 = tmp_path / "b1.json", tmp_path / "b2.json"
    p1.write_text(json.dumps({"ratio": 1.1, "summary": {"fixed": {"median": 0.49, "worst": 0.54, "best": 0.45}}}))
    p2.write_text(json.dumps({"ratio": 1.1, "sample_phase": "aligned",
                              "summary": {"chosen": {"median": 0.42, "worst": 0.47, "best": 0.37}}}))
    b = fp.bound_points([str(p1), str(p2)])
    assert b == {"fixed": [(1.1, 0.49, 0.54)], "chosen aligned": [(1.1, 0.42, 0.47)]}
    common = {"reference_hold": "mean", "unreached_share": 0.8}
    a = _sweep(tmp_path / "fixed.json", "schepers-adaptive", [_run(1, dict(common), 6.0, 5.0, 0.5, (10.0, 5.0, 0.5))])
    c = _sweep(tmp_path / "chosen.json", "schepers-adaptive",
               [_run(1, dict(common, **{"adaptive_policy.pulse_length": "chosen"}), 5.0, 5.0, 0.5, (10.0, 5.0, 0.5))])
    shared = fp.common_settings([a, c])
    assert shared == {("reference_hold", "mean"), ("unreached_share", "0.8")}
    labels = [pt["label"] for path in (a, c) for pt in fp.sweep_points(path, None, shared)]
    assert labels == ["fixed", "chosen pulse_length=chosen"]


def test_bound_columns_pick_the_floors_drawn(tmp_path, capsys):
    """``--bound-columns`` keeps the named columns only; a name no file has is refused (exit 2, nothing
    written)."""
    p = tmp_path / "b.json"
    p.write_text(json.dumps({"ratio": 1.1, "summary": {"fixed": {"median": 0.49, "worst": 0.54, "best": 0.45},
                                                       "chosen": {"median": 0.48, "worst": 0.53, "best": 0.44}}}))
    png = tmp_path / "f.png"
    assert fp.main(["--bound", str(p), "--bound-columns", "fixed", "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "fixed: ratio 1.1" in out and "chosen:" not in out
    assert fp.main(["--bound", str(p), "--bound-columns", "chosen aligned", "--png", str(tmp_path / "g.png")]) == 2
    assert not (tmp_path / "g.png").exists()
