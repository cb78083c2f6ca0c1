"""``python -m coiltrack.tools.docsgen [DIR]``: write the generated reference pages into DIR
(default ``docs/reference``) and bring the generated message table of the protocol
specification (``--protocol``, default ``docs/protocol.md``; the block of
:mod:`coiltrack.protocol.docgen`) up to date; ``--check``: write nothing, exit 1 if a page or
the table differs from the code's. ``--example PATH``: write the example configuration file
(``examples/firmware.toml``: every key with its default and meaning) instead."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .reference import PAGES, example_toml


def protocol_text(text: str) -> str:
    """``text`` with its generated message table replaced by the schema's current one."""
    from coiltrack.protocol.docgen import BEGIN, END, extract_generated, markdown_table

    i, j = text.find(BEGIN), text.find(END)
    if i < 0 or j < 0:
        raise ValueError(f"no generated block ({BEGIN} ... {END})")
    new = text[:i] + markdown_table().rstrip("\n") + text[j + len(END):]
    assert extract_generated(new) == markdown_table()
    return new


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m coiltrack.tools.docsgen",
                                description="write the reference pages generated from the code")
    p.add_argument("out", nargs="?", default="docs/reference", help="directory (default docs/reference)")
    p.add_argument("--protocol", default="docs/protocol.md", metavar="PATH",
                   help="the protocol specification whose generated message table is brought up to date "
                        "(default docs/protocol.md; '' for none)")
    p.add_argument("--check", action="store_true", help="only compare: exit 1 when a page is out of date")
    p.add_argument("--example", metavar="PATH",
                   help="write the example configuration (every key, its default and meaning) to PATH "
                        "(examples/firmware.toml) and nothing else; with --check only compare")
    args = p.parse_args(argv)
    if args.example:
        path, text = Path(args.example), example_toml()
        if args.check:
            if not path.exists() or path.read_text() != text:
                print(f"out of date: {path}", file=sys.stderr)
                return 1
            return 0
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
            print(f"wrote {path}")
        return 0
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
    if args.protocol:
        spec = Path(args.protocol)
        text = spec.read_text()
        new = protocol_text(text)
        if new != text:
            if args.check:
                stale.append(str(spec))
            else:
                spec.write_text(new)
                print(f"wrote the message table of {spec}")
    if stale:
        print("out of date: " + ", ".join(stale), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
