"""Golden byte vectors: every message's example (``protocol.examples``)
encoded for each link, shipped under ``protocol/golden/``:

- ``serial/NAME.bin``: the serial frame, COBS-encoded with its 0x00;
- ``serial/NAME.signed.bin``: signed with ``examples.SIGNING_KEY`` (signable
  commands only);
- ``can/NAME.log``: the classic CAN frames in candump ``-L`` / python-can
  ``.log`` format (``(time) can0 ID#DATA``);
- ``can/NAME.signed.log``: the signed PDU's classic frames;
- ``can/NAME.fd.log``: the CAN FD frames (``ID##<flags>DATA``).

``coiltrack golden --write`` regenerates them; ``coiltrack golden`` (and the
golden-file test) regenerate in memory and compare byte for byte. A change
to the schema table changes the hash in HEARTBEAT and the CRC extra bytes,
so the vectors must be regenerated and reviewed together with the table.
"""
from __future__ import annotations

from pathlib import Path

from .examples import EXAMPLES, SIGNING_KEY, SIGNING_LINK_ID, SIGNING_TIMESTAMP
from .framing import cobs_encode, encode_frame
from .signing import Signer

GOLDEN_DIR = Path(__file__).with_name("golden")
CHANNEL = "can0"


def format_can_log(frames, channel: str = CHANNEL, t0: float = 0.0, dt: float = 1e-4) -> str:
    """candump ``-L`` lines for classic and FD frames (deterministic times)."""
    lines = []
    for i, f in enumerate(frames):
        ident = f"{f.arbitration_id:08X}" if f.is_extended_id else f"{f.arbitration_id:03X}"
        data = bytes(f.data).hex().upper()
        if f.is_fd:
            flags = (1 if f.bitrate_switch else 0) | (2 if f.error_state_indicator else 0)
            body = f"{ident}##{flags:X}{data}"
        else:
            body = f"{ident}#{data}"
        lines.append(f"({t0 + i * dt:.6f}) {channel} {body}")
    return "\n".join(lines) + "\n"


def golden_files() -> dict[str, bytes]:
    """Relative path -> expected bytes, for every golden file."""
    from .can import CanCodec

    classic, fd = CanCodec(fd=False), CanCodec(fd=True, brs=True)
    out: dict[str, bytes] = {}
    for name, ex in EXAMPLES.items():
        out[f"serial/{name}.bin"] = encode_frame(ex.msg, ex.seq, ex.src)
        out[f"can/{name}.log"] = format_can_log(classic.encode(ex.msg, ex.seq, ex.src)).encode()
        out[f"can/{name}.fd.log"] = format_can_log(fd.encode(ex.msg, ex.seq, ex.src)).encode()
        if ex.msg.DEF.signable:
            raw = Signer(SIGNING_KEY, SIGNING_LINK_ID).signed_frame(ex.msg, ex.seq, ex.src, SIGNING_TIMESTAMP)
            out[f"serial/{name}.signed.bin"] = cobs_encode(raw) + b"\x00"
            out[f"can/{name}.signed.log"] = format_can_log(classic.frames_from_raw(raw)).encode()
    return out


def write_golden(directory: Path | str | None = None) -> list[Path]:
    d = Path(directory) if directory is not None else GOLDEN_DIR
    written = []
    files = golden_files()
    for rel, data in files.items():
        p = d / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        if not p.exists() or p.read_bytes() != data:
            p.write_bytes(data)
            written.append(p)
    return written


def check_golden(directory: Path | str | None = None) -> list[str]:
    """Differences between the files on disk and a fresh generation."""
    d = Path(directory) if directory is not None else GOLDEN_DIR
    problems = []
    files = golden_files()
    for rel, data in files.items():
        p = d / rel
        if not p.exists():
            problems.append(f"missing {rel}")
        elif p.read_bytes() != data:
            problems.append(f"differs {rel}")
    for sub in ("serial", "can"):
        if (d / sub).is_dir():
            for p in sorted((d / sub).iterdir()):
                rel = f"{sub}/{p.name}"
                if rel not in files:
                    problems.append(f"unexpected {rel}")
    return problems


def read_can_log(path) -> list:
    """Frames of a python-can readable log (``.log``, ``.asc``, ``.blf``, ...)."""
    import can

    with can.LogReader(str(path)) as reader:
        return list(reader)
