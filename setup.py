"""Build of the optional compiled core (``coiltrack.firmware._core``); everything else is in
pyproject.toml.  A machine without a C compiler installs the pure-Python package: the
extension is optional and the firmware then runs its Python core (``[core] impl``).

The sources are every kernel file (``src/*.c``) and every area's CPython glue (``py_*.c``)
beside the module's own ``_coremodule.c``, which registers them. The build compiles in a
fingerprint of those sources (``_core.SOURCE_HASH``) that the tests check against the tree."""
import importlib.util

from setuptools import Extension, setup

CORE = "firmware_py/core"


def _sources():
    """``firmware_py/core/sources.py``, loaded by path (the package is not installed yet): the
    one list of the extension's files and their fingerprint (compiled in as
    ``_core.SOURCE_HASH``)."""
    spec = importlib.util.spec_from_file_location("_ct_sources", f"{CORE}/sources.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


SOURCES = _sources()
FILES = [f"{CORE}/{f.relative_to(SOURCES.HERE).as_posix()}" for f in SOURCES.files()]

setup(
    ext_modules=[
        Extension(
            "coiltrack.firmware._core",
            sources=[f for f in FILES if f.endswith(".c")],
            include_dirs=[f"{CORE}/include"],
            depends=[f for f in FILES if f.endswith(".h")],   # include/*.h, py_glue.h, ...
            # no fused multiply-adds: the results must not depend on the compiler's choice
            # (it fuses by default on aarch64 and with -march=native); C99 as on the board
            extra_compile_args=["-O2", "-ffp-contract=off", "-std=c99"],
            define_macros=[("CT_SOURCE_HASH", f'"{SOURCES.fingerprint()}"')],
            optional=True,
        )
    ],
)
