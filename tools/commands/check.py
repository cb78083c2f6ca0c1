"""Robustness sweep: every registered scenario (or those named) on a range of seeds, short runs
on the simulated clock, in a process pool. Counts what must not happen: exceptions (with the
scenario, the seed and where the traceback ends), invalid poses and, with ``--faults``, faults the
firmware did not report. ``tools/bench/check.py`` describes a run.

Stopped by Ctrl-C or SIGTERM, the runs finished are summarised and written (``--json``), marked
"interrupted": true."""
from __future__ import annotations

import json
import sys
import time

from .. import args as A
from ..stopping import Stopped
from ..bench.check import select, run_jobs, summarize

HELP = "robustness sweep: every scenario on a range of seeds, counting exceptions and faults unreported"
EXIT = {1: "a run raised an exception, or a fault injected was not reported (the table names them)",
        130: "stopped by SIGINT: the runs finished are summarised and written, marked interrupted",
        143: "stopped by SIGTERM: likewise"}
#: most runs one call makes
MAX_RUNS = 20_000


def add_arguments(p) -> None:
    p.add_argument("--scenarios", default=None, metavar="NAMES",
                   help="comma list of scenario names or shell patterns, e.g. 'roetenberg-walking-*,static' "
                        "(default: every registered scenario)")
    p.add_argument("--seeds", default="1-40", help="seeds: A-B, N or a comma list of both (default 1-40)")
    p.add_argument("--duration", type=A.bench_seconds, default=5.0,
                   help=f"simulated seconds per run, (0, {A.MAX_BENCH_S:g}] (default 5)")
    p.add_argument("--faults", default="none", metavar="none|one|TEXT",
                   help="none (default); one: one timed fault per run, its kind by the seed (tools/bench/check.py); "
                        "or a --faults text of `coiltrack bench` for every run")
    p.add_argument("--workers", type=A.integer(1, 64), default=1, help="runs in parallel (default 1)")
    p.add_argument("--json", type=A.output_path, metavar="PATH", help="write every run and the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no line per finished run on stderr")


def _plan(args) -> tuple[list[str], list[int]]:
    # imported where used here and below: the scenarios (scipy underneath) load only when needed, not for --help
    from .. import scenarios
    from ..bench.sweep import parse_seeds

    try:
        names = select(args.scenarios, scenarios.SCENARIOS)
    except ValueError as exc:
        raise ValueError(f"--scenarios: {exc}") from None
    try:
        seeds = parse_seeds(args.seeds, MAX_RUNS)
    except ValueError as exc:
        raise ValueError(f"--seeds: {exc}") from None
    if len(names) * len(seeds) > MAX_RUNS:
        raise ValueError(f"--scenarios x --seeds: {len(names) * len(seeds)} runs; at most {MAX_RUNS}")
    if args.faults not in ("none", "one"):
        from ..bench.runner import parse_faults

        for n in names:
            if scenarios.get(n) is None:
                continue
            try:
                from ..bench import sweep

                if sweep.experiment(n) is None:
                    parse_faults(args.faults, scenarios.get(n))
            except ValueError as exc:
                raise ValueError(f"--faults: {exc} (scenario {n})") from None
    return names, seeds


def format_summary(s: dict, runs: list[dict]) -> str:
    lines = [f"  runs                      {s['runs']} ({s['scenarios']} scenarios)",
             f"  exceptions                {s['exceptions']}",
             f"  runs with invalid poses   {s['runs_with_invalid_poses']}  "
             f"({s['poses_invalid']} of {s['poses']} poses invalid)",
             f"  faults injected           {s['faults_injected']}, unreported {s['faults_unreported']}",
             f"  run time (sum)            {s['wall_s_sum']:g} s"]
    for k, n in sorted(s["exception_kinds"].items(), key=lambda kv: -kv[1]):
        lines.append(f"  {n:4d} x {k}")
    for r in runs:
        if r["exception"]:
            via = f", from {r['origin']}" if r.get("origin") else ""
            lines.append(f"  EXCEPTION {r['scenario']} seed {r['seed']}: {r['exception']} "
                         f"({r['side']}: {r['where']}{via})")
    for r in runs:
        if r["faults_unreported"]:
            lines.append(f"  UNREPORTED {r['scenario']} seed {r['seed']}: {', '.join(r['faults_unreported'])}")
    return "\n".join(lines)


def run(args) -> int:
    try:
        names, seeds = _plan(args)
    except ValueError as exc:
        print(f"coiltrack check: {exc}", file=sys.stderr)
        return 2
    jobs = [(n, s, args.duration, args.faults) for n in names for s in seeds]
    print(f"coiltrack check: {len(names)} scenarios x {len(seeds)} seeds = {len(jobs)} runs of {args.duration:g} s, "
          f"faults {args.faults}, {args.workers} workers", flush=True)
    done = [0]

    def progress(r: dict) -> None:
        done[0] += 1
        if not args.quiet:
            what = f"EXCEPTION {r['exception']} ({r['where']})" if r["exception"] else \
                f"{r['poses']} poses, {r['poses_invalid']} invalid"
            print(f"[{done[0]}/{len(jobs)}] {r['scenario']} seed {r['seed']}: {what} ({r['wall_s']} s)",
                  file=sys.stderr, flush=True)

    wall0 = time.monotonic()
    status = 0
    stopped = None
    try:
        results = run_jobs(jobs, args.workers, progress)
    except (KeyboardInterrupt, Stopped) as exc:
        results = getattr(exc, "partial", None) or []
        stopped = exc
        status = exc.exit_code if isinstance(exc, Stopped) else 130
    runs = [r for r in results if r is not None]
    s = summarize(runs)
    print(format_summary(s, runs))
    wall = time.monotonic() - wall0
    print(f"{len(runs)} of {len(jobs)} runs in {wall:.1f} s wall" + (" (interrupted)" if stopped else ""))
    if args.json:
        doc = {"scenarios": names, "seeds": seeds, "duration_s": args.duration, "faults": args.faults,
               "workers": args.workers, "interrupted": stopped is not None, "wall_s": round(wall, 1),
               "summary": s, "runs": runs}
        with open(args.json, "w") as fh:
            json.dump(doc, fh, indent=1, allow_nan=False)
            fh.write("\n")
        print(f"runs and summary written to {args.json}")
    if status:
        return status
    return 1 if s["exceptions"] or s["faults_unreported"] else 0
