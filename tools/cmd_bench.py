"""Run a scenario on the emulated bench and report accuracy against ground truth."""
from __future__ import annotations

import sys

HELP = "run a scenario on the emulated bench"


def add_arguments(p) -> None:
    p.add_argument("--scenario", default="roetenberg-bench", help="scenario name (default roetenberg-bench)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    p.add_argument("--transport", choices=("inproc", "can", "pty", "slcan"), default="inproc",
                   help="inproc: one process, simulated clock, byte pipe (default); can: one process, "
                        "simulated clock, python-can virtual bus; pty: firmware and emulator as two "
                        "processes over a pseudo-terminal serial link, wall clock; slcan: two processes "
                        "on a CAN bus through slcan adapters on pseudo-terminals, wall clock")
    p.add_argument("--faults", default="",
                   help="fault switches, comma separated (see hil/faults.py): link drop=P, corrupt=P, "
                        "truncate=P, duplicate=P, garbage=P, delay=P [delay_ms=MS], both_ways=1; nodes and "
                        "world drift=[NODE:]PPM, clock_step=[NODE:]STEP@T, sat=WHEN, open_circuit=COIL@WHEN, "
                        "short=COIL@WHEN, sag=FACTOR@WHEN, overheat=COIL@WHEN, metal=WHEN, node_off=NODE@T1-T2 (NODE sensor|driver; "
                        "WHEN T or T1-T2; times 20s, 1500ms). E.g. drop=0.01,clock_step=5ms@8s,metal=12s")
    p.add_argument("--json", metavar="PATH", help="write the report as JSON")
    p.add_argument("--log", metavar="PATH", help="write what the firmware received, tick by tick (JSON lines; "
                                                 "for `coiltrack perf --log` and `coiltrack smooth`; in-process "
                                                 "transports only)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    from .outputs import add_bench_arguments

    add_bench_arguments(p)


def run(args) -> int:
    from coiltrack.hil.faults import BenchFaults

    from . import report, scenarios

    sc = scenarios.get(args.scenario)
    duration = args.duration if args.duration is not None else sc.duration_s
    if duration <= 0:
        print("coiltrack bench: --duration must be > 0", file=sys.stderr)
        return 2
    try:
        faults = BenchFaults.parse(args.faults)
    except ValueError as exc:
        print(f"coiltrack bench: --faults: {exc}", file=sys.stderr)
        return 2
    from .outputs import open_or_exit

    outputs = open_or_exit("bench", args, can_link=args.transport in ("can", "slcan"))
    if args.transport in ("inproc", "can"):
        from .runner import run_inproc

        rep = run_inproc(sc, args.seed, duration, faults=faults, progress=not args.quiet,
                         transport=args.transport, log_path=args.log, outputs=outputs)
    else:
        if args.log:
            print("coiltrack bench: --log needs an in-process transport", file=sys.stderr)
            return 2
        from .realtime import run_pty

        rep = run_pty(sc, args.seed, duration, faults=faults, progress=not args.quiet,
                      transport=args.transport, outputs=outputs)
    if sc.fixed_config is not None:
        # an actuation-policy scenario: the fixed cycle on the same trajectory and seed (fixed_*)
        from .runner import add_fixed_comparison

        add_fixed_comparison(rep, sc, args.seed, duration, faults=faults, transport=args.transport)
    print(f"coiltrack bench: {sc.description}")
    print(report.format_table(rep))
    if args.json:
        report.write_json(rep, args.json)
        print(f"report written to {args.json}")
    if args.log:
        print(f"frame log written to {args.log}")
    outputs.say_written(rep)
    return 0
