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
    with open(path) as fh:
        header = json.loads(fh.readline())
        if header.get("format") != FORMAT:
            raise ValueError(f"{path}: not a {FORMAT} log")
        reads = []
        for line in fh:
            if line.strip():
                o = json.loads(line)
                reads.append((int(o["t"]), base64.b64decode(o["rx"])))
    return header, reads


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
