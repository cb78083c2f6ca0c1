"""CAN bus load of a coiltrack system: N sensor nodes (MAG_PACKED at the
magnetometer rate, IMU_DELTA pairs at the delta rate, heartbeats, sync replies),
the coil driver and the firmware, per message and in total, with worst-case
bit stuffing for classic frames.

The TIME_SYNC rate (and the cycle and the coils) default to what the firmware
does with its defaults (``FirmwareConfig``, ``SupervisorConfig``): a periodic
broadcast every ``sync_period_us`` after the previous one, and with
``sync_around_burst`` one as the commands leave and three after the last pulse
ends (``Supervisor.step``), each answered by every node."""
from __future__ import annotations

import json

from .. import args as A

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
    p.add_argument("--coils", type=A.integer(1, 16), default=None,
                   help="source coils, 1..16 (default: the firmware's, 3)")
    p.add_argument("--cycle-ms", type=A.real(0.0, 3_600_000.0, lo_open=True), default=None,
                   help="actuation cycle (default: the firmware's, 600 ms)")
    p.add_argument("--sync-rate", type=A.real(0.0, 10_000.0), default=None,
                   help="TIME_SYNC rate, Hz (default: the firmware's, from its defaults and the cycle: 10 Hz)")
    p.add_argument("--heartbeat-rate", type=A.real(0.0, 10_000.0), default=1.0, help="HEARTBEAT rate, Hz (default 1)")
    p.add_argument("--signed", action="store_true", help="pulse commands signed (+13 bytes)")
    p.add_argument("--no-pulse-windows", action="store_true", help="firmware does not send PULSE_WINDOW")
    p.add_argument("--fd", action="store_true", help="CAN FD frames (estimate)")
    p.add_argument("--data-bitrate", type=A.bitrate, default=2_000_000, help="CAN FD data phase bit rate")
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def firmware_sync_hz(cycle_us: int | None = None, coils: int | None = None) -> float:
    """TIME_SYNC broadcasts per second of the firmware with its default configuration (the cycle
    and the number of coils may be changed): ``sync_period_us`` after the previous broadcast, and
    with ``sync_around_burst`` one as the commands leave (``lead_us`` before the cycle) and
    ``supervisor.BURST_SYNCS_AFTER_US`` after the last pulse ends (``(coils - 1) * spacing_us + pulse_us``
    into the cycle)."""
    from coiltrack.firmware.config import FirmwareConfig
    from coiltrack.firmware.supervise.supervisor import BURST_SYNCS_AFTER_US, SupervisorConfig
    from coiltrack.protocol.busload import sync_broadcasts_per_cycle

    fc, sc = FirmwareConfig(), SupervisorConfig()
    cycle = fc.timing.cycle_us if cycle_us is None else int(cycle_us)
    n = len(fc.source.coils) if coils is None else int(coils)
    req = []
    if sc.sync_around_burst:
        last_end = fc.timing.lead_us + (n - 1) * fc.timing.spacing_us + fc.timing.pulse_us     # after the commands leave
        req = [0] + [last_end + d for d in BURST_SYNCS_AFTER_US]
    return sync_broadcasts_per_cycle(cycle, sc.sync_period_us, req) * 1e6 / cycle


def run(args) -> int:
    from coiltrack.firmware.config import FirmwareConfig
    from coiltrack.protocol.busload import Traffic, bus_load, format_report

    fc = FirmwareConfig()
    coils = len(fc.source.coils) if args.coils is None else args.coils
    cycle_us = fc.timing.cycle_us if args.cycle_ms is None else int(round(args.cycle_ms * 1000.0))
    sync_hz = firmware_sync_hz(cycle_us, coils) if args.sync_rate is None else args.sync_rate
    t = Traffic(sensors=args.nodes, coils=coils, mag_rate_hz=args.mag_rate, imu_rate_hz=args.imu_rate,
                cycle_s=cycle_us / 1e6, heartbeat_hz=args.heartbeat_rate, sync_hz=sync_hz,
                signed_commands=args.signed, pulse_windows=not args.no_pulse_windows,
                imu_delta_rate_hz=args.imu_delta_rate, host_outputs=args.host_outputs, compact=not args.v1)
    rep = bus_load(t, args.bitrate, args.fd, args.data_bitrate)
    print(json.dumps(rep, indent=2) if args.json else format_report(rep))
    return 0
