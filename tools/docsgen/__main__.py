"""``python -m coiltrack.tools.docsgen [DIR]``: write the generated reference pages into DIR
(default ``docs/reference``); ``--check``: exit 1 if a page on disk differs from the code's."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .reference import PAGES


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m coiltrack.tools.docsgen",
                                description="write the reference pages generated from the code")
    p.add_argument("out", nargs="?", default="docs/reference", help="directory (default docs/reference)")
    p.add_argument("--check", action="store_true", help="only compare: exit 1 when a page is out of date")
    args = p.parse_args(argv)
    out = Path(args.out)
    stale = []
    if not args.check:
        out.mkdir(parents=True, exist_ok=True)
    for name, make in PAGES.items():
        text = make()
        path = out / name
        if args.check:
            if not path.exists() or path.read_text() != text:
                stale.append(str(path))
            continue
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
            print(f"wrote {path}")
    if stale:
        print("out of date: " + ", ".join(stale), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
