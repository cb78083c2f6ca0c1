"""Build of the optional compiled core (``coiltrack.firmware._core``); everything else is in
pyproject.toml.  A machine without a C compiler installs the pure-Python package: the
extension is optional and the firmware then runs its Python core (``[core] impl``).

The sources are every kernel file (``src/*.c``) and every area's CPython glue (``py_*.c``)
beside the module's own ``_coremodule.c``, which registers them."""
from glob import glob

from setuptools import Extension, setup

CORE = "firmware_py/core"

setup(
    ext_modules=[
        Extension(
            "coiltrack.firmware._core",
            sources=[f"{CORE}/_coremodule.c", *sorted(glob(f"{CORE}/src/*.c")),
                     *sorted(glob(f"{CORE}/py_*.c"))],
            include_dirs=[f"{CORE}/include"],
            depends=sorted(glob(f"{CORE}/include/*.h")) + sorted(glob(f"{CORE}/*.h")),   # py_glue.h
            # no fused multiply-adds: the results must not depend on the compiler's choice
            # (it fuses by default on aarch64 and with -march=native); C99 as on the board
            extra_compile_args=["-O2", "-ffp-contract=off", "-std=c99"],
            optional=True,
        )
    ],
)
