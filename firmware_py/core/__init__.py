"""Which numeric core the firmware runs: the compiled C99 kernels or their Python reference.

The C sources beside this module (``src/*.c``, ``include/coiltrack_core.h`` and the CPython glue
``_coremodule.c``) are built by ``pip install .`` into the optional extension
``coiltrack.firmware._core`` (``setup.py``: ``-O2 -ffp-contract=off -std=c99``). The Python
modules are the reference and the specification: each C kernel follows one Python function with
the same name and the same operations in the same order (see ``include/coiltrack_core.h``).

The choice is made once, at composition, and passed down; nothing here is mutable.
:class:`coiltrack.firmware.loop.Firmware` calls :func:`load` with the configuration's
``[core] impl`` and hands the :class:`Core` it gets to the stages it builds; each component that
binds kernels (``model.signal.SignalModel``, ``estimate.ekf``, ``pose.solver``, ``receive``,
``transmit``, ...) takes it as its ``core`` constructor argument and binds the chosen kernels
there, so no tick tests the choice. A component built without one (a tool, a test) runs
:data:`DEFAULT`: the compiled core where it is built, else the Python one. ``"compiled"`` falls
back to ``"python"`` where the extension was not built (an install without a C compiler), with
one line on stderr saying so (:func:`load`).
"""
from __future__ import annotations

import functools
import sys
from dataclasses import dataclass
from types import ModuleType

__all__ = ["IMPLS", "Core", "PYTHON", "DEFAULT", "available", "resolve", "load"]

#: the values of ``[core] impl``
IMPLS = ("compiled", "python")

try:
    from coiltrack.firmware import _core as _ext
except ImportError:         # built without a compiler: the Python core only
    _ext = None


@dataclass(frozen=True)
class Core:
    """One numeric core: its ``name`` (``"compiled"`` or ``"python"``) and, for the compiled
    one, the extension module ``ext`` whose kernels the components bind (None for Python)."""
    name: str
    ext: ModuleType | None = None

    def __post_init__(self):
        if self.name not in IMPLS:
            raise ValueError(f"core impl must be one of {IMPLS}, got {self.name!r}")
        if (self.name == "compiled") != (self.ext is not None):
            raise ValueError("a compiled core needs its extension module, the Python core none")


#: the Python reference
PYTHON = Core("python")
#: what a component built without a ``core`` runs: compiled where built, else Python
DEFAULT = Core("compiled", _ext) if _ext is not None else PYTHON


def available() -> bool:
    """Whether the compiled extension is installed."""
    return _ext is not None


def resolve(impl: str, ext: ModuleType | None = _ext) -> str:
    """The core that runs for ``impl`` where the extension is ``ext``: ``"compiled"`` only where
    it is built, otherwise ``"python"``."""
    if impl not in IMPLS:
        raise ValueError(f"core impl must be one of {IMPLS}, got {impl!r}")
    return "python" if ext is None else impl


@functools.cache
def _say_python_fallback() -> None:
    """The one line saying the compiled core is missing (once per process: cached)."""
    print("coiltrack: the compiled core is not built in this install (no C compiler at "
          "`pip install`); running the Python core", file=sys.stderr)


def load(impl: str, ext: ModuleType | None = _ext) -> Core:
    """The :class:`Core` for ``[core] impl`` (chosen once, at composition): ``"compiled"`` where
    the extension ``ext`` is built, else the Python core with one line on stderr saying so."""
    name = resolve(impl, ext)
    if name != impl:
        _say_python_fallback()
    return Core(name, ext) if name == "compiled" else PYTHON
