"""Compile the firmware's C99 core (``firmware_py/core/src/*.c``) freestanding for a Cortex-M7
with the GNU Arm Embedded toolchain and report its text / data / bss sizes (bytes, from
``arm-none-eabi-size``), per source file and in total, and the symbols it needs from outside
(the C library's ``sqrt`` and the like).

Flags: ``-mcpu=cortex-m7 -mfpu=fpv5-d16 -mfloat-abi=hard -mthumb -ffreestanding -Os -std=c99
-ffp-contract=off -fno-math-errno -c`` (the same sources the host build compiles with ``-O2``;
no fused multiply-adds, so a board computes the host's results; no errno, so a square root is
the FPU's instruction). The toolchain is Debian's ``gcc-arm-none-eabi`` and
``binutils-arm-none-eabi``; without it the command says so and exits 2."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from .. import args as A

NAME = "core-size"
HELP = "compile the C core for a Cortex-M7 (freestanding) and report its text/data/bss sizes"
EXIT = {1: "the cross-compiler refused a source (its messages are printed)"}

FLAGS = ("-mcpu=cortex-m7", "-mfpu=fpv5-d16", "-mfloat-abi=hard", "-mthumb", "-ffreestanding", "-Os",
         "-std=c99", "-ffp-contract=off", "-fno-math-errno", "-Wall", "-Wextra", "-c")
INSTALL = ("install the GNU Arm Embedded toolchain: Debian/Ubuntu `apt-get install gcc-arm-none-eabi "
           "binutils-arm-none-eabi` (or Arm's own release, on the PATH)")


def add_arguments(p) -> None:
    p.add_argument("--cc", default="arm-none-eabi-gcc", help="the cross-compiler (default arm-none-eabi-gcc)")
    p.add_argument("--size", default="arm-none-eabi-size",
                   help="the size tool of the same toolchain (default arm-none-eabi-size)")
    p.add_argument("--json", type=A.output_path, metavar="PATH", help="write the sizes as JSON")


def core_dir() -> Path:
    """The core's sources: ``src/*.c`` and ``include/`` beside ``coiltrack.firmware.core``."""
    from coiltrack.firmware import core

    return Path(core.__file__).resolve().parent


def measure(cc: str, size: str) -> dict:
    """Compile every core source with :data:`FLAGS` and read the sizes; raises
    ``subprocess.CalledProcessError`` when a source does not compile."""
    d = core_dir()
    sources = sorted((d / "src").glob("*.c"))
    if not sources:
        raise FileNotFoundError(f"no C sources under {d / 'src'}")
    nm = str(Path(size).with_name(Path(size).name.replace("size", "nm")))
    with tempfile.TemporaryDirectory(prefix="coiltrack-core-") as tmp:
        objs = []
        for src in sources:
            obj = Path(tmp) / (src.stem + ".o")
            subprocess.run([cc, *FLAGS, "-I", str(d / "include"), str(src), "-o", str(obj)],
                           check=True, capture_output=True, text=True)
            objs.append(obj)
        out = subprocess.run([size, "-t", *map(str, objs)], check=True, capture_output=True, text=True).stdout
        undefined = set()
        if shutil.which(nm):
            for obj in objs:
                res = subprocess.run([nm, "-u", str(obj)], capture_output=True, text=True)
                undefined.update(line.split()[-1] for line in res.stdout.splitlines() if line.strip())
        defined = set()
        if shutil.which(nm):
            for obj in objs:
                res = subprocess.run([nm, "--defined-only", "-g", str(obj)], capture_output=True, text=True)
                defined.update(line.split()[-1] for line in res.stdout.splitlines() if line.strip())
    files = {}
    total = None
    for line in out.splitlines()[1:]:
        parts = line.split()
        if len(parts) < 6:
            continue
        text, data, bss = int(parts[0]), int(parts[1]), int(parts[2])
        name = Path(parts[5]).name
        row = {"text": text, "data": data, "bss": bss}
        if name == "(TOTALS)":
            total = row
        else:
            files[Path(name).stem + ".c"] = row
    return {"target": "cortex-m7 (fpv5-d16, hard float, thumb)", "flags": " ".join(FLAGS), "cc": cc,
            "files": files, "total": total, "needs": sorted(undefined - defined)}


def run(args) -> int:
    for tool in (args.cc, args.size):
        if shutil.which(tool) is None:
            print(f"coiltrack core-size: {tool} not found: {INSTALL}", file=sys.stderr)
            return 2
    try:
        rep = measure(args.cc, args.size)
    except subprocess.CalledProcessError as exc:
        print(exc.stderr or exc.stdout, file=sys.stderr)
        print(f"coiltrack core-size: {Path(exc.cmd[0]).name} failed (exit {exc.returncode})", file=sys.stderr)
        return 1
    except FileNotFoundError as exc:
        print(f"coiltrack core-size: {exc}", file=sys.stderr)
        return 2
    print(f"coiltrack core-size: the C core for {rep['target']}, {args.cc} {rep['flags']}")
    print(f"  {'file':<16}{'text':>8}{'data':>8}{'bss':>8}")
    for name, r in rep["files"].items():
        print(f"  {name:<16}{r['text']:>8}{r['data']:>8}{r['bss']:>8}")
    t = rep["total"]
    print(f"  {'total':<16}{t['text']:>8}{t['data']:>8}{t['bss']:>8}")
    if rep["needs"]:
        print(f"  needs from the C library: {', '.join(rep['needs'])}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rep, fh, indent=2)
        print(f"sizes written to {args.json}")
    return 0
