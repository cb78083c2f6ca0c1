"""Run the firmware alone on the wall clock against a serial port (a real
board's UART, a pseudo-terminal, or ``loop://``) or a CAN bus.

The firmware is the time master: it broadcasts ``TIME_SYNC`` and the nodes
(emulated by ``coiltrack emulator`` or real boards) synchronise to it, so the
two sides need no shared epoch. ``--epoch-ns`` only lines up the firmware's
clock with an emulator's ground truth when both run on this machine
(``coiltrack bench --transport pty`` does that).

It runs for ``--duration`` seconds, or until stopped (SIGINT, SIGTERM), or
until nothing has arrived from the nodes for ``--peer-timeout`` seconds; each
way it reports its tick timing and counters, marked ``interrupted`` when
stopped early.
"""
from __future__ import annotations

import os
import sys

from .. import args as A
from .. import scenarios
from ..bench.links import add_link_arguments, GuardedPort, open_link, warn_virtual_bus
from ..bench.realtime import KeepAwake, _realtime_setup, firmware_loop, no_ticks
from ..bench.timing import LoopTrace
from ..inputs.infile import InputFileError
from ..inputs.userconfig import load_over
from ..outputs import jsonout
from ..outputs.sinks import add_capture_argument, add_igtl_arguments, open_or_exit
from ..scenarios import get
from ..stopping import PeerSilent, Stopped, mark

HELP = "run the firmware loop on a serial port or a CAN bus (wall clock)"
EXIT = {3: "stopped because the nodes were silent for --peer-timeout seconds (statistics still written)",
        130: "stopped by SIGINT: the statistics of what was done are written, marked interrupted",
        143: "stopped by SIGTERM: likewise"}


def add_arguments(p) -> None:
    add_link_arguments(p)
    p.add_argument("--config", type=A.input_file, metavar="FILE",
                   help="TOML firmware configuration, over the scenario's (see examples/firmware.toml)")
    p.add_argument("--core", choices=("compiled", "python"), default=None,
                   help="the firmware's numeric core ([core] impl; default the configuration's: compiled "
                        "where the extension is built)")
    p.add_argument("--scenario", type=scenarios.known, default="roetenberg-bench",
                   help="take the configuration of this scenario (default roetenberg-bench)")
    p.add_argument("--duration", type=A.real(0.0, A.MAX_WALL_S), default=0.0,
                   help=f"seconds to run, 0..{A.MAX_WALL_S:g} (default 0: until stopped)")
    p.add_argument("--peer-timeout", type=A.real(0.0, 3600.0), default=10.0, metavar="S",
                   help="stop when nothing has arrived for S seconds (default 10; 0: keep waiting)")
    p.add_argument("--calibration", metavar="FILE",
                   help="calibration file (TOML, from `coiltrack calibrate`) applied at start-up")
    p.add_argument("--epoch-ns", type=A.integer(0), default=None, help="CLOCK_MONOTONIC epoch shared with the emulator")
    p.add_argument("--stats-json", type=A.output_path, metavar="PATH", help="write tick timing and counters here on exit")
    p.add_argument("--realtime", action="store_true",
                   help="best-effort real-time set-up: SCHED_FIFO if permitted, cyclic GC frozen and disabled")
    p.add_argument("--cpu", type=A.cpu, default=None, help="pin the loop to this CPU")
    p.add_argument("--no-keep-awake", action="store_true",
                   help="with --realtime --cpu: let that CPU idle between ticks (default: a SCHED_IDLE busy loop "
                        "keeps it awake, as a virtual machine's halted CPU wakes late)")
    p.add_argument("--rt-priority", type=A.integer(1, 99), default=None, metavar="P",
                   help="SCHED_FIFO priority with --realtime, 1..99 (default 30: above the two-process "
                        "bench's emulator at 20, below the kernel's threaded interrupts at 50)")
    add_igtl_arguments(p)
    add_capture_argument(p)
    p.add_argument("--key", type=A.signing_key, metavar="KEY",
                   help="sign the coil commands and configuration writes with KEY (64 hex digits, a passphrase, "
                        "@FILE or @env for $COILTRACK_SIGNING_KEY); overrides signing.signing_key of --config")


def _config(args):
    from coiltrack.firmware.config import ConfigError

    base = get(args.scenario).firmware_config()
    try:
        cfg = load_over(args.config, base) if args.config else base
        if args.key:
            import dataclasses

            cfg = cfg.with_(signing={"signing_key": args.key})
        if args.core:
            import dataclasses

            cfg = cfg.with_(core={"impl": args.core})
        return cfg
    except InputFileError as exc:
        print(f"coiltrack firmware: --config {exc}", file=sys.stderr)
        return None
    except ConfigError as exc:
        print(f"coiltrack firmware: --config {args.config}: {exc}", file=sys.stderr)
        return None


def run(args) -> int:
    from coiltrack.firmware.loop import Firmware
    from coiltrack.hil.clock import WallClock

    cfg = _config(args)
    if cfg is None:
        return 2
    if args.calibration:
        from ..inputs.calibfile import with_calibration

        cfg = with_calibration(args.calibration, cfg)
        if isinstance(cfg, str):
            print(f"coiltrack firmware: {cfg}", file=sys.stderr)
            return 2
    warn_virtual_bus(args, "firmware")
    try:
        link, _ = open_link(args, cfg.link.node_id)
    except ValueError as exc:
        print(f"coiltrack firmware: {exc}", file=sys.stderr)
        return 2
    outputs = open_or_exit("firmware", args, can_link=args.transport == "can")
    clock = WallClock(args.epoch_ns)
    port = GuardedPort(outputs.wrap(link, clock_us=clock.now), clock, args.peer_timeout)
    fw = Firmware(cfg, port)
    rt = {}
    awake = KeepAwake((args.cpu,) if args.realtime and args.cpu is not None and not args.no_keep_awake else ())
    duration_us = int(args.duration * 1e6) if args.duration > 0 else 2**62
    code, report = 0, {}
    trace = LoopTrace(path=os.environ["COILTRACK_LOOP_TRACE"]) if os.environ.get("COILTRACK_LOOP_TRACE") else None
    if trace is not None and hasattr(link, "bytes_rx"):
        trace.link = link
    try:                                # a signal during the set-up is reported as one in the loop
        awake.__enter__()               # before SCHED_FIFO: the busy loop does not inherit it
        if args.realtime or args.cpu is not None:
            rt.update(_realtime_setup(args.cpu, **({"priority": args.rt_priority} if args.rt_priority else {})))
        rt["keep_awake"] = bool(awake.children)
        # a link that coalesces writes (a pty: FdLink) sends a tick's frames together after it
        timing = firmware_loop(fw, clock, duration_us, cfg.timing.tick_us, after_tick=getattr(link, "flush", None),
                               trace=trace, align_us=cfg.timing.align_us, slew_us=cfg.timing.align_slew_us)
    except Stopped as exc:
        # a signal before the loop's first statement has no partial: zero ticks, still the keys
        timing, code = exc.partial or no_ticks(cfg.timing.tick_us), exc.exit_code
        mark(report, exc)
        hint = " (--peer-timeout 0 keeps waiting)" if isinstance(exc, PeerSilent) else ""
        print(f"coiltrack firmware: stopped: {exc.reason}{hint}", file=sys.stderr)
    finally:
        port.close()
        awake.__exit__(None, None, None)
        if trace is not None:
            trace.save()
    timing.update({"rt_" + k: v for k, v in rt.items()})
    timing["link_errors"] = port.errors
    outputs.finish(None, timing)
    report.update({"status": fw.status(), "timing": timing})
    if args.stats_json:
        jsonout.write(args.stats_json, report)
    else:
        print(jsonout.dumps(report, indent=2))
    return code
