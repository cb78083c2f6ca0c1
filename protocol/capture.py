"""Decode captures: a raw serial byte capture, or a python-can log
(``.log``, ``.asc``, ``.blf``, ``.trc``, ``.csv``, ``.mf4``, ``.db``), into
readable messages, with counters of bad frames.

A damaged capture is used up to its damage: a serial capture cut inside a
frame (its last frame counted bad, ``cut_at_byte``); a text log (``.log``,
``.asc``, ``.trc``, ``.csv``) up to its first line that is not UTF-8 or its
last line cut short (without its newline); any log up to where python-can's
reader gives up (a binary ``.blf`` cut short). :attr:`CaptureResult.damage`
then says where it stops, and an empty capture, or one with nothing readable
before its damage, is refused (:class:`CaptureFileError`, a ValueError naming
the file)."""
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
    #: None for a whole capture; else where the capture stops being readable and why (one phrase)
    damage: str | None = None


class CaptureFileError(ValueError):
    """A capture with nothing readable in it; the message names the file (and where)."""


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
    cut = len(data) - len(d._buf) if d._buf else None
    if d._buf:                                # a last frame without its delimiter
        d.feed(b"\x00")
    res.counters = d.counters()
    if cut is not None:
        res.counters["cut_at_byte"] = cut
        res.damage = f"cut short at byte {cut} (a last frame without its 0x00 delimiter, counted bad)"
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


def _good_text(data: bytes) -> tuple[str, str | None]:
    """The text of a line-oriented log up to its damage, and the damage (None for a whole
    file): the first line that is not UTF-8, or a last line without its newline."""
    lines = data.split(b"\n")
    out = []
    for n, b in enumerate(lines, 1):
        if n == len(lines):
            return "".join(out), (f"line {n}: cut short (no newline at its end)" if b else None)
        try:
            out.append(b.decode("utf-8") + "\n")
        except UnicodeDecodeError as exc:
            return "".join(out), f"line {n}: byte {b[exc.start]:#04x} at column {exc.start + 1} is not UTF-8"
    return "".join(out), None


def canutils_frames(path, bad_lines: list, text: str | None = None):
    """The frames of a candump ``.log`` (its ``text`` when given), read one line at a time by
    python-can: a line it cannot read is skipped and its number appended to ``bad_lines``."""
    import io

    import can

    if text is None:
        with open(path, encoding="utf-8", errors="replace") as fh:
            text = fh.read()
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            frames = list(can.CanutilsLogReader(io.StringIO(line)))
        except Exception:        # noqa: BLE001 - python-can raises ValueError, IndexError, ...
            bad_lines.append(n)
            continue
        yield from frames


def _guarded(frames, damage: list):
    """``frames`` until the reader raises; then where (frames read) and why appended to ``damage``."""
    n = 0
    it = iter(frames)
    while True:
        try:
            f = next(it)
        except StopIteration:
            return
        except Exception as exc:     # noqa: BLE001 - a damaged log: struct.error, ValueError, zlib.error, ...
            damage.append(f"unreadable after {n} frames ({type(exc).__name__}: {exc})".replace("\n", " "))
            return
        n += 1
        yield f


_TEXT_LOGS = (".log", ".asc", ".trc", ".csv")


def decode_file(path, kind: str = "auto") -> CaptureResult:
    """Decode a capture (see the module docstring for a damaged one). A candump ``.log``
    line that does not parse is skipped and counted (``malformed_lines``, with their
    numbers in ``malformed_line_numbers``). Raises OSError (unreadable) or
    :class:`CaptureFileError` (empty, or nothing readable before the damage)."""
    p = Path(path)
    if kind == "auto":
        kind = detect_kind(p)
    data = p.read_bytes()
    if not data.strip(b" \t\r\n"):
        raise CaptureFileError(f"{path}: is empty: no capture in it")
    if kind == "serial":
        return decode_serial_bytes(data)
    suffix = p.suffix.lower()
    damage: list[str] = []
    if suffix in _TEXT_LOGS:
        import io

        if data.startswith(b"\xef\xbb\xbf"):
            data = data[3:]
        if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
            raise CaptureFileError(f"{path}: is UTF-16 text, not UTF-8: save it as UTF-8")
        text, cut = _good_text(data)
        if cut:
            damage.append(cut)
        if suffix == ".log":
            bad: list[int] = []
            res = decode_can_frames(canutils_frames(p, bad, text))
            res.counters.update(malformed_lines=len(bad), malformed_line_numbers=bad)
            frames_read = None
        else:
            import can

            try:
                reader = can.io.player.MESSAGE_READERS[suffix](io.StringIO(text))
            except Exception as exc:     # noqa: BLE001 - a damaged header
                raise CaptureFileError(f"{path}: not a readable {suffix} log ({type(exc).__name__}: {exc})") from None
            read = list(_guarded(reader, damage))
            res, frames_read = decode_can_frames(read), len(read)
    else:
        import can

        try:
            reader = can.LogReader(str(p))
        except Exception as exc:     # noqa: BLE001 - a damaged header: struct.error, ValueError, ...
            raise CaptureFileError(f"{path}: not a readable {suffix} log ({type(exc).__name__}: {exc})") from None
        with reader:
            read = list(_guarded(reader, damage))
        recorded = getattr(reader, "file_size", 0) or 0          # a BLF header records its size
        if recorded > len(data):
            damage.append(f"cut short: {len(data)} of the {recorded} bytes its header records "
                          f"({len(read)} of {getattr(reader, 'object_count', '?')} objects read)")
        res, frames_read = decode_can_frames(read), len(read)
    if damage:
        res.damage = "; ".join(damage)
        if frames_read == 0 or (frames_read is None and not res.items):
            raise CaptureFileError(f"{path}: {res.damage}; nothing readable before it")
    return res
