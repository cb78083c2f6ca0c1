"""Run the emulated nodes and world alone on the wall clock, for a firmware
(``coiltrack firmware`` or a real board) to talk to: on a serial port, on a
new pseudo-terminal (``--create-pty``), or on a CAN bus (``--transport can
--interface socketcan --channel can0``, or slcan on a serial adapter).

The nodes keep their own drifting clocks and synchronise to the firmware's
``TIME_SYNC`` broadcasts, so the firmware needs no shared epoch. Without
``--epoch-ns`` the recorder learns the firmware's clock from the same
broadcasts to look up the true pose of each ``POSE`` frame; with it (both on
this machine) the two clocks are the same. Stopped early (SIGINT,
SIGTERM), it reports what was done, marked ``interrupted``.
"""
from __future__ import annotations

import sys

from .. import args as A
from .. import scenarios
from ..bench.links import add_link_arguments, FdLink, GuardedPort, make_raw_pty, open_link, warn_virtual_bus
from ..bench.realtime import elapsed_s, emulator_loop
from ..outputs import report
from ..outputs.sinks import add_capture_argument, open_or_exit
from ..stopping import Stopped, mark

EXIT = {130: "stopped by SIGINT: the report of what was done is printed (and written), marked interrupted",
        143: "stopped by SIGTERM: likewise"}
HELP = "run the emulated coil driver and sensor nodes on a serial link or a CAN bus (wall clock)"


def add_arguments(p) -> None:
    add_link_arguments(p, serial_port_type=A.serial_port)
    p.add_argument("--create-pty", action="store_true",
                   help="create a pseudo-terminal, print its path and talk on it (serial frames; not with --transport can)")
    p.add_argument("--scenario", type=scenarios.known, default="roetenberg-bench",
                   help="the world and nodes of this scenario (default roetenberg-bench)")
    p.add_argument("--seed", type=A.seed, default=1, help="0..2^32-1 (default 1)")
    p.add_argument("--duration", type=A.wall_seconds, default=None,
                   help=f"seconds, (0, {A.MAX_WALL_S:g}] (default: the scenario's)")
    p.add_argument("--epoch-ns", type=A.integer(0), default=None, help="CLOCK_MONOTONIC epoch shared with the firmware")
    p.add_argument("--faults", default="", help="fault switches, as for 'coiltrack bench --faults'")
    p.add_argument("--json", type=A.output_path, metavar="PATH", help="write the report as JSON")
    add_capture_argument(p)


def _link(args):
    """The emulator's end of the link (pty, serial port or CAN bus), its kind, and the
    path of a pty created for it (None otherwise)."""
    from coiltrack.protocol.schema import NODE_COIL_DRIVER

    if args.create_pty:
        master, slave, name = make_raw_pty()
        return FdLink(master), "serial", name
    link, _ = open_link(args, NODE_COIL_DRIVER)
    return GuardedPort(link), args.transport, None


def _where(args, kind: str, pty: str | None) -> str:
    """Where the emulator talks, for its waiting line."""
    if pty:
        return f"pty {pty}"
    if kind == "can":
        return f"CAN bus {args.interface}:{args.channel}"
    return f"serial port {args.port}"


def run(args) -> int:
    import coiltrack.hil.world  # noqa: F401 - the bench extra, checked before a link is opened
    from coiltrack.hil.clock import WallClock
    from coiltrack.hil.nodes import Recorder

    # imported where used here and below: the world's physics (magpylib) loads only when a run starts
    from ..bench.runner import BenchSetup, parse_faults

    if not args.create_pty and args.transport == "serial" and args.port is None:
        print("coiltrack emulator: give --port, --create-pty or --transport can --channel", file=sys.stderr)
        return 2
    if args.create_pty and args.transport != "serial":
        print(f"coiltrack emulator: --create-pty makes a serial link (COBS frames on a pseudo-terminal) and "
              f"cannot carry --transport {args.transport}; on CAN give the bus: --interface slcan --channel "
              f"DEVICE, --interface socketcan --channel can0", file=sys.stderr)
        return 2
    warn_virtual_bus(args, "emulator")
    sc = scenarios.get(args.scenario)
    duration = args.duration if args.duration is not None else sc.duration_s
    try:
        faults = parse_faults(args.faults, sc)
    except ValueError as exc:
        print(f"coiltrack emulator: --faults: {exc}", file=sys.stderr)
        return 2
    outputs = open_or_exit("emulator", args)
    try:
        link, kind, pty = _link(args)
    except ValueError as exc:
        print(f"coiltrack emulator: {exc}", file=sys.stderr)
        return 2
    link = outputs.wrap(link, side="emulator", clock_us=WallClock(args.epoch_ns).now)
    bench = BenchSetup(sc, args.seed, duration, link, faults)
    if args.epoch_ns is None:
        # the firmware's clock is its own: learn it from its TIME_SYNC broadcasts
        rec = Recorder(bench.world, master_to_true="sync")
        bench.recorder = bench.emulator.recorder = bench.bench.recorder = rec
    clock = WallClock(args.epoch_ns)
    stopped = None
    try:
        if pty:
            print(pty, flush=True)          # the firmware's side; printed once the emulator is ready
        print(f"coiltrack emulator: the nodes of scenario {sc.name} are up on {_where(args, kind, pty)}; waiting for "
              f"a firmware or tester there (its TIME_SYNC and commands) for {duration:g} s",
              file=sys.stderr, flush=True)
        emulator_loop(bench.emulator, bench.link, clock, int(duration * 1e6))
    except Stopped as exc:
        stopped = exc
    finally:
        link.close()
    done = duration if stopped is None else elapsed_s(clock, duration)
    rep = report.build(bench, {}, done, transport=kind, cfg=sc.firmware_config())
    rep.update(bench.emulator.counters())   # what the emulator itself received (no firmware status here)
    if stopped is not None:
        mark(rep, stopped)
    outputs.finish(bench, rep)
    print(report.format_table(rep))
    if args.json:
        report.write_json(rep, args.json)
    return 0 if stopped is None else stopped.exit_code
