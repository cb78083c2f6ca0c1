"""``coiltrack``: one module per command, listed in ``tools/commands/__init__.py``
(:data:`coiltrack.tools.commands.COMMANDS`; what a command module gives is there).
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from importlib.metadata import PackageNotFoundError, requires
from importlib.metadata import version as dist_version

from . import commands
from .inputs.infile import InputFileError
from .stopping import EXIT_BROKEN_PIPE, Interrupted, on_signals

#: exit statuses every command shares
COMMON_EXIT = {
    0: "done",
    2: "bad argument, configuration value or input file, refused before any work (or a missing optional "
       "package: the message names the extra to install)",
    130: "stopped by SIGINT (Ctrl-C)",
    143: "stopped by SIGTERM",
    141: "standard output closed by its reader (e.g. piped into head)",
}


def subcommands() -> list[str]:
    """The command modules of the registry (:data:`coiltrack.tools.commands.COMMANDS`)."""
    return list(commands.COMMANDS)


def exit_codes(mod) -> dict[int, str]:
    """The exit statuses of a command: the common ones and its own."""
    return dict(sorted({**COMMON_EXIT, **getattr(mod, "EXIT", {})}.items()))


def _epilog(mod) -> str:
    parts = [mod.epilog()] if hasattr(mod, "epilog") else []
    parts.append("exit status:\n" + "\n".join(f"  {k:>3}  {v}" for k, v in exit_codes(mod).items()))
    return "\n\n".join(parts)


def version() -> str:
    """The installed distribution's version (``importlib.metadata``)."""
    try:
        return dist_version("coiltrack")
    except PackageNotFoundError:
        return "unknown (not installed: pip install -e .)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="coiltrack", description="Magnetic 6-DOF tracker: firmware, protocol and emulated bench.")
    parser.add_argument("--version", action="version", version=f"coiltrack {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in commands.COMMANDS:
        mod = commands.load(module)
        p = sub.add_parser(commands.name_of(mod), help=mod.HELP, description=mod.__doc__, epilog=_epilog(mod),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def extra_for(module: str) -> str | None:
    """The optional extra of coiltrack that installs ``module`` (from the installed metadata)."""
    want = module.split(".")[0].lower().replace("_", "-")
    try:
        reqs = requires("coiltrack") or []
    except PackageNotFoundError:
        return None
    for r in reqs:
        name = re.match(r"[A-Za-z0-9_.-]+", r).group(0).lower().replace("_", "-")
        extra = re.search(r"extra\s*==\s*['\"]([^'\"]+)['\"]", r)
        if name == want and extra:
            return extra.group(1)
    return None


def _missing(command: str, exc: ModuleNotFoundError) -> int:
    extra = extra_for(exc.name or "")
    if extra is None and (exc.name or "").startswith("coiltrack"):
        raise exc                   # one of ours: a bug, not an installation
    how = f"pip install 'coiltrack[{extra}]'" if extra else f"pip install {exc.name}"
    print(f"coiltrack {command}: needs the package '{exc.name}', which is not installed: {how}", file=sys.stderr)
    return 2


def _broken_pipe() -> int:
    # the reader went away: nothing more can be written, and Python must not try at exit
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    return EXIT_BROKEN_PIPE


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), "")
    with on_signals():
        try:
            args = build_parser().parse_args(argv)
            return int(args._run(args) or 0)
        except Interrupted as exc:
            print(f"coiltrack: stopped by {exc.reason}", file=sys.stderr)
            return exc.exit_code
        except InputFileError as exc:       # a damaged input file: one line naming it, no traceback
            print(f"coiltrack {command}: {exc}", file=sys.stderr)
            return 2
        except ModuleNotFoundError as exc:
            return _missing(command, exc)
        except BrokenPipeError:
            return _broken_pipe()


if __name__ == "__main__":
    sys.exit(main())
