"""The fixed cycle's run-to-run spread on one trajectory: ``schepers-adaptive``'s fixed X, Y, Z
cycle over several bench draws per seed.

``python -m coiltrack.tools.analyses.adaptive_noise_spread --seeds 1-10 --draws 1,2 [--duration 60]
[--workers 1] [--with SWEEP.json ...] --json OUT.json``

Each run is the scenario's ``fixed_config`` on the seed's trajectory with the bench's other draws
taken anew (``bench.runner.BenchSetup`` ``noise_draw``: driver, sensor, IMU, clocks; draw 0 the
seed's own), the comparison ``coiltrack sweep --set bench.noise_draw=...`` makes beside the policy.
``--with``: sweeps of ``schepers-adaptive`` (any ``bench.noise_draw`` in their params, 0 without)
whose ``fixed_*`` figures join as further draws (the same fixed cycle, not run again), and whose
policy ratios are gathered per seed and draw.

Printed per seed: the fixed cycle's position and orientation RMS over the draws, their mean and
the standard deviation of each draw's RMS over the seed's mean (``sd_pos``, ``sd_ori``: the
spread of a ratio whose denominator is one draw's fixed cycle), and, where the policy ran on
several draws, its ratios per draw and their standard deviation. Not a bench command: a
measurement for ``docs/adaptive.md``.

Exit status: 0 done; 2 a bad argument or an unreadable ``--with`` file.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor

from coiltrack.tools.bench.sweep import parse_seeds

SCENARIO = "schepers-adaptive"


def fixed_run(seed: int, draw: int, duration: float) -> dict:
    """The scenario's fixed cycle on ``seed``'s trajectory, bench draw ``draw``."""
    from coiltrack.tools.bench.runner import run_inproc
    from coiltrack.tools.scenarios import get

    sc = get(SCENARIO)
    rep = run_inproc(sc, seed, duration, cfg=sc.fixed_config(), noise_draw=draw)
    return {k: rep.get(k) for k in ("position_rms_mm", "orientation_rms_deg", "coil_energy_j")}


def gather(sweeps: list[dict], duration: float) -> tuple[dict, dict]:
    """From sweep documents: {(seed, draw): fixed figures} and {(seed, draw): policy ratios}."""
    fixed, policy = {}, {}
    for doc in sweeps:
        if doc.get("scenario") != SCENARIO or float(doc.get("duration_s", -1)) != duration:
            raise ValueError(f"--with: a sweep of {SCENARIO} for {duration} s is needed")
        for r in doc["runs"]:
            f = r["figures"]
            key = (int(r["seed"]), int(r["params"].get("bench.noise_draw", 0)))
            if f.get("fixed_position_rms_mm") is not None:
                fixed.setdefault(key, {"position_rms_mm": f["fixed_position_rms_mm"],
                                       "orientation_rms_deg": f["fixed_orientation_rms_deg"],
                                       "coil_energy_j": f["fixed_coil_energy_j"]})
            if f.get("orientation_rms_ratio") is not None:
                policy.setdefault(key, {k: f[k] for k in ("energy_ratio", "position_rms_ratio",
                                                          "orientation_rms_ratio")})
    return fixed, policy


def spread(fixed: dict, policy: dict, seeds: list[int]) -> list[dict]:
    """Per seed: the fixed cycle's RMS over its draws and their relative spread; the policy's ratios."""
    rows = []
    for s in seeds:
        draws = sorted(d for (t, d) in fixed if t == s)
        row = {"seed": s, "draws": draws}
        for k, name in (("position_rms_mm", "pos"), ("orientation_rms_deg", "ori")):
            v = [fixed[(s, d)][k] for d in draws]
            m = statistics.fmean(v) if v else None
            row[f"fixed_{name}"] = v
            row[f"mean_{name}"] = round(m, 4) if v else None
            row[f"sd_{name}"] = round(statistics.stdev([x / m for x in v]), 4) if len(v) > 1 else None
        pd = sorted(d for (t, d) in policy if t == s)
        for k in ("energy_ratio", "position_rms_ratio", "orientation_rms_ratio"):
            v = [policy[(s, d)][k] for d in pd]
            row[k] = v
            row[f"sd_{k}"] = round(statistics.stdev(v), 4) if len(v) > 1 else None
        row["policy_draws"] = pd
        rows.append(row)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="1-10")
    ap.add_argument("--draws", default="1,2", help="bench draws to run (0: the seed's own)")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--with", dest="sweeps", action="append", default=[], metavar="SWEEP.json")
    ap.add_argument("--json", required=True)
    a = ap.parse_args(argv)
    try:
        seeds = parse_seeds(a.seeds)
        draws = parse_seeds(a.draws) if a.draws.strip() else []
        if not (0.0 < a.duration <= 3600.0) or not 1 <= a.workers <= 2:
            raise ValueError("--duration must be in (0, 3600] s and --workers 1 or 2")
        docs = []
        for p in a.sweeps:
            with open(p) as f:
                docs.append(json.load(f))
        fixed, policy = gather(docs, a.duration)
    except (ValueError, OSError, KeyError) as exc:
        print(f"adaptive_noise_spread: {exc}", file=sys.stderr)
        return 2
    t0 = time.time()
    todo = [(s, d) for d in draws for s in seeds if (s, d) not in fixed]
    with ProcessPoolExecutor(max_workers=a.workers) as ex:
        futs = {k: ex.submit(fixed_run, k[0], k[1], a.duration) for k in todo}
        for k in todo:
            fixed[k] = futs[k].result()
            print(f"seed {k[0]} draw {k[1]}: {fixed[k]}", flush=True)
    rows = spread(fixed, policy, seeds)
    for r in rows:
        print(json.dumps(r))
    doc = {"scenario": SCENARIO, "duration_s": a.duration, "seeds": seeds, "draws_run": draws, "with": a.sweeps,
           "wall_s": round(time.time() - t0, 1),
           "fixed_runs": [{"seed": s, "draw": d, **f} for (s, d), f in sorted(fixed.items())], "rows": rows}
    with open(a.json, "w") as f:
        json.dump(doc, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
