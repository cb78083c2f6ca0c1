"""``tools.analyses.pareto --bound``: the floors per seed beside the adaptive sweeps' energy ratios."""
import json

from coiltrack.tools.analyses import pareto


def test_bound_table_puts_each_seeds_ratio_over_its_own_floor(tmp_path):
    """Two floors (60 ms pulses, chosen lengths) read from ``energy_bound --json`` files and one
    adaptive sweep's per-seed energy ratios: each cell is the ratio and its quotient by each floor
    of the same seed (0.60 / 0.50 = 1.20, 0.60 / 0.40 = 1.50). Catches the quotient inverted or
    a floor taken from another seed."""
    paths = []
    for name, floors in (("bound-60ms", {1: 0.50, 2: 0.55}), ("bound-chosen", {1: 0.40, 2: 0.44})):
        p = tmp_path / f"{name}.json"
        p.write_text(json.dumps({"seeds": [{"seed": s, "energy_fraction": f} for s, f in floors.items()]}))
        paths.append(str(p))
    bounds = pareto.load_bounds(paths)
    assert bounds == {"bound-60ms": {1: 0.50, 2: 0.55}, "bound-chosen": {1: 0.40, 2: 0.44}}
    row = {"series": "s", "scenario": "schepers-adaptive", "params": {}, "per_seed": [(1, 1.0, 1.0, 0.60),
                                                                                   (2, 1.0, 1.0, 0.66)]}
    lines = pareto.bound_table([row], bounds).splitlines()
    assert lines[2] == "| 1 | 0.500 | 0.400 | 0.600 (1.20 / 1.50) |"
    assert lines[3] == "| 2 | 0.550 | 0.440 | 0.660 (1.20 / 1.50) |"


def test_energy_bound_files_give_one_floor_per_column_and_are_not_sweeps(tmp_path):
    """``energy_bound --json`` writes per seed a floor per column (``modes``); each column is a floor of
    its own, a file of pulses timed to the samples marked ``aligned``. Such a file among the sweeps (a
    folder's ``*.json``) is taken as a bound, not refused as a damaged sweep."""
    p = tmp_path / "energy-bound.json"
    p.write_text(json.dumps({"ratio": 1.1, "summary": {}, "seeds": [
        {"seed": 1, "modes": {"fixed": {"energy_fraction": 0.456}, "chosen": {"energy_fraction": 0.446}}},
        {"seed": 2, "modes": {"fixed": {"energy_fraction": 0.499}, "chosen": {"energy_fraction": 0.494}}}]}))
    q = tmp_path / "timed.json"
    q.write_text(json.dumps({"ratio": 1.1, "sample_phase": "aligned", "summary": {},
                             "seeds": [{"seed": 1, "modes": {"chosen": {"energy_fraction": 0.372}}}]}))
    assert pareto.is_bound_file(str(p)) and pareto.is_bound_file(str(q))
    assert pareto.load_bounds([str(p), str(q)]) == {"energy-bound fixed": {1: 0.456, 2: 0.499},
                                                    "energy-bound chosen": {1: 0.446, 2: 0.494},
                                                    "timed chosen aligned": {1: 0.372}}
    sweep = tmp_path / "s.json"
    sweep.write_text(json.dumps({"scenario": "schepers-adaptive", "interrupted": False, "runs": [
        {"seed": 1, "params": {}, "figures": {"position_rms_mm": 3.0, "orientation_rms_deg": 0.3, "coil_energy_j": 18.0,
                                              "coil_charge_c": 10.0, "pulses_per_s": 9.0, "fixed_position_rms_mm": 3.0,
                                              "fixed_orientation_rms_deg": 0.3, "fixed_coil_energy_j": 30.0,
                                              "fixed_coil_charge_c": 16.0}}]}))
    assert not pareto.is_bound_file(str(sweep))
    assert pareto.main([str(sweep), str(p), str(q)]) == 0
