"""Run a scenario on the emulated bench and report accuracy against ground truth.

Stopped early (SIGINT, SIGTERM), it reports what was done, marked
``"interrupted": true``, and leaves no process or temporary file behind."""
from __future__ import annotations

import sys

from .. import args as A
from .. import scenarios
from ..bench.sweep import experiment
from ..inputs.infile import InputFileError
from ..inputs.userconfig import load_over
from ..outputs import report
from ..outputs.sinks import add_bench_arguments, open_or_exit
from ..scenarios import get
from ..stopping import Stopped, mark

EXIT = {130: "stopped by SIGINT: the report of what was done is printed (and written), marked interrupted",
        143: "stopped by SIGTERM: likewise"}
HELP = "run a scenario on the emulated bench"


def epilog() -> str:
    return scenarios.listing()


def add_arguments(p) -> None:
    p.add_argument("--scenario", type=scenarios.known, default="roetenberg-bench",
                   help="scenario name, listed below (default roetenberg-bench)")
    p.add_argument("--seed", type=A.seed, default=1, help="0..2^32-1 (default 1)")
    p.add_argument("--duration", type=A.bench_seconds, default=None,
                   help=f"simulated seconds, (0, {A.MAX_BENCH_S:g}] (default: the scenario's)")
    p.add_argument("--config", type=A.input_file, metavar="FILE",
                   help="TOML firmware configuration put over the scenario's (see examples/firmware.toml)")
    p.add_argument("--transport", choices=("inproc", "can", "pty", "slcan"), default="inproc",
                   help="inproc: one process, simulated clock, byte pipe (default); can: one process, "
                        "simulated clock, an in-process python-can bus; pty: firmware and emulator as two "
                        "processes over a pseudo-terminal serial link, wall clock; slcan: two processes "
                        "on a CAN bus through slcan adapters on pseudo-terminals, wall clock")
    p.add_argument("--faults", default="",
                   help="fault switches, comma separated (see hil/faults.py): link drop=P, corrupt=P, "
                        "truncate=P, duplicate=P, garbage=P, delay=P [delay_ms=MS], both_ways=1; nodes and "
                        "world drift=[NODE:]PPM, clock_step=[NODE:]STEP@T, sat=WHEN, open_circuit=COIL@WHEN, "
                        "short=COIL@WHEN, sag=FACTOR@WHEN, overheat=COIL@WHEN, metal=WHEN, node_off=NODE@T1-T2 (NODE sensor|driver; "
                        "WHEN T or T1-T2; times 20s, 1500ms). E.g. drop=0.01,clock_step=5ms@8s,metal=12s")
    p.add_argument("--calibration", metavar="FILE",
                   help="calibration file (TOML, from `coiltrack calibrate`) the firmware applies")
    p.add_argument("--json", type=A.output_path, metavar="PATH", help="write the report as JSON")
    p.add_argument("--log", type=A.output_path, metavar="PATH",
                   help="write what the firmware received, tick by tick (JSON lines; for `coiltrack perf --log` "
                        "and `coiltrack smooth`; in-process transports only)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument("--core", choices=("compiled", "python"), default=None,
                   help="the firmware's numeric core ([core] impl; default the configuration's: compiled "
                        "where the extension is built)")
    p.add_argument("--key", type=A.signing_key, metavar="KEY",
                   help="sign the firmware's commands with KEY (64 hex digits, a passphrase, @FILE or @env for "
                        "$COILTRACK_SIGNING_KEY); the emulated nodes then require signatures and refuse, and count, "
                        "unsigned or forged commands")
    add_bench_arguments(p)


def _setup(args):
    """The scenario, duration, firmware configuration and faults of the run, or the
    one-line error (a str) that refuses one of them."""
    from coiltrack.firmware.config import ConfigError

    # imported where used here and below: the world's physics (magpylib) loads only when a run starts
    from ..bench.runner import parse_faults

    sc = get(args.scenario)
    if experiment(args.scenario) is not None:
        return (f"--scenario {args.scenario}: a measurement-level experiment, not a bench run; "
                f"run it with `coiltrack sweep --scenario {args.scenario}`")
    if args.log and args.transport not in ("inproc", "can"):
        return "--log needs an in-process transport (inproc or can)"
    try:
        cfg = load_over(args.config, sc.firmware_config()) if args.config else None
    except InputFileError as exc:
        return f"--config {exc}"
    except ConfigError as exc:
        return f"--config {args.config}: {exc}"
    try:
        faults = parse_faults(args.faults, sc)
    except ValueError as exc:
        return f"--faults: {exc}"
    if args.key:
        import dataclasses

        cfg = (cfg or sc.firmware_config()).with_(signing={"signing_key": args.key})
    if args.core:
        import dataclasses

        cfg = (cfg or sc.firmware_config()).with_(core={"impl": args.core})
    if args.calibration:
        from ..inputs.calibfile import with_calibration

        cfg = with_calibration(args.calibration, cfg or sc.firmware_config())
        if isinstance(cfg, str):
            return cfg
    return sc, (args.duration if args.duration is not None else sc.duration_s), cfg, faults


def _run(args, sc, duration, cfg, faults, outputs) -> dict:
    from ..bench.recovery import TraceKeeper, add_recovery_reference, needs_reference, reference_trace
    from ..bench.runner import add_fixed_comparison, run_inproc

    outputs = keep = TraceKeeper(outputs)   # the fused error trace, for the recovery against a no-fault run
    if args.transport in ("inproc", "can"):
        rep = run_inproc(sc, args.seed, duration, faults=faults, progress=not args.quiet, cfg=cfg,
                         transport=args.transport, log_path=args.log, outputs=outputs)
    else:
        from ..bench.realtime import run_pty

        rep = run_pty(sc, args.seed, duration, faults=faults, progress=not args.quiet, transport=args.transport,
                      cfg=cfg, config_path=args.config, outputs=outputs)
    try:
        # an actuation-policy scenario: the fixed cycle on the same trajectory and seed (fixed_*)
        add_fixed_comparison(rep, sc, args.seed, duration, faults=faults, transport=args.transport)
        # an imperfect-bench scenario: uncalibrated and perfect runs on the same trajectory and seed
        from ..scenarios.imperfect import add_imperfect_comparison

        add_imperfect_comparison(rep, sc, args.seed, duration, cfg=cfg, faults=faults, transport=args.transport)
        # timed faults: each one's recovery against the same run without them (tools.bench.recovery)
        if needs_reference(faults) and keep.trace is not None:
            ref = reference_trace(sc, args.seed, duration, faults=faults, cfg=cfg, transport=args.transport)
            add_recovery_reference(rep, keep.trace, faults, ref)
    except Stopped as exc:
        raise mark(rep, exc) from None
    return rep


def run(args) -> int:
    setup = _setup(args)
    if isinstance(setup, str):
        print(f"coiltrack bench: {setup}", file=sys.stderr)
        return 2
    sc, duration, cfg, faults = setup
    outputs = open_or_exit("bench", args, can_link=args.transport in ("can", "slcan"))
    code = 0
    try:
        rep = _run(args, sc, duration, cfg, faults, outputs)
    except Stopped as exc:
        if exc.partial is None:
            raise
        rep, code = exc.partial, exc.exit_code
        print(f"coiltrack bench: stopped by {exc.reason} at {rep['duration_s']:.1f} s", file=sys.stderr)
    print(f"coiltrack bench: {sc.description}")
    print(report.format_table(rep))
    if args.json:
        report.write_json(rep, args.json)
        print(f"report written to {args.json}")
    if args.log:
        print(f"frame log written to {args.log}")
    outputs.say_written(rep)
    return code
