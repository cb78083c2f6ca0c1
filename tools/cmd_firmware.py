"""Run the firmware alone on the wall clock against a serial port (a real
board's UART, a pseudo-terminal, or ``loop://``)."""
from __future__ import annotations

import json
import sys

HELP = "run the firmware loop on a serial port (wall clock)"


def add_arguments(p) -> None:
    p.add_argument("--port", required=True, help="serial device, pty path or pyserial URL")
    p.add_argument("--baudrate", type=int, default=1_000_000)
    p.add_argument("--config", help="TOML configuration file (default: the scenario's)")
    p.add_argument("--scenario", default="roetenberg-bench", help="take the configuration of this scenario")
    p.add_argument("--duration", type=float, default=0.0, help="seconds to run (0: until interrupted)")
    p.add_argument("--epoch-ns", type=int, default=None, help="CLOCK_MONOTONIC epoch shared with the emulator")
    p.add_argument("--stats-json", help="write tick timing and counters here on exit")


def run(args) -> int:
    from firmware_py.config import ConfigError, load_config
    from firmware_py.firmware import Firmware
    from firmware_py.port import SerialPort
    from hil.clock import WallClock

    from .realtime import firmware_loop
    from .scenarios import get

    try:
        cfg = load_config(args.config) if args.config else get(args.scenario).firmware_config()
    except (ConfigError, OSError) as exc:
        print(f"coiltrack firmware: {exc}", file=sys.stderr)
        return 2
    port = SerialPort(args.port, args.baudrate)
    fw = Firmware(cfg, port)
    clock = WallClock(args.epoch_ns)
    duration_us = int(args.duration * 1e6) if args.duration > 0 else 2**62
    try:
        timing = firmware_loop(fw, clock, duration_us, cfg.tick_us)
    except KeyboardInterrupt:
        timing = {}
    finally:
        port.close()
    if args.stats_json:
        with open(args.stats_json, "w") as fh:
            json.dump({"status": fw.status(), "timing": timing}, fh, indent=2)
    return 0
