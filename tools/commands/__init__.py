"""The commands of ``coiltrack``: one module per command, listed in :data:`COMMANDS`.

A command module gives ``HELP``, ``add_arguments(parser)`` and ``run(args)``, and may give
``NAME`` (the command's name when it is not the module's), ``EXIT`` (its own exit statuses, for
the ``--help`` epilog and the command reference) and ``epilog()`` (more text after the options).
A new command is a new module added to :data:`COMMANDS`.
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: the modules of this package that are commands, in the order ``coiltrack --help`` lists them
COMMANDS = (
    "bench",
    "busload",
    "calibrate",
    "check",
    "conform",
    "core_size",
    "dbc",
    "decode",
    "emulator",
    "firmware",
    "golden",
    "perf",
    "plot",
    "results",
    "schema",
    "smooth",
    "soak",
    "sweep",
)


def load(module: str) -> ModuleType:
    """The command module ``module`` of :data:`COMMANDS` (imported on first use: a command's
    dependencies load only when the parser is built or the command runs)."""
    if module not in COMMANDS:
        raise KeyError(f"'{module}' is not a command module; known: {', '.join(COMMANDS)}")
    return importlib.import_module(f"{__name__}.{module}")


def name_of(module: ModuleType) -> str:
    """The command's name: its ``NAME``, else its module's last part."""
    return getattr(module, "NAME", module.__name__.rpartition(".")[2])
