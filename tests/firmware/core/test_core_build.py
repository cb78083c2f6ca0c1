"""The installed compiled core is built from the sources beside it.

The extension is optional (``setup.py``): a compile error does not stop ``pip install``, it
leaves the Python core, or an extension an earlier build left in place, which would then run
kernels older than their Python reference. The build compiles in a fingerprint of its sources
(``firmware_py/core/sources.py``); these tests compare it with the files on disk, and where CI
says a compiler is there (``COILTRACK_REQUIRE_CORE=1``, set by ``.ci/run``) a missing extension
fails instead of skipping.
"""
import os
import shutil

import pytest

from coiltrack.firmware import core
from coiltrack.firmware.core import sources


def _ext():
    if core.available():
        from coiltrack.firmware import _core
        return _core
    if os.environ.get("COILTRACK_REQUIRE_CORE") == "1":
        pytest.fail("the compiled core is not built although COILTRACK_REQUIRE_CORE=1 (a C "
                    "compiler is present): the extension failed to compile; run "
                    "`pip install -v -e .` to see the compiler's error")
    pytest.skip("the compiled core is not built in this install")


def test_extension_is_built_from_the_sources_beside_it():
    # fails on a stale build: a C edit whose compile failed leaves the older .so in place
    ext = _ext()
    assert ext.SOURCE_HASH == sources.fingerprint(), (
        "the compiled core was built from other sources than the ones installed beside it "
        f"({ext.SOURCE_HASH} != {sources.fingerprint()}): a later build failed; rebuild with "
        "`pip install -v -e .` and read the compiler's error")


def test_every_kernel_and_glue_file_is_a_source():
    # a file left out of the list would be neither built nor fingerprinted
    names = {f.relative_to(sources.HERE).as_posix() for f in sources.files()}
    on_disk = {f.relative_to(sources.HERE).as_posix()
               for pat in ("*.c", "*.h", "src/*.c", "include/*.h") for f in sources.HERE.glob(pat)}
    assert names == on_disk
    assert "_coremodule.c" in names and "include/coiltrack_core.h" in names


@pytest.fixture
def tree(tmp_path):
    root = tmp_path / "core"
    shutil.copytree(sources.HERE, root, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    return root


def test_fingerprint_follows_every_edit(tree):
    # a fingerprint of names only, or of one file, would miss these
    base = sources.fingerprint(tree)
    assert base == sources.fingerprint(sources.HERE)
    kernel = sorted(tree.glob("src/*.c"))[-1]
    kernel.write_bytes(kernel.read_bytes() + b" ")
    edited = sources.fingerprint(tree)
    assert edited != base
    header = tree / "py_glue.h"
    header.write_bytes(header.read_bytes() + b"\n")
    assert sources.fingerprint(tree) not in (base, edited)


def test_fingerprint_follows_a_rename_and_a_new_file(tree):
    base = sources.fingerprint(tree)
    kernel = sorted(tree.glob("src/*.c"))[0]
    kernel.rename(kernel.with_name("zz_" + kernel.name))
    renamed = sources.fingerprint(tree)
    assert renamed != base
    (tree / "src" / "extra.c").write_text("/* empty */\n")
    assert sources.fingerprint(tree) not in (base, renamed)
