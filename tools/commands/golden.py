"""Golden byte vectors of every message (serial frames and CAN frames,
``protocol/golden/``), generated from the fixed example values in
``protocol/examples.py``. Without ``--write`` the files are regenerated in
memory and compared byte for byte."""
from __future__ import annotations

import sys

from .. import args as A

HELP = "check (default) or --write the golden byte vectors under protocol/golden/"


EXIT = {1: "the golden files on disk differ from the regenerated ones"}


def add_arguments(p) -> None:
    p.add_argument("--write", action="store_true", help="write the files (only those that changed)")
    p.add_argument("--dir", help="golden directory (default: the package's protocol/golden)")


def run(args) -> int:
    from coiltrack.protocol.golden import GOLDEN_DIR, check_golden, golden_files, write_golden

    d = args.dir or GOLDEN_DIR
    if args.write:
        written = write_golden(d)
        print(f"{len(golden_files())} golden files in {d}; {len(written)} written")
        for p in written:
            print(f"  {p}")
        return 0
    problems = check_golden(d)
    if problems:
        for p in problems:
            print(p, file=sys.stderr)
        print(f"golden vectors in {d} are not current ({len(problems)} problems); "
              f"review and run `coiltrack golden --write`", file=sys.stderr)
        return 1
    print(f"{len(golden_files())} golden files in {d} match")
    return 0
