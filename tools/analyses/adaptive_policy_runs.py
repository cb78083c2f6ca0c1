"""The adaptive policy's runs of ``schepers-adaptive`` against fixed-cycle figures already measured.

``python -m coiltrack.tools.analyses.adaptive_policy_runs --fixed-from SWEEP.json --seeds 1-10
[--duration 60] [--set KEY=VALUE ...] [--workers N] --json OUT.json``

``coiltrack sweep --scenario schepers-adaptive`` runs, per seed, the policy and the fixed X, Y, Z
cycle it is compared with (``bench.runner.add_fixed_comparison``: the scenario's own
``fixed_config``, which no ``--set`` changes). The fixed cycle's figures therefore do not change
with the policy's settings: this command runs the policy alone, with the ``--set`` keys, and takes
each seed's ``fixed_*`` figures from a sweep of the same scenario and duration that ran them
(``--fixed-from``), forming the same ratios (``position_rms_ratio``, ``orientation_rms_ratio``,
``energy_ratio``, rounded as the runner does). ``--set bench.noise_draw=K`` runs bench draw ``K`` and takes
the fixed figures of that draw. The output is a sweep file (one grid point) that
``tools.analyses.pareto`` reads. The fixed cycle's figures are the same only while its code and
configuration are: check the branch against the sweep's with ``coiltrack results`` first.

Exit status: 0 done; 2 a bad argument or an unreadable ``--fixed-from`` (nothing run).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor

from coiltrack.tools.analyses.adaptive_consistency import set_keys
from coiltrack.tools.bench.sweep import parse_seeds

SCENARIO = "schepers-adaptive"


def _policy_run(seed: int, duration: float, keys: dict, fixed_cycle: bool = False) -> dict:
    """The policy's run as ``bench.sweep.run_task`` makes it, without the fixed-cycle comparison;
    ``fixed_cycle``: the scenario's fixed cycle itself with ``keys`` (e.g. its filter changed).
    ``bench.noise_draw`` among ``keys``: the bench's draw (as in a sweep)."""
    from coiltrack.tools.bench.runner import run_inproc
    from coiltrack.tools.bench.sweep import figures, scenario_with, split_noise_draw
    from coiltrack.tools.scenarios import get

    draw, rest = split_noise_draw(tuple(keys.items()))
    if fixed_cycle:
        sc = get(SCENARIO)
        return figures(run_inproc(sc, seed, duration, cfg=sc.fixed_config().with_keys(**dict(rest)), noise_draw=draw))
    return figures(run_inproc(scenario_with(SCENARIO, tuple(keys.items())), seed, duration, noise_draw=draw))


def with_fixed(rep: dict, fixed: dict) -> dict:
    """``rep`` with the fixed cycle's figures (``fixed_*`` of a sweep run) and the ratios, as
    ``bench.runner.add_fixed_comparison`` forms them."""
    from coiltrack.tools.bench.runner import FIXED_KEYS

    out = dict(rep)
    for k in FIXED_KEYS:
        out["fixed_" + k] = fixed.get("fixed_" + k)

    def ratio(a, b):
        return round(a / b, 3) if a is not None and b else None
    out["position_rms_ratio"] = ratio(rep.get("position_rms_mm"), fixed.get("fixed_position_rms_mm"))
    out["orientation_rms_ratio"] = ratio(rep.get("orientation_rms_deg"), fixed.get("fixed_orientation_rms_deg"))
    out["energy_ratio"] = ratio(rep.get("coil_energy_j"), fixed.get("fixed_coil_energy_j"))
    return out


def _fixed_figures(path: str, seeds: list[int], duration: float, draw: int = 0) -> dict[int, dict]:
    """Each seed's fixed-cycle figures of bench draw ``draw`` in the sweep ``path``."""
    from coiltrack.tools.bench.sweep import NOISE_DRAW_KEY
    from coiltrack.tools.inputs.sweepfile import read_json

    doc = read_json(path)
    if doc["scenario"] != SCENARIO or float(doc.get("duration_s", -1)) != duration:
        raise ValueError(f"--fixed-from {path}: a sweep of {SCENARIO} for {duration} s is needed, "
                         f"got {doc['scenario']} for {doc.get('duration_s')} s")
    got = {}
    for r in doc["runs"]:
        if r["figures"].get("fixed_coil_energy_j") and int(r["params"].get(NOISE_DRAW_KEY, 0)) == draw:
            got.setdefault(int(r["seed"]), r["figures"])
    missing = [s for s in seeds if s not in got]
    if missing:
        raise ValueError(f"--fixed-from {path}: no fixed-cycle figures of bench draw {draw} for seeds {missing}")
    return got


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fixed-from", required=True, metavar="SWEEP.json")
    ap.add_argument("--seeds", default="1-10")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="firmware configuration key (repeatable)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--fixed-cycle", action="store_true",
                    help="run the scenario's fixed cycle with the --set keys instead of the policy")
    ap.add_argument("--json", required=True)
    a = ap.parse_args(argv)
    try:
        seeds = parse_seeds(a.seeds)
        keys = set_keys(a.set)
        if not (0.0 < a.duration <= 3600.0) or not 1 <= a.workers <= 16:
            raise ValueError("--duration must be in (0, 3600] s and --workers in 1..16")
        from coiltrack.tools.bench.sweep import scenario_with
        scenario_with(SCENARIO, tuple(keys.items())).firmware_config().validate()
        from coiltrack.tools.bench.sweep import split_noise_draw
        fixed = _fixed_figures(a.fixed_from, seeds, a.duration, split_noise_draw(tuple(keys.items()))[0])
    except (ValueError, TypeError, OSError) as exc:
        print(f"adaptive_policy_runs: {exc}", file=sys.stderr)
        return 2
    t0 = time.time()
    with ProcessPoolExecutor(max_workers=a.workers) as ex:
        futs = {s: ex.submit(_policy_run, s, a.duration, keys, a.fixed_cycle) for s in seeds}
        runs = []
        for s in seeds:
            fig = with_fixed(futs[s].result(), fixed[s])
            runs.append({"seed": s, "params": keys, "figures": fig})
            print(f"seed {s}: energy {fig['energy_ratio']}, position {fig['position_rms_ratio']}, "
                  f"orientation {fig['orientation_rms_ratio']}", flush=True)
    doc = {"scenario": SCENARIO, "executor": "local", "workers": a.workers, "scheduler": None, "seeds": seeds,
           "duration_s": a.duration, "grid": {k: [v] for k, v in keys.items()}, "interrupted": False,
           "wall_s": round(time.time() - t0, 2), "fixed_from": a.fixed_from, "fixed_cycle": a.fixed_cycle,
           "runs": runs}
    with open(a.json, "w") as f:
        json.dump(doc, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
