"""CAN bus load of a coiltrack system: N sensor nodes (MAG_PACKED at the
magnetometer rate, IMU_DELTA pairs at the delta rate, heartbeats, sync replies),
the coil driver and the firmware, per message and in total, with worst-case
bit stuffing for classic frames."""
from __future__ import annotations

import json

from . import args as A

HELP = "CAN bus load for N sensor nodes at a bit rate (worst-case stuffing)"


def add_arguments(p) -> None:
    p.add_argument("--nodes", type=A.integer(0, 48), default=8, help="sensor nodes, 0..48 (ids 16..63; default 8)")
    p.add_argument("--bitrate", type=A.bitrate, default=500_000, help="nominal bit rate, bit/s (default 500000)")
    p.add_argument("--mag-rate", type=A.real(0.0, 100_000.0), default=120.0,
                   help="MAG_SAMPLE rate per node, Hz (default 120)")
    p.add_argument("--imu-rate", type=A.real(0.0, 100_000.0), default=100.0,
                   help="IMU sampling rate per node, Hz (default 100; 0: no IMU; the IMU_SAMPLE rate with --v1)")
    p.add_argument("--imu-delta-rate", type=A.real(0.0, 100_000.0), default=10.0,
                   help="IMU_DELTA pairs per node per second (default 10)")
    p.add_argument("--host-outputs", action="store_true",
                   help="POSE and PULSE_WINDOW on this bus too (default: on the host link)")
    p.add_argument("--v1", action="store_true", help="protocol v1 sample traffic (MAG_SAMPLE, IMU_SAMPLE)")
    p.add_argument("--coils", type=A.integer(1, 16), default=3, help="source coils, 1..16 (default 3)")
    p.add_argument("--cycle-ms", type=A.real(0.0, 3_600_000.0, lo_open=True), default=600.0,
                   help="actuation cycle (default 600 ms)")
    p.add_argument("--sync-rate", type=A.real(0.0, 10_000.0), default=1.0, help="TIME_SYNC rate, Hz (default 1)")
    p.add_argument("--heartbeat-rate", type=A.real(0.0, 10_000.0), default=1.0, help="HEARTBEAT rate, Hz (default 1)")
    p.add_argument("--signed", action="store_true", help="pulse commands signed (+13 bytes)")
    p.add_argument("--no-pulse-windows", action="store_true", help="firmware does not send PULSE_WINDOW")
    p.add_argument("--fd", action="store_true", help="CAN FD frames (estimate)")
    p.add_argument("--data-bitrate", type=A.bitrate, default=2_000_000, help="CAN FD data phase bit rate")
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def run(args) -> int:
    from coiltrack.protocol.busload import Traffic, bus_load, format_report

    t = Traffic(sensors=args.nodes, coils=args.coils, mag_rate_hz=args.mag_rate, imu_rate_hz=args.imu_rate,
                cycle_s=args.cycle_ms / 1000.0, heartbeat_hz=args.heartbeat_rate, sync_hz=args.sync_rate,
                signed_commands=args.signed, pulse_windows=not args.no_pulse_windows,
                imu_delta_rate_hz=args.imu_delta_rate, host_outputs=args.host_outputs, compact=not args.v1)
    rep = bus_load(t, args.bitrate, args.fd, args.data_bitrate)
    print(json.dumps(rep, indent=2) if args.json else format_report(rep))
    return 0
