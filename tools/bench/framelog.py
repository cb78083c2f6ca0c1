"""Frame logs: what a firmware received, tick by tick, to replay it later.

A bench run (``coiltrack bench --log PATH``) records every chunk of bytes the
firmware's port returned, with the tick time it was read at. Replaying the
log into a fresh firmware on the same virtual clock reproduces the run
exactly (the firmware is deterministic and its inputs are all in the log), so
``coiltrack perf`` can time the tick on real inputs and ``coiltrack smooth``
can re-run the fusion filter with a recorder attached.

Format (JSON lines, ``coiltrack-frames/1``): a header object with
``format``, ``scenario``, ``seed``, ``duration_s``, ``tick_us`` and the
firmware ``config`` (``FirmwareConfig`` as a dict), then one object per read,
``{"t": tick_us, "rx": base64 bytes}``.

A log cut short (a run killed while writing, a truncated copy) is read up to
the first line that does not parse: the reads before it are replayed, and
the header says where the log stopped (``truncated``).
"""
from __future__ import annotations

import base64
import json

from coiltrack.firmware.config import FirmwareConfig, config_from_dict, config_to_dict  # noqa: F401
from coiltrack.firmware.port import Port
from ..inputs.infile import InputFileError, loads_json, read_bytes, text_lines, warn

FORMAT = "coiltrack-frames/1"


class RecordingPort(Port):
    """Wraps a port; every non-empty read is kept with the current tick time
    (set ``now_us`` before each tick)."""

    def __init__(self, port: Port):
        self.port = port
        self.now_us = 0
        self.reads: list[tuple[int, bytes]] = []

    def read(self) -> bytes:
        data = self.port.read()
        if data:
            self.reads.append((self.now_us, bytes(data)))
        return data

    def write(self, data: bytes) -> None:
        self.port.write(data)

    def close(self) -> None:
        self.port.close()


class ReplayPort(Port):
    """Returns the logged bytes of the current tick (set ``now_us``); writes
    are counted and dropped."""

    def __init__(self, reads):
        self.reads = reads
        self.i = 0
        self.now_us = 0
        self.bytes_tx = 0

    def read(self) -> bytes:
        if self.i < len(self.reads) and self.reads[self.i][0] == self.now_us:
            data = self.reads[self.i][1]
            self.i += 1
            return data
        return b""

    def write(self, data: bytes) -> None:
        self.bytes_tx += len(data)


def write_log(path, header: dict, reads) -> None:
    with open(path, "w") as fh:
        fh.write(json.dumps(dict(header, format=FORMAT)) + "\n")
        for t, data in reads:
            fh.write(json.dumps({"t": t, "rx": base64.b64encode(data).decode()}) + "\n")


def _check_header(header, path) -> None:
    """The header's values, of the right types (an InputFileError naming the key)."""
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise InputFileError(path, f"not a {FORMAT} header", line=1)
    tick = header.get("tick_us")
    if isinstance(tick, bool) or not isinstance(tick, int) or not 1 <= tick <= 10_000_000:
        raise InputFileError(path, f"must be a whole number of microseconds in [1, 10000000], got {tick!r}",
                             key="tick_us")
    dur = header.get("duration_s")
    if isinstance(dur, bool) or not isinstance(dur, (int, float)) or not 0 <= dur <= 7 * 86400:
        raise InputFileError(path, f"must be a number of seconds in [0, 604800], got {dur!r}", key="duration_s")
    if not isinstance(header.get("config"), dict):
        raise InputFileError(path, f"must be an object of configuration sections, got {header.get('config')!r}",
                             key="config")
    from coiltrack.firmware.config import ConfigError

    try:
        log_config(header)
    except ConfigError as exc:
        raise InputFileError(path, exc.message, key=f"config.{exc.key}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise InputFileError(path, f"not a firmware configuration ({type(exc).__name__}: {exc})",
                             key="config") from None


def _read(o, prev_t: int, tick: int) -> tuple[int, bytes] | str:
    """One read of the log, or what is wrong with it (a str)."""
    import binascii

    if not isinstance(o, dict) or set(o) != {"t", "rx"}:
        return 'not a read {"t": ..., "rx": ...}'
    t, rx = o["t"], o["rx"]
    if isinstance(t, bool) or not isinstance(t, int) or t < prev_t or t % tick:
        return f"t {t!r} is not a tick time (a multiple of {tick} us, not before the read above)"
    if not isinstance(rx, str) or not rx:
        return f"rx {rx!r} is not base64 bytes"
    try:
        return t, base64.b64decode(rx, validate=True)
    except (binascii.Error, ValueError):
        return "rx is not base64"


def read_log(path) -> tuple[dict, list[tuple[int, bytes]]]:
    """The header and the reads of a log, read strictly (``tools.inputs.infile``). Line 1 must be a
    header of the right types (else an :class:`~coiltrack.tools.inputs.infile.InputFileError`,
    a ValueError, naming the file and the line or key). A log damaged further on (cut short,
    a line that is not UTF-8 or not JSON, a read of the wrong shape or out of order) is
    used up to the damage: the reads before it, and the header with ``duration_s`` the
    time of the last read kept and ``truncated`` (line, reads kept, recorded duration,
    what is wrong there)."""
    data = read_bytes(path)
    if not data.strip():
        raise InputFileError(path, "is empty: no frame log in it")
    lines, damage = text_lines(data, path)
    if not lines:
        raise InputFileError(path, f"not a {FORMAT} header ({damage[1]})", line=1)
    try:
        header = loads_json(lines[0][1], path, line=1)
    except InputFileError as exc:
        raise InputFileError(path, f"not a {FORMAT} header ({exc.message})", line=1) from None
    _check_header(header, path)
    if header["duration_s"] * 1e6 > 2**62:
        raise InputFileError(path, "out of range", key="duration_s")
    reads: list[tuple[int, bytes]] = []
    tick = header["tick_us"]
    for n, line in lines[1:]:
        if not line.strip():
            continue
        try:
            o = loads_json(line, path, line=n)
        except InputFileError as exc:
            damage = (n, exc.message)
            break
        r = _read(o, reads[-1][0] if reads else 0, tick)
        if isinstance(r, str):
            damage = (n, r)
            break
        reads.append(r)
    if damage:
        return _cut(header, reads, *damage), reads
    return header, reads


def _cut(header: dict, reads, line: int, why: str = "") -> dict:
    return dict(header, duration_s=reads[-1][0] * 1e-6 if reads else 0.0,
                truncated={"line": line, "reads": len(reads), "recorded_duration_s": header.get("duration_s"),
                           "why": why})


def load(command: str, path):
    """:func:`read_log` for ``coiltrack COMMAND``: None after a one-line error, or the log,
    with a warning line on standard error where it was cut short."""
    import sys

    try:
        header, reads = read_log(path)
    except (OSError, ValueError) as exc:
        print(f"coiltrack {command}: {exc}", file=sys.stderr)
        return None
    if header.get("truncated"):
        warn(command, path, truncation_note(None, header))
    return header, reads


def truncation_note(path, header: dict) -> str | None:
    """One line saying where a cut log stopped (``path`` first when given), or None for a whole log."""
    cut = header.get("truncated")
    if not cut:
        return None
    why = f" ({cut['why']})" if cut.get("why") and not cut["why"].startswith("cut short") else ""
    return ((f"{path}: " if path is not None else "") +
            f"cut short at line {cut['line']}{why} (of a {cut['recorded_duration_s']} s run): "
            f"using the {cut['reads']} reads before it, {header['duration_s']:.3f} s")


def log_config(header: dict) -> FirmwareConfig:
    d = dict(header["config"])
    return config_from_dict(d)


def replay(fw_factory, header: dict, reads, on_tick=None):
    """Run a fresh firmware (``fw_factory(cfg, port)``) over the log on its
    virtual clock; ``on_tick(fw, t)`` after every tick. Returns the firmware."""
    cfg = log_config(header)
    port = ReplayPort(reads)
    fw = fw_factory(cfg, port)
    tick = int(header["tick_us"])
    end = int(header["duration_s"] * 1e6)
    t = 0
    while t <= end:
        port.now_us = t
        fw.tick(t)
        if on_tick is not None:
            on_tick(fw, t)
        t += tick
    return fw
