"""The C core is written as firmware: only <math.h>, <string.h>, <stdint.h> (and its own header)
included; no global mutable state (no data, no bss in its objects); and `coiltrack core-size`
says how to get the Cortex-M7 toolchain when it is absent (exit 2). No test needs that toolchain."""
import re
import shutil
import subprocess

import pytest

from coiltrack.tools.commands import core_size as cmd_core_size
from coiltrack.tools.cli import main

CORE = cmd_core_size.core_dir()
ALLOWED = {"math.h", "string.h", "stdint.h", "coiltrack_core.h"}


def test_core_sources_include_only_the_allowed_headers():
    """Every #include of src/*.c and include/*.h is one of the three C headers, the core's own or a part's ct_*.h
    (the CPython glue _coremodule.c is outside the core and may include Python.h)."""
    files = sorted(CORE.glob("src/*.c")) + sorted(CORE.glob("include/*.h"))
    assert len(files) >= 3
    for f in files:
        for inc in re.findall(r'^\s*#\s*include\s*[<"]([^>"]+)[>"]', f.read_text(), re.M):
            own = re.fullmatch(r"ct_\w+\.h", inc) is not None and (CORE / "include" / inc).is_file()   # a part's header
            assert inc in ALLOWED or own, f"{f.name} includes {inc}"
        assert not re.search(r"\b(malloc|calloc|realloc|free)\s*\(", f.read_text()), f.name


@pytest.mark.skipif(shutil.which("gcc") is None or shutil.which("size") is None,
                    reason="needs a host gcc and binutils' size")
def test_core_objects_have_no_data_and_no_bss(tmp_path):
    """Compiled for this host, the core's objects hold no initialised or zeroed data: no global
    or static mutable state (a static counter or a scratch array at file scope would show)."""
    for src in sorted(CORE.glob("src/*.c")):
        obj = tmp_path / (src.stem + ".o")
        subprocess.run(["gcc", "-std=c99", "-O2", "-ffp-contract=off", "-Wall", "-Wextra", "-Werror",
                        "-pedantic", "-I", str(CORE / "include"), "-c", str(src), "-o", str(obj)], check=True)
        text, data, bss = map(int, subprocess.run(["size", str(obj)], capture_output=True, text=True,
                                                  check=True).stdout.splitlines()[1].split()[:3])
        assert text > 0 and data == 0 and bss == 0, (src.name, text, data, bss)


def test_core_size_without_the_toolchain_says_how_to_install_it(capsys):
    """An absent cross-compiler: one line naming it and the Debian packages, exit 2."""
    code = main(["core-size", "--cc", "no-such-arm-none-eabi-gcc"])
    err = capsys.readouterr().err
    assert code == 2
    assert "no-such-arm-none-eabi-gcc not found" in err and "gcc-arm-none-eabi" in err
    assert err.count("\n") == 1


@pytest.mark.skipif(shutil.which("arm-none-eabi-gcc") is None, reason="the Cortex-M7 toolchain is not installed")
def test_core_size_compiles_for_the_cortex_m7(tmp_path, capsys):
    """Where the toolchain is installed: every source compiles, text > 0, data = bss = 0."""
    import json

    out = tmp_path / "sizes.json"
    assert main(["core-size", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["total"]["text"] > 0 and rep["total"]["data"] == 0 and rep["total"]["bss"] == 0
    assert set(rep["files"]) == {p.name for p in CORE.glob("src/*.c")}
