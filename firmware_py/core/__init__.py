"""Which numeric core the firmware runs: the compiled C99 kernels or their Python reference.

The C sources beside this module (``src/*.c``, ``include/coiltrack_core.h`` and the CPython glue
``_coremodule.c``) are built by ``pip install .`` into the optional extension
``coiltrack.firmware._core`` (``setup.py``: ``-O2 -ffp-contract=off -std=c99``). The Python
modules are the reference and the specification: each C kernel follows one Python function with
the same name and the same operations in the same order (see ``include/coiltrack_core.h``).

The choice is made once, at composition: :class:`coiltrack.firmware.loop.Firmware` calls
:func:`select` with the configuration's ``[core] impl`` before it builds its stages, and each
component that does numeric work (``model.signal.SignalModel``) binds the chosen kernel when it
is constructed (:func:`extension`); no tick tests the choice. ``"compiled"`` (the default) falls
back to ``"python"`` where the extension was not built (an install without a C compiler), with
one line on stderr saying so.
"""
from __future__ import annotations

import sys

__all__ = ["IMPLS", "available", "resolve", "select", "current", "extension"]

#: the values of ``[core] impl``
IMPLS = ("compiled", "python")

try:
    from coiltrack.firmware import _core as _ext
except ImportError:         # built without a compiler: the Python core only
    _ext = None

_state = {"selected": "compiled" if _ext is not None else "python", "said": False}


def available() -> bool:
    """Whether the compiled extension is installed."""
    return _ext is not None


def resolve(impl: str) -> str:
    """The core that runs for ``impl`` here: ``"compiled"`` only where the extension is built
    (otherwise ``"python"``, said once per process on stderr)."""
    if impl not in IMPLS:
        raise ValueError(f"core impl must be one of {IMPLS}, got {impl!r}")
    if impl == "compiled" and _ext is None:
        if not _state["said"]:
            _state["said"] = True
            print("coiltrack: the compiled core is not built in this install (no C compiler at "
                  "`pip install`); running the Python core", file=sys.stderr)
        return "python"
    return impl


def select(impl: str) -> str:
    """Choose the core the components constructed from now on bind (composition time);
    returns the core that runs (:func:`resolve`)."""
    _state["selected"] = resolve(impl)
    return _state["selected"]


def current() -> str:
    """The core the components constructed now bind: ``"compiled"`` or ``"python"``."""
    return _state["selected"]


def extension():
    """The compiled extension module when the selected core is the compiled one, else None."""
    return _ext if _state["selected"] == "compiled" else None
