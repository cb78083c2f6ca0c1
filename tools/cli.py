"""``coiltrack``: one module per subcommand (``tools/cmd_*.py``)."""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from pathlib import Path


def subcommands() -> list[str]:
    """Every ``tools/cmd_NAME.py`` module is the subcommand ``NAME``."""
    here = str(Path(__file__).parent)
    return sorted(m.name[4:] for m in pkgutil.iter_modules([here]) if m.name.startswith("cmd_"))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="coiltrack", description="Magnetic 6-DOF tracker: firmware, protocol and emulated bench.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in subcommands():
        mod = importlib.import_module(f"coiltrack.tools.cmd_{name}")
        name = getattr(mod, "NAME", name)
        p = sub.add_parser(name, help=mod.HELP, description=mod.__doc__)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
