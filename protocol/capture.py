"""Decode captures: a raw serial byte capture, or a python-can log
(``.log``, ``.asc``, ``.blf``, ``.trc``, ``.csv``, ``.mf4``), into readable
messages, with counters of bad frames."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from .framing import FLAG_SIGNED, FrameDecoder

CAN_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".csv", ".mf4", ".db")


@dataclass
class Decoded:
    t: float | None
    src: int
    seq: int
    signed: bool
    msg: object


@dataclass
class CaptureResult:
    kind: str
    items: list = field(default_factory=list)
    counters: dict = field(default_factory=dict)


def format_value(f, raw) -> str:
    if isinstance(raw, float):
        s = f"{raw:.9g}"
    else:
        s = str(raw)
    if f.scale != 1.0:
        s += f" ({raw * f.scale:.6g} {f.unit})".replace(" )", ")")
    elif f.unit and f.unit != "us":
        s += f" {f.unit}"
    return s


def format_message(msg, src: int | None = None, seq: int | None = None, t: float | None = None,
                   signed: bool = False) -> str:
    """One readable line: time, sender, sequence, name and every field."""
    head = []
    if t is not None:
        head.append(f"{t:12.6f}")
    if src is not None:
        head.append(f"src={src:<3d}")
    if seq is not None:
        head.append(f"seq={seq:<3d}")
    fields = " ".join(f"{f.name}={format_value(f, v)}" for f, v in zip(msg.DEF.fields, msg))
    return " ".join(head + [msg.NAME + (" [signed]" if signed else ""), fields])


def detect_kind(path: Path) -> str:
    return "can" if path.suffix.lower() in CAN_SUFFIXES else "serial"


def decode_serial_bytes(data: bytes) -> CaptureResult:
    res = CaptureResult("serial")

    def on_frame(hdr, msg):
        res.items.append(Decoded(None, hdr.src, hdr.seq, bool(hdr.flags & FLAG_SIGNED), msg))

    d = FrameDecoder(on_frame=on_frame)
    d.feed(data)
    if d._buf:                                # a last frame without its delimiter
        d.feed(b"\x00")
    res.counters = d.counters()
    return res


def decode_can_frames(frames, timeout_s: float | None = 0.5) -> CaptureResult:
    from .can import CanReassembler

    res = CaptureResult("can")
    r = CanReassembler(timeout_s=timeout_s)
    n = 0
    for f in frames:
        n += 1
        for hdr, msg in r.feed_with_headers(f):
            res.items.append(Decoded(f.timestamp, hdr.src, hdr.seq, bool(hdr.flags & FLAG_SIGNED), msg))
    res.counters = r.counters()
    res.counters["incomplete_at_end"] = r.open_reassemblies()
    res.counters["bad_by_message"] = dict(r.bad_by_message)
    return res


def canutils_frames(path, bad_lines: list):
    """The frames of a candump ``.log``, read one line at a time by python-can: a line it
    cannot read is skipped and its number appended to ``bad_lines``."""
    import io

    import can

    with open(path, encoding="utf-8", errors="replace") as fh:
        for n, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                frames = list(can.CanutilsLogReader(io.StringIO(line)))
            except Exception:        # noqa: BLE001 - python-can raises ValueError, IndexError, ...
                bad_lines.append(n)
                continue
            yield from frames


def decode_file(path, kind: str = "auto") -> CaptureResult:
    """Decode a capture. A candump ``.log`` line that does not parse is skipped and
    counted (``malformed_lines``, with their numbers in ``malformed_line_numbers``)."""
    p = Path(path)
    if kind == "auto":
        kind = detect_kind(p)
    if kind == "serial":
        return decode_serial_bytes(p.read_bytes())
    if p.suffix.lower() == ".log":
        bad: list[int] = []
        res = decode_can_frames(canutils_frames(p, bad))
        res.counters.update(malformed_lines=len(bad), malformed_line_numbers=bad)
        return res
    import can

    with can.LogReader(str(p)) as reader:
        return decode_can_frames(reader)
