"""Argument types shared by every command.

Each type checks one argument when the command line is parsed, before any
work: a bad value is refused by argparse with one line naming the argument
and the accepted range, and exit status 2. Output paths are checked
writable here too, so a run is never lost to a bad ``--json`` path at its
end.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

#: the longest run a simulated-clock bench accepts: its buffers are sized from the duration
MAX_BENCH_S = 3600.0
#: the longest wall-clock run of the firmware or the emulator (a week)
MAX_WALL_S = 7 * 86400.0


def _interval(lo, hi, lo_open: bool) -> str:
    left = "(" if lo_open else "["
    fmt = lambda v: str(int(v)) if float(v).is_integer() else f"{v:g}"  # noqa: E731
    lo_s = "-inf" if lo is None else fmt(lo)
    hi_s = "inf" if hi is None else fmt(hi)
    return f"{left}{lo_s}, {hi_s}{']' if hi is not None else ')'}"


def real(lo: float | None = None, hi: float | None = None, lo_open: bool = False):
    """A finite number in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``); ``None``: unbounded."""
    span = _interval(lo, hi, lo_open)

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            v = math.nan
        below = lo is not None and (v <= lo if lo_open else v < lo)
        if not math.isfinite(v) or below or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"must be a finite number in {span}, got '{text}'")
        return v
    parse.__name__ = "number"
    return parse


def integer(lo: int | None = None, hi: int | None = None):
    """A whole number in ``[lo, hi]``; ``None``: unbounded."""
    span = _interval(lo, hi, False)

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer in {span}, got '{text}'") from None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"must be an integer in {span}, got '{text}'")
        return v
    parse.__name__ = "integer"
    return parse


#: simulated seconds of a bench run
bench_seconds = real(0.0, MAX_BENCH_S, lo_open=True)
#: wall-clock seconds of a firmware or emulator run
wall_seconds = real(0.0, MAX_WALL_S, lo_open=True)
#: a seed of numpy's SeedSequence
seed = integer(0, 2**32 - 1)
#: a node id on the bus
node_id = integer(0, 255)
#: a bit rate or a baud rate, bit/s
bitrate = integer(1, 100_000_000)
#: a CPU number
cpu = integer(0, 4095)


def output_path(text: str) -> str:
    """A file the command can write: tried now (appended to, or created and removed)."""
    p = Path(text)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"'{text}' is a directory, not a file")
    existed = p.exists()
    try:
        with open(p, "a" if existed else "x"):
            pass
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot write '{text}': {exc.strerror}") from None
    if not existed:
        os.unlink(p)
    return text


def input_file(text: str) -> str:
    """A file the command can read."""
    try:
        with open(text, "rb"):
            pass
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot read '{text}': {exc.strerror}") from None
    return text


#: the environment variable a signing key may come in (a child process gets it so, not on its command line)
KEY_ENV = "COILTRACK_SIGNING_KEY"


def signing_key(text: str) -> str:
    """A signing key: 64 hex digits, a passphrase (hashed with SHA-256), ``@PATH`` to read either from
    a file, or ``@env`` to take it from the environment variable :data:`KEY_ENV` (so the key does not
    show in the process list)."""
    if text == "@env":
        text = os.environ.get(KEY_ENV, "")
        if not text.strip():
            raise argparse.ArgumentTypeError(f"--key @env: the environment variable {KEY_ENV} is not set")
    elif text.startswith("@"):
        try:
            with open(text[1:], encoding="utf-8") as f:
                text = f.read().strip()
        except OSError as exc:
            raise argparse.ArgumentTypeError(f"cannot read the key file '{text[1:]}': {exc.strerror}") from None
    if not text.strip():
        raise argparse.ArgumentTypeError("the signing key is empty")
    return text.strip()


def serial_port(text: str) -> str:
    """A serial device, pseudo-terminal or pyserial URL that reaches another party
    (``loop://`` only echoes back what is written)."""
    if text.startswith("loop://"):
        raise argparse.ArgumentTypeError("'loop://' echoes this side's own frames back: give a device, "
                                         "a pty path or another pyserial URL")
    return text
