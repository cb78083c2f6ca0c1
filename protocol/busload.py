"""CAN bus load of a coiltrack system, worst case.

Classic frames count worst-case bit stuffing with the standard formula
(Davis, Burns, Bril, Lukkien 2007, "Controller Area Network (CAN)
schedulability analysis: refuted, revisited and revised")::

    bits(n) = g + 8n + 13 + floor((g + 8n - 1) / 4)

with ``n`` data bytes and ``g = 34`` control bits exposed to stuffing for an
11-bit identifier (54 for a 29-bit one); the 13 are CRC delimiter, ACK, EOF
and the 3-bit interframe space. An 8-byte standard frame is 135 bits.

CAN FD frames (``fd=True``) are an upper estimate: the arbitration phase
(17 bits + 4 stuff bits) and the tail (CRC delimiter, ACK, EOF, IFS: 13
bits) at the nominal rate; ESI, DLC and data with worst-case dynamic
stuffing, the stuff count and the CRC (17 or 21 bits) with their fixed stuff
bits at the data rate.

The traffic model (protocol v4, the sensor bus; HEARTBEAT, TIME_SYNC,
TIME_SYNC_REPLY, COIL_PULSE_CMD and COIL_STATUS in their 8-byte bus forms): every sensor node sends
MAG_PACKED at the magnetometer rate (one 8-byte frame), its IMU as IMU_DELTA
pairs (delta angle and delta velocity, one 8-byte frame each) at the delta
rate, a HEARTBEAT and a TIME_SYNC_REPLY per sync; the coil driver a
HEARTBEAT, a TIME_SYNC_REPLY and one COIL_STATUS per pulse; the firmware
TIME_SYNC, one COIL_PULSE_CMD per pulse (optionally signed), one
MAG_FLIP_CMD per sensor per cycle and its HEARTBEAT. POSE and PULSE_WINDOW
are firmware outputs for the host: they travel on the host link (serial, or
a CAN FD host bus), not on the sensor bus, unless ``host_outputs`` puts them
there (one POSE per sensor per cycle, one PULSE_WINDOW per sensor and coil).
``compact=False`` gives the v1 sample traffic (MAG_SAMPLE, IMU_SAMPLE at the
IMU rate) for comparison.

The TIME_SYNC rate is the firmware's (:func:`sync_broadcasts_per_cycle`): a
periodic broadcast whose timer restarts at every broadcast, plus the ones it
requests around each burst; every node answers each broadcast.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

from .can import PDU_OVERHEAD, direct_size, frame_data_lengths, is_direct, pdu_length
from .framing import SIG_LEN
from .schema import BY_NAME, MAX_NODE_ID, NODE_SENSOR_BASE


def classic_frame_bits(n: int, extended: bool = False) -> int:
    """Worst-case bits on the wire of a classic data frame with ``n`` bytes."""
    if not 0 <= n <= 8:
        raise ValueError("a classic CAN frame carries 0..8 data bytes")
    g = 54 if extended else 34
    return g + 8 * n + 13 + (g + 8 * n - 1) // 4


def fd_frame_time(n: int, bitrate: int, data_bitrate: int, brs: bool = True) -> float:
    """Upper estimate of the time (s) of one CAN FD frame with ``n`` data bytes."""
    nominal = 17 + 4 + 13
    crc = 17 if n <= 16 else 21
    data = 5 + 8 * n + (5 + 8 * n - 1) // 4 + 4 + crc + (4 + crc + 3) // 4
    if not brs:
        return (nominal + data) / bitrate
    return nominal / bitrate + data / data_bitrate


def sync_broadcasts_per_cycle(cycle_us: int, period_us: int, requests_us=(), cycles: int = 16) -> float:
    """TIME_SYNC broadcasts per actuation cycle of a master that broadcasts ``period_us`` after
    its previous broadcast (the timer restarts at each one, requested or periodic) and at each
    requested instant ``requests_us`` (offsets within the cycle, us; a periodic broadcast due at
    a requested instant is that one): the mean over cycles 2..``cycles`` of ``cycles`` simulated
    from a broadcast at 0 (the master's boot). Integer microseconds."""
    if cycle_us <= 0 or period_us <= 0 or cycles < 2:
        raise ValueError("cycle_us and period_us must be positive, cycles at least 2")
    req = sorted(int(r) for r in requests_us if 0 <= r < cycle_us)
    last = -period_us
    count = 0
    for c in range(cycles):
        t0 = c * cycle_us
        for r in [t0 + r for r in req] + [t0 + cycle_us]:
            while last + period_us < r:         # periodic broadcasts due before the next request
                last += period_us
                count += c > 0
            if r < t0 + cycle_us:
                last = r
                count += c > 0
    return count / (cycles - 1)


@dataclass
class Traffic:
    sensors: int = 8
    coils: int = 3
    mag_rate_hz: float = 120.0
    imu_rate_hz: float = 100.0
    #: IMU_DELTA pairs per second per node (compact traffic; 0: no IMU)
    imu_delta_rate_hz: float = 10.0
    cycle_s: float = 0.6
    heartbeat_hz: float = 1.0
    #: TIME_SYNC broadcasts per second (each answered by every node); the firmware's: 10 per s
    #: (``tools/commands/busload.py`` derives it from the firmware's defaults)
    sync_hz: float = 10.0
    signed_commands: bool = False
    flips_per_cycle: float = 1.0
    pulse_windows: bool = True
    #: POSE and PULSE_WINDOW on the sensor bus (else on the host link)
    host_outputs: bool = False
    #: v2 sample messages (MAG_PACKED, IMU_DELTA); False: MAG_SAMPLE and IMU_SAMPLE
    compact: bool = True


def traffic_rows(t: Traffic) -> list[tuple[str, str, int, float, bool]]:
    """``(message, sender, number of senders, rate per sender Hz, signed)``."""
    cyc = 1.0 / t.cycle_s
    pulses = t.coils * cyc
    if t.compact:
        imu_rate = t.imu_delta_rate_hz if t.imu_rate_hz > 0 else 0.0
        rows = [("MAG_PACKED", "sensor", t.sensors, t.mag_rate_hz, False),
                ("IMU_DELTA", "sensor", t.sensors, 2.0 * imu_rate, False)]
    else:
        rows = [("MAG_SAMPLE", "sensor", t.sensors, t.mag_rate_hz, False),
                ("IMU_SAMPLE", "sensor", t.sensors, t.imu_rate_hz, False)]
    rows += [
        ("HEARTBEAT", "sensor", t.sensors, t.heartbeat_hz, False),
        ("TIME_SYNC_REPLY", "sensor", t.sensors, t.sync_hz, False),
        ("COIL_STATUS", "coil driver", 1, pulses, False),
        ("HEARTBEAT", "coil driver", 1, t.heartbeat_hz, False),
        ("TIME_SYNC_REPLY", "coil driver", 1, t.sync_hz, False),
        ("TIME_SYNC", "firmware", 1, t.sync_hz, False),
        ("COIL_PULSE_CMD", "firmware", 1, pulses, t.signed_commands),
        ("MAG_FLIP_CMD", "firmware", 1, t.flips_per_cycle * t.sensors * cyc, False),
        ("HEARTBEAT", "firmware", 1, t.heartbeat_hz, False),
    ]
    if t.host_outputs:
        rows.append(("POSE", "firmware", 1, t.sensors * cyc, False))
    if t.host_outputs and t.pulse_windows:
        rows.append(("PULSE_WINDOW", "firmware", 1, t.sensors * t.coils * cyc, False))
    return [r for r in rows if r[2] > 0 and r[3] > 0]


def message_bits(name: str, signed: bool = False, fd: bool = False, bitrate: int = 500_000,
                 data_bitrate: int = 2_000_000) -> tuple[list[int], float]:
    """``(data bytes per frame, bus time in nominal bit times)`` of one message."""
    mid = BY_NAME[name].id
    sizes = frame_data_lengths(mid, signed, fd)
    if fd:
        t = sum(fd_frame_time(n, bitrate, data_bitrate) for n in sizes)
        return sizes, t * bitrate
    return sizes, float(sum(classic_frame_bits(n) for n in sizes))


def bus_load(t: Traffic, bitrate: int = 500_000, fd: bool = False, data_bitrate: int = 2_000_000) -> dict:
    rows = []
    total = 0.0
    for name, sender, n, rate, signed in traffic_rows(t):
        sizes, bits = message_bits(name, signed, fd, bitrate, data_bitrate)
        bps = bits * rate * n
        total += bps
        rows.append({"message": name, "sender": sender, "senders": n, "rate_hz": round(rate, 4),
                     "pdu_bytes": (direct_size(BY_NAME[name].id) if not signed and is_direct(BY_NAME[name].id, fd)
                                   else pdu_length(BY_NAME[name].id, signed)), "signed": signed,
                     "frames_per_msg": len(sizes), "frame_bytes": sizes,
                     "bits_per_msg": round(bits, 1), "bits_per_s": round(bps, 1),
                     "load_pct": round(100.0 * bps / bitrate, 3)})
    load = total / bitrate
    # how many sensor nodes fit (load <= 100 %) with everything else unchanged
    fit = 0
    for k in range(0, MAX_NODE_ID - NODE_SENSOR_BASE + 2):
        tk = Traffic(**{**asdict(t), "sensors": k})
        if sum(message_bits(nm, sg, fd, bitrate, data_bitrate)[1] * r * nn
               for nm, _, nn, r, sg in traffic_rows(tk)) <= bitrate:
            fit = k
        else:
            break
    return {
        "bitrate": bitrate, "fd": fd, "data_bitrate": data_bitrate if fd else None,
        "traffic": asdict(t), "rows": rows,
        "total_bits_per_s": round(total, 1), "load_pct": round(100.0 * load, 2),
        "fits": load <= 1.0, "max_sensor_nodes": fit,
        "stuffing": "worst case (Davis et al. 2007)" if not fd else "worst-case estimate (CAN FD)",
        "pdu_overhead_bytes": PDU_OVERHEAD, "signature_bytes": SIG_LEN,
    }


def format_report(rep: dict) -> str:
    lines = []
    mode = "CAN FD, data %d bit/s" % rep["data_bitrate"] if rep["fd"] else "classic CAN, 11-bit ids"
    tr = rep["traffic"]
    lines.append(f"bus load at {rep['bitrate']} bit/s ({mode}), {tr['sensors']} sensor nodes, "
                 f"MAG {tr['mag_rate_hz']:g} Hz, IMU {tr['imu_rate_hz']:g} Hz, {tr['coils']} coils "
                 f"every {tr['cycle_s']:g} s; stuffing {rep['stuffing']}")
    hdr = f"{'message':16s} {'sender':12s} {'n':>3s} {'rate Hz':>8s} {'PDU':>4s} {'frames':>6s} {'bits/msg':>9s} {'bit/s':>10s} {'load %':>8s}"
    lines.append(hdr)
    lines.append("-" * len(hdr))
    for r in rep["rows"]:
        name = r["message"] + (" (signed)" if r["signed"] else "")
        lines.append(f"{name:16s} {r['sender']:12s} {r['senders']:3d} {r['rate_hz']:8.3f} {r['pdu_bytes']:4d} "
                     f"{r['frames_per_msg']:6d} {r['bits_per_msg']:9.1f} {r['bits_per_s']:10.1f} {r['load_pct']:8.2f}")
    lines.append("-" * len(hdr))
    lines.append(f"{'total':16s} {'':12s} {'':3s} {'':8s} {'':4s} {'':6s} {'':9s} "
                 f"{rep['total_bits_per_s']:10.1f} {rep['load_pct']:8.2f}")
    verdict = "fits" if rep["fits"] else "OVERLOADED"
    lines.append(f"{verdict}: {rep['load_pct']:.1f} % of the bus; at most {rep['max_sensor_nodes']} sensor "
                 f"nodes fit at this bit rate with the same traffic per node")
    if not tr.get("host_outputs", True):
        lines.append("POSE and PULSE_WINDOW travel on the host link (serial or a CAN FD host bus), not on this bus")
    return "\n".join(lines)
