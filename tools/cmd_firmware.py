"""Run the firmware alone on the wall clock against a serial port (a real
board's UART, a pseudo-terminal, or ``loop://``).

The firmware is the time master: it broadcasts ``TIME_SYNC`` and the nodes
(emulated by ``coiltrack emulator`` or real boards) synchronise to it, so the
two sides need no shared epoch. ``--epoch-ns`` only lines up the firmware's
clock with an emulator's ground truth when both run on this machine
(``coiltrack bench --transport pty`` does that).
"""
from __future__ import annotations

import json
import sys

HELP = "run the firmware loop on a serial port (wall clock)"


def add_arguments(p) -> None:
    p.add_argument("--transport", choices=("serial", "can"), default="serial",
                   help="serial: COBS frames on --port; can: the same messages on a python-can bus")
    p.add_argument("--port", help="serial device, pty path or pyserial URL (--transport serial)")
    p.add_argument("--interface", default="slcan", help="python-can interface (--transport can): slcan, socketcan, virtual")
    p.add_argument("--channel", help="python-can channel (--transport can): slcan device or pty, can0, ...")
    p.add_argument("--bitrate", type=int, default=500_000, help="CAN bit rate (--transport can)")
    p.add_argument("--baudrate", type=int, default=1_000_000)
    p.add_argument("--config", help="TOML configuration file (default: the scenario's)")
    p.add_argument("--scenario", default="roetenberg-bench", help="take the configuration of this scenario")
    p.add_argument("--duration", type=float, default=0.0, help="seconds to run (0: until interrupted)")
    p.add_argument("--epoch-ns", type=int, default=None, help="CLOCK_MONOTONIC epoch shared with the emulator")
    p.add_argument("--stats-json", help="write tick timing and counters here on exit")
    p.add_argument("--realtime", action="store_true",
                   help="best-effort real-time set-up: SCHED_FIFO if permitted, cyclic GC frozen and disabled")
    p.add_argument("--cpu", type=int, default=None, help="pin the loop to this CPU")
    from .outputs import add_capture_argument, add_igtl_arguments

    add_igtl_arguments(p)
    add_capture_argument(p)


class _LinkGuard:
    """Wraps the port so that a link that goes away (a pty whose other side closed, a USB
    adapter unplugged: EIO) costs frames, not the firmware loop. Errors are counted."""

    def __init__(self, port):
        self.port = port
        self.errors = 0

    def read(self) -> bytes:
        try:
            return self.port.read()
        except (OSError, ValueError):      # pyserial's SerialException is an OSError
            self.errors += 1
            return b""

    def write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except (OSError, ValueError):
            self.errors += 1

    def close(self) -> None:
        try:
            self.port.close()
        except OSError:
            pass


def run(args) -> int:
    from coiltrack.firmware.config import ConfigError, load_config
    from coiltrack.firmware.loop import Firmware
    from coiltrack.firmware.port import SerialPort
    from coiltrack.hil.clock import WallClock

    from .realtime import _realtime_setup, firmware_loop
    from .scenarios import get

    try:
        cfg = load_config(args.config) if args.config else get(args.scenario).firmware_config()
    except (ConfigError, OSError) as exc:
        print(f"coiltrack firmware: {exc}", file=sys.stderr)
        return 2
    from .outputs import open_or_exit

    outputs = open_or_exit("firmware", args, can_link=args.transport == "can")
    where = args.port if args.transport == "serial" else f"{args.interface}:{args.channel}"
    if (args.port if args.transport == "serial" else args.channel) is None:
        print(f"coiltrack firmware: --transport {args.transport} needs "
              f"{'--port' if args.transport == 'serial' else '--channel'}", file=sys.stderr)
        return 2
    try:
        if args.transport == "serial":
            port = SerialPort(args.port, args.baudrate)
        else:
            from coiltrack.protocol.can import CanLink, open_bus

            port = CanLink(open_bus(args.interface, args.channel, args.bitrate), cfg.node_id)
    except Exception as exc:  # pyserial: SerialException (an OSError) or ValueError; python-can: CanError
        print(f"coiltrack firmware: cannot open {where}: {exc}", file=sys.stderr)
        return 2
    port = _LinkGuard(outputs.wrap(port, clock_us=WallClock(args.epoch_ns).now))
    fw = Firmware(cfg, port)
    rt = _realtime_setup(args.cpu) if (args.realtime or args.cpu is not None) else {}
    clock = WallClock(args.epoch_ns)
    duration_us = int(args.duration * 1e6) if args.duration > 0 else 2**62
    try:
        timing = firmware_loop(fw, clock, duration_us, cfg.tick_us)
    except KeyboardInterrupt:
        timing = {}
    finally:
        port.close()
    timing.update({"rt_" + k: v for k, v in rt.items()})
    timing["link_errors"] = port.errors
    outputs.finish(None, timing)
    if args.stats_json:
        with open(args.stats_json, "w") as fh:
            json.dump({"status": fw.status(), "timing": timing}, fh, indent=2)
    else:
        print(json.dumps({"status": fw.status(), "timing": timing}, indent=2))
    return 0
