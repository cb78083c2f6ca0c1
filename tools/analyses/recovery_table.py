"""The recovery table of docs/faults.md on many seeds, with the undisturbed run beside it.

``python -m coiltrack.tools.analyses.recovery_table --dir D --seeds 1-10 --workers 2`` runs
``roetenberg-fusion`` for 120 s on each seed without a fault and with each of the four faults of
the table (sensor and driver off 40-45 s, saturation 40-45 s, open coil 1 at 40-50 s), on the
simulated clock in worker processes, keeping each run's report (``sS_NAME.json``) and the error
trace of its valid fused poses (``sS_NAME.npz``: true time s, error m) in ``D`` (a run whose
files are there already is not run again), and prints per run:

* ``rec``: ``fault_recovery_s`` as ``coiltrack bench --scenario roetenberg-fusion --seed S
  --duration 120 --faults F`` reports it: the faulted run scored against the no-fault run of
  the same seed by ``tools.bench.recovery.add_recovery_reference`` (the bench runs that no-fault
  run itself; here the one no-fault run of the seed serves its four faults);
* ``rec_level``: the measure before it, twice the run's own no-fault level alone;
* ``rec_local``: against twice the undisturbed run's RMS over the same second alone (no level):
  how long the fault's trace stays worse than the tracker's own;
* ``undisturbed``: ``rec_level`` the undisturbed run itself would get for a fault ending at the
  same instant, with the same level: what the level-only measure asks of the tracker that had no
  fault at all (``undisturbed_worst``: the longest for fault ends up to 1 s either side);
* fused RMS and its ratio to the undisturbed run, the overconfident fraction (fused and
  magnetic-only poses), and the overconfident poses in the fault window and the 3 s after.

Not a bench command: a measurement for the note (``--no-run`` tabulates what is in ``D``).
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import multiprocessing
import os
import sys

import numpy as np
from coiltrack.tools.outputs.faultreport import recovery_time

#: the four faults of the recovery table (docs/faults.md, README "Faults and recovery"): name, switch, end (s)
FAULTS = (("sensor", "node_off=sensor@40s-45s", 45.0), ("driver", "node_off=driver@40s-45s", 45.0),
          ("sat", "sat=40s-45s", 45.0), ("open", "open_circuit=1@40s-50s", 50.0))
SCENARIO = "roetenberg-fusion"
DURATION_S = 120.0


def _seeds(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def fused_errors(path: str) -> tuple[np.ndarray, np.ndarray]:
    """True times (s) and position errors (m) of the valid fused poses of a run kept in ``D``."""
    with np.load(path) as z:
        return z["t"], z["e"]


def recovery_against(ft, fe, rt, re, t_end: float, level_mm: float, step=0.1, window=1.0, horizon=30.0):
    """Seconds from ``t_end`` until the RMS of ``fe`` over the next ``window`` is within twice
    ``max(level, RMS of the undisturbed run's errors re over the same window)``; None if never."""
    k = 0
    while k * step <= horizon:
        t = t_end + k * step
        s = (ft >= t) & (ft < t + window)
        r = (rt >= t) & (rt < t + window)
        if s.sum() >= 2 and r.sum() >= 2:
            ref = max((level_mm or 0.0) * 1e-3, math.sqrt(float(np.mean(re[r] ** 2))))
            if math.sqrt(float(np.mean(fe[s] ** 2))) <= 2.0 * ref:
                return round(k * step, 2)
        if len(ft) and t > ft[-1]:
            return None
        k += 1
    return None


def run(job) -> str:
    """One run of the table (``job`` = (dir, seed, name, switch)): its report and fused error trace."""
    from coiltrack.tools.bench.recovery import TraceKeeper
    from coiltrack.tools.bench.runner import parse_faults, run_inproc
    from coiltrack.tools.outputs.report import write_json
    from coiltrack.tools.scenarios import get

    out, seed, name, switch = job
    base = os.path.join(out, f"s{seed}_{name}")
    sc = get(SCENARIO)
    keep = TraceKeeper()
    rep = run_inproc(sc, seed, DURATION_S, faults=parse_faults(switch, sc) if switch else None, outputs=keep)
    np.savez(base + ".npz", t=keep.trace[0], e=keep.trace[1])
    write_json(rep, base + ".json")
    return f"seed {seed} {name}"


def table(out: str, seeds: list[int]) -> list[dict]:
    from coiltrack.hil.faults import TimedFault
    from coiltrack.tools.bench.recovery import add_recovery_reference
    from coiltrack.tools.bench.runner import parse_faults
    from coiltrack.tools.scenarios import get

    sc = get(SCENARIO)
    rows = []
    for seed in seeds:
        base = os.path.join(out, f"s{seed}_none")
        if not os.path.exists(base + ".json"):
            continue
        j0 = json.load(open(base + ".json"))
        rt, re = fused_errors(base + ".npz")
        rows.append({"seed": seed, "fault": "none", "rms_mm": j0["position_rms_mm"], "rms_ratio": 1.0,
                     "overconfident": j0["overconfident_fraction"], "over_fused": j0["overconfidence"]["fused"],
                     "over_mag": j0["overconfidence"]["magnetic"], "quality_rank": j0.get("quality_error_rank_corr")})
        for name, switch, t_end in FAULTS:
            p = os.path.join(out, f"s{seed}_{name}")
            if not os.path.exists(p + ".json"):
                continue
            j = json.load(open(p + ".json"))
            ft, fe = fused_errors(p + ".npz")
            faults = parse_faults(switch, sc)
            lvl = j["no_fault_level_mm"]
            rec = add_recovery_reference(dict(j), (ft, fe), faults, (rt, re))["fault_recovery_s"]
            und = []
            for k in range(-10, 11):          # fault ends 1 s either side of the real one
                te = t_end + 0.1 * k
                und.append(recovery_time(rt, re, TimedFault("sat", int((te - 5.0) * 1e6), int(te * 1e6)), lvl))
            by = j["overconfident_by_fault"]
            rows.append({"seed": seed, "fault": name, "rec": next(iter(rec.values())),
                         "rec_level": next(iter(j["fault_recovery_s"].values())),
                         "rec_local": recovery_against(ft, fe, rt, re, t_end, None),
                         "undisturbed": und[10],
                         "undisturbed_worst": max((u for u in und if u is not None), default=None),
                         "level_mm": lvl,
                         "rms_mm": j["position_rms_mm"],
                         "rms_ratio": round(j["position_rms_mm"] / j0["position_rms_mm"], 3),
                         "overconfident": j["overconfident_fraction"], "over_fused": j["overconfidence"]["fused"],
                         "over_mag": j["overconfidence"]["magnetic"],
                         "over_in_window": sum(v for k, v in by.items() if k != "outside fault windows")})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", required=True)
    ap.add_argument("--seeds", default="1-10")
    ap.add_argument("--workers", type=int, default=1, help="runs in parallel (default 1)")
    ap.add_argument("--no-run", action="store_true", help="tabulate the runs in --dir, run nothing")
    a = ap.parse_args(argv)
    seeds = _seeds(a.seeds)
    os.makedirs(a.dir, exist_ok=True)
    if not a.no_run:
        jobs = [(a.dir, seed, name, switch) for seed in seeds
                for name, switch in (("none", None),) + tuple((n, s) for n, s, _ in FAULTS)
                if not os.path.exists(os.path.join(a.dir, f"s{seed}_{name}.json"))]
        with multiprocessing.Pool(max(1, a.workers)) as pool:
            for done in pool.imap_unordered(run, jobs):
                print(done, file=sys.stderr, flush=True)
    cols = ("seed", "fault", "rec", "rec_level", "rec_local", "undisturbed", "undisturbed_worst", "level_mm",
            "rms_mm", "rms_ratio", "overconfident", "over_fused", "over_mag", "over_in_window", "quality_rank")
    w = csv.writer(sys.stdout, delimiter="\t")
    w.writerow(cols)
    for r in table(a.dir, seeds):
        w.writerow(["-" if r.get(c) is None else r.get(c) for c in cols])
    return 0


if __name__ == "__main__":
    sys.exit(main())
