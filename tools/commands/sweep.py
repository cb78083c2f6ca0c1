"""Monte Carlo sweep: independent in-process bench runs of one scenario over seeds and a grid of
firmware configuration values, on a local process pool, a Dask cluster or Ray; prints the
median, p90 and worst of each figure per grid point.

Exit status: 0 done; 1 a run failed; 2 bad arguments (nothing run); 130 interrupted by Ctrl-C
(SIGINT), 143 by SIGTERM (the runs done so far are summarised and written, marked
"interrupted": true)."""
from __future__ import annotations

import csv
import json
import math
import os
import sys
import time
from pathlib import Path

from ..stopping import held_signals, on_signals

EXIT = {1: "a run failed: the error names its seed and parameter values",
        130: "stopped by SIGINT: the runs done are written, marked interrupted",
        143: "stopped by SIGTERM: likewise"}
HELP = "Monte Carlo sweep of bench runs over seeds and configuration values"

#: bounds of the arguments
MAX_DURATION_S = 3600.0
MAX_WORKERS = 1024
MAX_RUNS = 100_000
#: the figure --plot draws
PLOT_FIGURE = "position_rms_mm"


def add_arguments(p) -> None:
    p.add_argument("--scenario", required=True, help="scenario name (as for `coiltrack bench`)")
    p.add_argument("--seeds", default="1-10", help="seeds: A-B, N or a comma list of both, e.g. 1-100 (default 1-10)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="firmware configuration key (section.key, e.g. pulse.mag_sigma_t, or a plain key) and "
                        "its values; repeatable: the runs are the cartesian product of every --set times the seeds")
    p.add_argument("--duration", default=None, help=f"seconds per run, 0 < S <= {MAX_DURATION_S:g} "
                                                    "(default: the scenario's)")
    p.add_argument("--executor", choices=("local", "dask", "ray"), default="local",
                   help="local: a process pool on this machine (default); dask: a Dask cluster (a LocalCluster on "
                        "127.0.0.1 unless --scheduler); ray: a Ray cluster (extra 'ray')")
    p.add_argument("--workers", default=None, help=f"worker processes of the local pool or of the cluster this "
                                                   f"command starts, 1-{MAX_WORKERS} (default: the CPU count)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="an existing cluster: a Dask scheduler (tcp://HOST:PORT) or a Ray address")
    p.add_argument("--json", metavar="PATH", help="write runs and summary as JSON")
    p.add_argument("--csv", metavar="PATH", help="write one row per run as CSV")
    p.add_argument("--plot", metavar="PATH", help=f"plot {PLOT_FIGURE} against seeds and grid points (PNG, ...)")
    p.add_argument("--progress", action="store_true", help="progress bar on stderr even when it is not a terminal")


class BadArgument(ValueError):
    pass


def run(args) -> int:
    # imported where used here and below: the scenarios (scipy underneath) load only when needed, not for --help
    from ..bench import sweep

    try:
        plan = _plan(args)
    except BadArgument as exc:
        print(f"coiltrack sweep: {exc}", file=sys.stderr)
        return 2
    tasks = [sweep.Task(args.scenario, s, plan["duration_s"], point) for point in plan["grid"] for s in plan["seeds"]]
    where = args.scheduler or f"{plan['workers']} workers"
    print(f"coiltrack sweep: {args.scenario}, {_n(len(plan['seeds']), 'seed')} x {_n(len(plan['grid']), 'grid point')}"
          f" = {_n(len(tasks), 'run')} of {plan['duration_s']:g} s, executor {args.executor} ({where})")
    bar = sweep.ProgressBar(len(tasks), args.progress or sys.stderr.isatty())
    wall0 = time.perf_counter()
    bar.update(0)
    status = 0
    try:
        with on_signals():
            runs = sweep.run_tasks(tasks, args.executor, plan["workers"], args.scheduler, on_result=bar.update)
    except sweep.SweepInterrupted as exc:
        runs, status = [r for r in exc.partial if r is not None], exc.exit_code
        bar.close()
        print(f"coiltrack sweep: stopped by {exc.reason} after {_n(len(runs), 'finished run')} of {len(tasks)}; "
              "writing them", file=sys.stderr)
    except sweep.SweepError as exc:
        bar.close()
        print(f"coiltrack sweep: {exc}", file=sys.stderr)
        return 1
    bar.close()
    with held_signals():    # a second signal waits for the finished runs to be written
        _finish(args, plan, runs, status, wall0)
    return status


def _finish(args, plan: dict, runs: list[dict], status: int, wall0: float) -> None:
    """The summary printed, the JSON, CSV and plot written, of the runs done."""
    from ..bench import sweep

    summary = sweep.summarize(runs)
    exp = sweep.experiment(args.scenario)
    print(sweep.format_summary(summary, shown_figures(summary, exp.headline if exp else sweep.HEADLINE)))
    tables = exp.tables(args.scenario, runs) if exp else {}
    if exp:
        print(exp.format(tables))
    wall = time.perf_counter() - wall0
    print(f"{len(runs)} runs in {wall:.1f} s wall" + (" (interrupted)" if status else ""))
    doc = {"scenario": args.scenario, "executor": args.executor, "workers": plan["workers"],
           "scheduler": args.scheduler, "seeds": plan["seeds"], "duration_s": plan["duration_s"],
           "grid": [dict(point) for point in plan["grid"]], "interrupted": bool(status), "wall_s": round(wall, 2),
           "runs": runs, "summary": summary, **tables}
    _write_outputs(args, doc)


def shown_figures(summary: list[dict], headline) -> tuple:
    """The figures of the printed summary: the headline ones, then every other figure
    whose median differs between grid points (what the swept keys moved; JSON and CSV
    have every figure anyway)."""
    medians: dict[str, set] = {}
    for g in summary:
        for name, s in g["figures"].items():
            medians.setdefault(name, set()).add(s["median"])
    moved = tuple(n for n, m in medians.items() if n not in headline and len(summary) > 1 and len(m) > 1)
    return tuple(headline) + moved


# ---------------------------------------------------------------- checks before any work

def _plan(args) -> dict:
    """Every argument checked (one BadArgument naming it) before anything runs."""
    from coiltrack.firmware.config import ConfigError

    from .. import scenarios
    from ..bench import sweep

    if args.scenario not in scenarios.SCENARIOS:
        raise BadArgument(f"--scenario: unknown '{args.scenario}'; known: {', '.join(sorted(scenarios.SCENARIOS))}")
    try:
        seeds = sweep.parse_seeds(args.seeds, MAX_RUNS)
    except ValueError as exc:
        raise BadArgument(f"--seeds: {exc}; e.g. 1-100 or 1-4,10") from None
    sets = [_parse_set(sweep, s) for s in args.sets]
    if len({k for k, _ in sets}) != len(sets):
        raise BadArgument("--set: a key is given twice")
    points = sweep.grid(sets)
    if len(points) * len(seeds) > MAX_RUNS:
        raise BadArgument(f"--seeds x --set: {len(points) * len(seeds)} runs; at most {MAX_RUNS}")
    for point in points:  # every value, and every combination, applied once
        try:
            sweep.scenario_with(args.scenario, point)
        except ConfigError as exc:
            raise BadArgument(f"--set {' '.join(f'{k}={v}' for k, v in point)}: {exc}") from None
    _check_executor(args)
    for opt in ("json", "csv", "plot"):
        _check_output(opt, getattr(args, opt))
    return {"seeds": seeds, "grid": points, "duration_s": _duration(args, scenarios.get(args.scenario)),
            "workers": _workers(args)}


def _parse_set(sweep, text: str):
    try:
        return sweep.parse_set(text)
    except ValueError as exc:
        raise BadArgument(f"--set: {exc}") from None


def _duration(args, sc) -> float:
    if args.duration is None:
        return sc.duration_s
    try:
        d = float(args.duration)
    except ValueError:
        d = math.nan
    if not (0.0 < d <= MAX_DURATION_S):
        raise BadArgument(f"--duration: '{args.duration}' is not a number of seconds in (0, {MAX_DURATION_S:g}]")
    return d


def _workers(args) -> int | None:
    if args.workers is None:
        return None if args.scheduler else os.cpu_count() or 1
    if args.scheduler:
        raise BadArgument("--workers: sizes a cluster this command starts; with --scheduler the cluster is given")
    w = args.workers.strip()
    if not w.isdecimal() or not 1 <= int(w) <= MAX_WORKERS:
        raise BadArgument(f"--workers: '{args.workers}' is not an integer in 1-{MAX_WORKERS}")
    return int(w)


def _check_executor(args) -> None:
    from ..bench import sweep

    if args.executor == "local" and args.scheduler:
        raise BadArgument("--scheduler: needs --executor dask or ray")
    module, extra = {"local": (None, None), "dask": ("distributed", "sweep"), "ray": ("ray", "ray")}[args.executor]
    if module:
        try:
            sweep.need_extra(module, extra, args.executor)
        except ImportError as exc:
            raise BadArgument(str(exc)) from None
    if args.plot:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            raise BadArgument("--plot: needs matplotlib: pip install 'coiltrack[bench]'") from None


def _check_output(opt: str, path) -> None:
    if not path:
        return
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise BadArgument(f"--{opt}: '{path}' is a directory")
    if not parent.is_dir() or not os.access(parent, os.W_OK):
        raise BadArgument(f"--{opt}: cannot write '{path}': no writable directory '{parent}'")


# ---------------------------------------------------------------- outputs

def _write_outputs(args, doc: dict) -> None:
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(doc, fh, indent=1, allow_nan=False)
            fh.write("\n")
        print(f"runs and summary written to {args.json}")
    if args.csv:
        write_csv(doc["runs"], args.csv)
        print(f"runs written to {args.csv}")
    if args.plot:
        from ..bench import sweep

        exp = sweep.experiment(doc["scenario"])
        if exp is not None and exp.plot is not None:
            exp.plot(doc, args.plot)
        else:
            plot(doc["runs"], doc["summary"], args.plot, doc["scenario"])
        print(f"plot written to {args.plot}")


def write_csv(runs: list[dict], path) -> None:
    """One row per run: the parameters, the seed, then every figure (empty when absent)."""
    params = list(dict.fromkeys(k for r in runs for k in r["params"]))
    names = list(dict.fromkeys(k for r in runs for k in r["figures"]))
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([*params, "seed", *names])
        for r in runs:
            w.writerow([*(r["params"].get(k) for k in params), r["seed"],
                        *("" if r["figures"].get(n) is None else r["figures"][n] for n in names)])


def plot(runs: list[dict], summary: list[dict], path, scenario: str, name: str = PLOT_FIGURE) -> None:
    """``name`` against the seed for each grid point, and its median and p90 per grid point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_s, ax_g) = plt.subplots(1, 2, figsize=(11, 4.2), width_ratios=(3, 2))
    labels = [" ".join(f"{k}={v}" for k, v in g["params"].items()) or scenario for g in summary]
    for g, label in zip(summary, labels):
        rs = [r for r in runs if r["params"] == g["params"]]
        ax_s.plot([r["seed"] for r in rs], [_nan(r["figures"].get(name)) for r in rs], "o-", ms=4, label=label)
    ax_s.set(xlabel="seed", ylabel=name, title=f"{scenario}: {name} per run")
    ax_s.xaxis.get_major_locator().set_params(integer=True)
    ax_s.legend(fontsize="small")
    x = range(len(summary))
    for stat, style in (("median", "o-"), ("p90", "s--"), ("worst", "^:")):
        ax_g.plot(x, [_nan(g["figures"].get(name, {}).get(stat)) for g in summary], style, label=stat)
    ax_g.set_xticks(list(x), labels, rotation=20, ha="right", fontsize="small")
    ax_g.set(ylabel=name, title="per grid point")
    ax_g.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}" + ("" if count == 1 else "s")


def _nan(v) -> float:
    return math.nan if v is None else v
