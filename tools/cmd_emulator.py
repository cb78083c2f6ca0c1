"""Run the emulated nodes and world alone on the wall clock, on a serial port
or on a new pseudo-terminal that a firmware (or a real board) connects to.

The nodes keep their own drifting clocks and synchronise to the firmware's
``TIME_SYNC`` broadcasts, so the firmware needs no shared epoch. Without
``--epoch-ns`` the recorder learns the firmware's clock from the same
broadcasts to look up the true pose of each ``POSE`` frame; with it (both on
this machine) the two clocks are the same.
"""
from __future__ import annotations

import sys

HELP = "run the emulated coil driver and sensor nodes on a serial link (wall clock)"


def add_arguments(p) -> None:
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--port", help="serial device or pyserial URL to talk on")
    g.add_argument("--create-pty", action="store_true", help="create a pseudo-terminal and print its path")
    p.add_argument("--baudrate", type=int, default=1_000_000)
    p.add_argument("--scenario", default="roetenberg-bench")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    p.add_argument("--epoch-ns", type=int, default=None, help="CLOCK_MONOTONIC epoch shared with the firmware")
    p.add_argument("--faults", default="", help="fault switches, as for 'coiltrack bench --faults'")
    p.add_argument("--json", metavar="PATH", help="write the report as JSON")
    from .outputs import add_capture_argument

    add_capture_argument(p)


def run(args) -> int:
    from coiltrack.firmware.port import SerialPort  # a plain pyserial wrapper
    from coiltrack.hil.clock import WallClock
    from coiltrack.hil.faults import BenchFaults
    from coiltrack.hil.nodes import Recorder

    from . import report, scenarios
    from .links import FdLink, make_raw_pty
    from .realtime import emulator_loop
    from .runner import BenchSetup

    sc = scenarios.get(args.scenario)
    duration = args.duration if args.duration is not None else sc.duration_s
    try:
        faults = BenchFaults.parse(args.faults)
    except ValueError as exc:
        print(f"coiltrack emulator: --faults: {exc}", file=sys.stderr)
        return 2
    from .outputs import open_or_exit

    outputs = open_or_exit("emulator", args)
    if args.create_pty:
        master, slave, name = make_raw_pty()
        print(name, flush=True)
        link = FdLink(master)
    else:
        try:
            link = SerialPort(args.port, args.baudrate)
        except Exception as exc:  # pyserial: SerialException (an OSError) or ValueError
            print(f"coiltrack emulator: cannot open {args.port}: {exc}", file=sys.stderr)
            return 2
    link = outputs.wrap(link, side="emulator", clock_us=WallClock(args.epoch_ns).now)
    bench = BenchSetup(sc, args.seed, duration, link, faults)
    if args.epoch_ns is None:
        # the firmware's clock is its own: learn it from its TIME_SYNC broadcasts
        rec = Recorder(bench.world, master_to_true="sync")
        bench.recorder = bench.emulator.recorder = bench.bench.recorder = rec
    clock = WallClock(args.epoch_ns)
    try:
        emulator_loop(bench.emulator, bench.link, clock, int(duration * 1e6))
    except KeyboardInterrupt:
        pass
    rep = report.build(bench, {}, duration, transport="serial", cfg=sc.firmware_config())
    outputs.finish(bench, rep)
    print(report.format_table(rep))
    if args.json:
        report.write_json(rep, args.json)
    return 0
