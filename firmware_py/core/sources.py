"""The compiled core's source files and their fingerprint.

``setup.py`` builds the extension from :func:`files` and compiles :func:`fingerprint` into it
(``_core.SOURCE_HASH``); the tests compare the two, so an extension that an earlier build left
in place while a later edit failed to compile (the build is optional and does not stop the
install) is caught instead of silently run. No import from the package: ``setup.py`` loads this
file by path before the package is installed.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

__all__ = ["files", "fingerprint"]

#: this folder: ``_coremodule.c``, the glue ``py_*.c`` / ``*.h``, ``src/*.c``, ``include/*.h``
HERE = Path(__file__).resolve().parent


def files(root: Path = HERE) -> list[Path]:
    """Every file the extension is built from, in a fixed order: the module, the kernels, the
    glue, then every header."""
    return [root / "_coremodule.c", *sorted(root.glob("src/*.c")), *sorted(root.glob("py_*.c")),
            *sorted(root.glob("include/*.h")), *sorted(root.glob("*.h"))]


def fingerprint(root: Path = HERE) -> str:
    """SHA-256 (first 16 hex digits) over each source file's path relative to ``root`` and its
    bytes, in :func:`files` order: it changes when a file is edited, added, removed or renamed."""
    h = hashlib.sha256()
    for f in files(root):
        h.update(f.relative_to(root).as_posix().encode() + b"\0")
        h.update(f.read_bytes() + b"\0")
    return h.hexdigest()[:16]
