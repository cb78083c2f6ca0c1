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


def read_log(path) -> tuple[dict, list[tuple[int, bytes]]]:
    """The header and the reads of a log (ValueError if line 1 is not a header). Cut
    short, the reads before the first bad line, and the header with ``duration_s``
    the time of the last read kept and ``truncated`` (line, reads kept, recorded
    duration)."""
    with open(path) as fh:
        try:
            header = json.loads(fh.readline())
        except ValueError:
            header = None
        if not isinstance(header, dict) or header.get("format") != FORMAT:
            raise ValueError(f"{path}: line 1 is not a {FORMAT} header")
        reads = []
        for n, line in enumerate(fh, start=2):
            if not line.strip():
                continue
            try:
                o = json.loads(line)
                reads.append((int(o["t"]), base64.b64decode(o["rx"], validate=True)))
            except (ValueError, KeyError, TypeError):
                return _cut(header, reads, n), reads
    return header, reads


def _cut(header: dict, reads, line: int) -> dict:
    return dict(header, duration_s=reads[-1][0] * 1e-6 if reads else 0.0,
                truncated={"line": line, "reads": len(reads), "recorded_duration_s": header.get("duration_s")})


def load(command: str, path):
    """:func:`read_log` for ``coiltrack COMMAND``: None after a one-line error, or the log,
    with a line on standard error where it was cut short."""
    import sys

    try:
        header, reads = read_log(path)
    except (OSError, ValueError) as exc:
        print(f"coiltrack {command}: {exc}", file=sys.stderr)
        return None
    note = truncation_note(path, header)
    if note:
        print(f"coiltrack {command}: {note}", file=sys.stderr)
    return header, reads


def truncation_note(path, header: dict) -> str | None:
    """One line saying where a cut log stopped, or None for a whole log."""
    cut = header.get("truncated")
    if not cut:
        return None
    return (f"{path}: cut short at line {cut['line']} (of a {cut['recorded_duration_s']} s run): "
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
