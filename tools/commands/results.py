"""Run scenarios on the in-process bench and write the results pages from their reports.

By default the headline scenarios run at their own durations and the pages go to
out/results/ (results.json and index.md). With --publish they go to docs/results/ and the
headline table of README.md is written again from the same results.json (run it from the
repository's top folder); only the scenarios run are replaced in the committed results.json.
The files are written again after every run, so a stopped command keeps the runs it made.
--render writes the pages and the README table again from the committed results.json without
running anything. Figures are those of the simulated clock: the same code, scenario, seed and
duration give the same figures on every machine."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from .. import args as A
from ..docsgen import results as R
from ..docsgen.results import HEADLINE

EXIT = {1: "a scenario run failed: the others are written, the failed one is listed with its error"}
HELP = "run scenarios and write the results pages (and, with --publish, the README's headline table)"

PUBLISH_DIR = Path("docs") / "results"
README = Path("README.md")
#: the files whose headline table --publish renders (between the markers of docsgen.results)
TABLE_FILES = (README, Path("docs") / "index.md")


def _scenarios(text: str) -> list[str]:
    import argparse

    # imported where used here and below: the scenarios (scipy underneath) load only when needed, not for --help
    from ..scenarios import SCENARIOS

    if text == "headline":
        return list(HEADLINE)
    if text == "all":
        return sorted(SCENARIOS)
    names = [t.strip() for t in text.split(",") if t.strip()]
    bad = [n for n in names if n not in SCENARIOS]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"unknown scenario {', '.join(repr(b) for b in bad) or 'list'} "
                                          "(a comma list of names from `coiltrack bench --help`, 'headline' or 'all')")
    return names


def add_arguments(p) -> None:
    p.add_argument("--scenarios", type=_scenarios, default="headline", metavar="LIST",
                   help="comma list of scenario names, 'headline' (the README's table: default) or 'all'")
    p.add_argument("--seed", type=A.seed, default=1, help="0..2^32-1 (default 1)")
    p.add_argument("--duration", type=A.bench_seconds, default=None,
                   help=f"simulated seconds of every run, (0, {A.MAX_BENCH_S:g}] (default: each scenario's own)")
    p.add_argument("--workers", type=A.integer(1, 64), default=1,
                   help="runs at the same time, in spawned processes, 1-64 (default 1)")
    p.add_argument("--core", choices=("compiled", "python"), default=None,
                   help="the firmware's numeric core of every run ([core] impl; default the configuration's: "
                        "compiled where the extension is built); the two give the same figures")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="firmware configuration key (section.key, e.g. budget.track_budget_evals, or a plain key) "
                        "and one value, put over every scenario's configuration; repeatable. The runs' "
                        "commands are then `coiltrack sweep ... --set`; not with --publish")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--out", metavar="DIR", default="out/results",
                   help="directory of results.json and index.md (default out/results; created)")
    g.add_argument("--publish", action="store_true",
                   help="write into docs/results/ (merged with the runs already there) and the README's table")
    p.add_argument("--render", action="store_true",
                   help="with --publish: render the pages and the README's table from docs/results/results.json "
                        "without running anything")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("coiltrack")
    except PackageNotFoundError:
        return "unknown"


def _overrides(args) -> tuple:
    """The ``--set`` overrides as ((key, value), ...), each applied to every scenario of the run
    once before anything runs (a ValueError naming the key, the value or the scenario)."""
    from coiltrack.firmware.config import ConfigError, qualified

    from ..bench import sweep

    if not args.sets:
        return ()
    if args.publish:
        raise ValueError("the published results are the scenarios' own configurations: not with --publish")
    pairs = []
    for text in args.sets:
        key, values = sweep.parse_set(text)
        if len(values) != 1:
            raise ValueError(f"'{text}': one value per key here (`coiltrack sweep --set` takes several)")
        pairs.append((key, values[0]))
    keys = [qualified(k) for k, _ in pairs]            # pulse_us and timing.pulse_us are one key
    if len(set(keys)) != len(keys):
        raise ValueError("a key is given twice")
    for name in args.scenarios:
        try:
            sweep.scenario_with(name, pairs)
        except ConfigError as exc:
            raise ValueError(f"{' '.join(args.sets)} on {name}: {exc}") from None
    return tuple(pairs)


def run(args) -> int:
    if args.render and not args.publish:
        print("coiltrack results: error: --render needs --publish", file=sys.stderr)
        return 2
    try:
        overrides = _overrides(args)
    except ValueError as exc:
        print(f"coiltrack results: error: argument --set: {exc}", file=sys.stderr)
        return 2
    out = PUBLISH_DIR if args.publish else Path(args.out)
    if out.exists() and not out.is_dir():
        print(f"coiltrack results: error: argument --out: '{out}' is not a directory", file=sys.stderr)
        return 2
    if args.publish and not (README.is_file() and R.readme_block(README.read_text()) is not None):
        print("coiltrack results: error: --publish: run it from the repository's top folder (README.md with "
              "its results block not found here)", file=sys.stderr)
        return 2
    old = None
    if (out / "results.json").is_file():
        try:
            old = json.loads((out / "results.json").read_text())
        except ValueError:
            old = None
    if args.render:
        if old is None:
            print(f"coiltrack results: error: --render: no readable {out / 'results.json'}", file=sys.stderr)
            return 2
        data = old
    else:
        done = []

        def progress(r):
            what = r.get("error") or f"{r['report'].get('position_rms_mm')} mm"
            print(f"  {r['scenario']:<40} {r['duration_s']:g} s  {what}", file=sys.stderr, flush=True)
            done.append(r)              # written after every run: a stopped command keeps what it ran
            R.write(out, R.merge(old if args.publish else None, done, _version()))

        print(f"coiltrack results: {len(args.scenarios)} scenarios, seed {args.seed}, "
              f"{args.workers} worker(s)", file=sys.stderr)
        runs = R.run_all(args.scenarios, args.seed, args.duration, args.workers, progress, args.core, overrides)
        data = R.merge(old if args.publish else None, runs, _version())
    for path in R.write(out, data):
        print(f"wrote {path}")
    if args.publish:
        table = R.headline_table(data)
        for path in TABLE_FILES:
            if path.is_file() and R.readme_block(path.read_text()) is not None:
                path.write_text(R.update_readme(path.read_text(), table))
                print(f"wrote the headline table of {path}")
    failed = [r["scenario"] for r in data["runs"] if "error" in r]
    if failed:
        print(f"coiltrack results: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0
