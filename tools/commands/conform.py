"""Run the protocol conformance suite against a node (or a set of nodes) on
a serial port or a CAN bus, and print pass/fail per message and per rule.
The tester plays the master (node 1); it finds nodes by their HEARTBEAT and
runs the rules of each node's role (see protocol/conformance.py and
docs/protocol.md). Exit status 0 when everything applicable passes."""
from __future__ import annotations

import sys

from .. import args as A
from ..bench.links import warn_virtual_bus

EXIT = {1: "a rule that applies to a node failed"}
HELP = "conformance suite against a node on a serial port or CAN bus"


def add_arguments(p) -> None:
    p.add_argument("--transport", choices=("serial", "can"), default="serial")
    p.add_argument("--port", help="serial: device, pty path or pyserial URL")
    p.add_argument("--baudrate", type=A.bitrate, default=1_000_000)
    p.add_argument("--interface", default="slcan", help="can: python-can interface (slcan, virtual, socketcan)")
    p.add_argument("--channel", help="can: channel (slcan: serial device or pty path; virtual: a name)")
    p.add_argument("--bitrate", type=A.bitrate, default=500_000)
    p.add_argument("--fd", action="store_true", help="can: send CAN FD frames")
    p.add_argument("--key", help="signing key (64 hex digits, or a passphrase hashed with SHA-256): "
                                 "sign commands and check that unsigned, forged and replayed ones are refused")
    p.add_argument("--link-id", type=A.integer(0, 255), default=0, help="signing link id, 0..255 (default 0)")
    p.add_argument("--src", type=A.node_id, default=1, help="the tester's node id (default 1, the firmware's)")
    p.add_argument("--node", type=A.node_id, help="test only this node id")
    p.add_argument("--mag-rate", type=A.real(0.0, 100_000.0), default=120.0,
                   help="expected MAG_SAMPLE rate, Hz (0: any steady rate)")
    p.add_argument("--observe", type=A.real(0.0, 3600.0, lo_open=True), default=1.2,
                   help="seconds of stream observation (default 1.2)")
    p.add_argument("--discover", type=A.real(0.0, 3600.0, lo_open=True), default=None,
                   help="seconds to listen for nodes (default: the 1.5 s heartbeat timeout)")
    p.add_argument("--lead-ms", type=A.real(0.0, 10_000.0, lo_open=True), default=100.0,
                   help="pulses are scheduled this far ahead")
    p.add_argument("--answer-timeout", type=A.real(0.0, 3600.0, lo_open=True), default=1.0,
                   help="seconds an answer may take after its pulse (default 1.0; a node on a loaded "
                        "machine or behind a slow link needs more)")
    p.add_argument("--sync-period", type=A.real(0.0, 3600.0, lo_open=True), default=0.5,
                   help="TIME_SYNC broadcast period, s (default 0.5)")
    p.add_argument("--bench", action="store_true",
                   help="bench mode: the driver and the sensor share a real coil; pulses of the firmware's length "
                        "and current must show in the sensor's samples inside the firmware's window "
                        "(rule bench_pulse, with the edges and their margins in microseconds)")
    p.add_argument("--bench-current-ma", type=A.integer(1, 30_000), default=1500,
                   help="bench mode: pulse current, mA (default 1500, the firmware's)")
    p.add_argument("--bench-pulse-ms", type=A.real(5.0, 10_000.0), default=60.0,
                   help="bench mode: pulse length, ms (default 60, the firmware's)")
    p.add_argument("--seed", type=A.seed, default=1)
    p.add_argument("--json", type=A.output_path, metavar="PATH", help="also write the report as JSON")


def open_link(args):
    """The tester's Port and a description of it."""
    if args.transport == "serial":
        if not args.port:
            raise ValueError("--port is required with --transport serial")
        from coiltrack.protocol.serial_link import SerialLink

        return SerialLink(args.port, args.baudrate), f"serial {args.port}"
    if not args.channel:
        raise ValueError("--channel is required with --transport can")
    from coiltrack.protocol.can import CanLink, open_bus

    bus = open_bus(args.interface, args.channel, args.bitrate, fd=args.fd)
    return CanLink(bus, args.src, fd=args.fd), f"CAN {args.interface} {args.channel}"


def run(args) -> int:
    from coiltrack.protocol.conformance import ConformOptions, run_conformance
    from coiltrack.protocol.signing import key_from_text

    opts = ConformOptions(src=args.src, node=args.node, observe_s=args.observe, discover_s=args.discover,
                          lead_ms=args.lead_ms, answer_timeout_s=args.answer_timeout, sync_period_s=args.sync_period,
                          mag_rate_hz=args.mag_rate or None, seed=args.seed, link_id=args.link_id,
                          key=key_from_text(args.key) if args.key else None, bench=args.bench,
                          bench_current_ma=args.bench_current_ma, bench_pulse_ms=args.bench_pulse_ms)
    warn_virtual_bus(args, "conform")
    try:
        link, what = open_link(args)
    except Exception as exc:   # OSError, ValueError; python-can and pyserial initialisation errors
        print(f"coiltrack conform: cannot open the link: {exc}", file=sys.stderr)
        return 2
    try:
        rep = run_conformance(link, opts, transport=what)
    finally:
        link.close()
    print(rep.format())
    if args.json:
        import json

        from ..outputs.jsonout import write

        write(args.json, json.loads(rep.to_json()))
    return 0 if rep.ok else 1
