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
