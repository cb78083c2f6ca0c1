"""Run a scenario on the emulated bench and report accuracy against ground truth."""
from __future__ import annotations

import sys

HELP = "run a scenario on the emulated bench"


def add_arguments(p) -> None:
    p.add_argument("--scenario", default="roetenberg-bench", help="scenario name (default roetenberg-bench)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    p.add_argument("--transport", choices=("inproc", "pty"), default="inproc",
                   help="inproc: one process, simulated clock (default); pty: firmware and emulator "
                        "as two processes over a pseudo-terminal, wall clock")
    p.add_argument("--faults", default="", help="link faults, e.g. corrupt=0.01,drop=0.005,truncate=0.005")
    p.add_argument("--json", metavar="PATH", help="write the report as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress line")


def run(args) -> int:
    from hil.faults import LinkFaults

    from . import report, scenarios

    sc = scenarios.get(args.scenario)
    duration = args.duration if args.duration is not None else sc.duration_s
    if duration <= 0:
        print("coiltrack bench: --duration must be > 0", file=sys.stderr)
        return 2
    try:
        faults = LinkFaults.parse(args.faults)
    except ValueError as exc:
        print(f"coiltrack bench: --faults: {exc}", file=sys.stderr)
        return 2
    if args.transport == "inproc":
        from .runner import run_inproc

        rep = run_inproc(sc, args.seed, duration, faults=faults, progress=not args.quiet)
    else:
        from .realtime import run_pty

        rep = run_pty(sc, args.seed, duration, faults=faults, progress=not args.quiet)
    print(f"coiltrack bench: {sc.description}")
    print(report.format_table(rep))
    if args.json:
        report.write_json(rep, args.json)
        print(f"report written to {args.json}")
    return 0
