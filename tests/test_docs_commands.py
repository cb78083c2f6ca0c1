"""Every command the README and the user guides show runs as shown and writes nothing into the
repository's tracked files.

The commands are read from the fenced ``sh`` blocks of README.md, docs/getting-started.md,
docs/real-boards.md and docs/guide/*.md (``text`` blocks are usage lines and printed output,
not run). The blocks of a page run in order in one temporary folder whose entries are links to the repository's
top-level entries (so ``examples/firmware.toml`` is found, and a command writing into a
tracked path would write into the repository and be caught), one line after the other, each
line's exit status 0. A line ``coiltrack ...`` runs shortened: ``--duration`` at most
:data:`SHORT_S` (added to ``bench``, ``sweep`` and ``results`` when absent) and a sweep's
``--seeds`` cut to :data:`SHORT_SEEDS` on one worker. Lines starting with ``mkdir`` and ``printf`` run as
they are; ``make`` lines are the Makefile's own targets and are not run here.

Marking a block (a comment on any of its lines):

* ``# doc-test: skip, REASON``: never run: needs hardware (a board, a UART, SocketCAN), waits
  for a client, or runs on the wall clock for its whole duration.
* ``# doc-test: long``: run only when ``COILTRACK_DOCS_LONG=1`` (a calibration run, a Dask
  cluster's start-up): what takes more than about 10 s here even shortened.

Before and after all blocks of a file, ``git status --porcelain`` and the digest of ``git diff``
must be equal: no example may change a tracked file.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHORT_S = 2.0
SHORT_SEEDS = "1-2"
RUN = {"coiltrack", "mkdir", "printf"}
NOT_RUN = {"make"}
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.M | re.S)
LONG = os.environ.get("COILTRACK_DOCS_LONG") == "1"


def doc_files() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "docs" / "getting-started.md", ROOT / "docs" / "real-boards.md"]
    files += sorted((ROOT / "docs" / "guide").glob("*.md"))
    return [f for f in files if f.exists()]


def blocks(path: Path) -> list[tuple[int, list[str], str]]:
    """``(line number, commands, mark)`` of each ``sh`` block: continuation lines joined,
    comments and blank lines left out; mark ``skip``, ``long`` or ``""``."""
    text = path.read_text()
    out = []
    for m in FENCE.finditer(text):
        if m.group(1) not in ("sh", "bash", "shell", "console"):
            continue
        body = m.group(2)
        mark = "skip" if "doc-test: skip" in body else "long" if "doc-test: long" in body else ""
        lines, cur = [], ""
        for raw in body.splitlines():
            line = raw.rstrip()
            if line.endswith("\\"):
                cur += line[:-1] + " "
                continue
            cur += line
            cmd = re.sub(r"\s+#.*$", "", cur).strip()
            cur = ""
            if cmd and not cmd.startswith("#"):
                lines.append(cmd[2:] if cmd.startswith("$ ") else cmd)
        out.append((text[:m.start()].count("\n") + 1, lines, mark))
    return out


def shorten(cmd: str) -> str:
    """A ``coiltrack`` line made short: ``--duration`` at most SHORT_S, a sweep's seeds cut."""
    argv = shlex.split(cmd)
    if argv[0] != "coiltrack" or len(argv) < 2:
        return cmd
    sub = argv[1]
    if "--duration" in argv:
        i = argv.index("--duration")
        argv[i + 1] = f"{min(float(argv[i + 1]), SHORT_S):g}"
    elif sub in ("bench", "sweep", "results"):
        argv += ["--duration", f"{SHORT_S:g}"]
    if sub == "sweep" and "--seeds" in argv:
        argv[argv.index("--seeds") + 1] = SHORT_SEEDS
    if sub == "sweep" and "--workers" not in argv:
        argv += ["--workers", "1"]          # one spawned worker: one import of the bench, not two
    return shlex.join(argv)


def git_state() -> tuple[str, str]:
    st = subprocess.run(["git", "status", "--porcelain"], cwd=ROOT, capture_output=True, text=True, check=True)
    diff = subprocess.run(["git", "diff", "--binary"], cwd=ROOT, capture_output=True, check=True)
    return st.stdout, hashlib.sha1(diff.stdout).hexdigest()


def _have_git() -> bool:
    return shutil.which("git") is not None and (ROOT / ".git").exists()


def test_blocks_are_found_and_every_line_is_known():
    """The extraction finds the README's examples, and every line of an unmarked block is a
    command this test runs or a Makefile target (anything else must be marked)."""
    found = {p.name: blocks(p) for p in doc_files()}
    readme = [c for _, cmds, _ in found["README.md"] for c in cmds]
    assert "make bench" in readme and "make test" in readme
    assert any(c.startswith("coiltrack bench") for c in readme)
    for name, bl in found.items():
        for line, cmds, mark in bl:
            if mark:
                continue
            for c in cmds:
                assert c.split()[0] in RUN | NOT_RUN, f"{name}:{line}: '{c}' is neither run nor marked"


def test_shorten():
    assert shorten("coiltrack bench --scenario x --seed 1") == "coiltrack bench --scenario x --seed 1 --duration 2"
    assert shorten("coiltrack bench --duration 20 --seed 1") == "coiltrack bench --duration 2 --seed 1"
    assert shorten("coiltrack bench --duration 1 --seed 1") == "coiltrack bench --duration 1 --seed 1"
    assert (shorten("coiltrack sweep --scenario static --seeds 1-8 --duration 5 --set a.b=1,2")
            == "coiltrack sweep --scenario static --seeds 1-2 --duration 2 --set a.b=1,2 --workers 1")
    assert shorten("coiltrack schema") == "coiltrack schema"


def _cases():
    for path in doc_files():
        if any(c.split()[0] in RUN for _, cmds, _ in blocks(path) for c in cmds):
            yield pytest.param(path, id=str(path.relative_to(ROOT)))


@pytest.fixture
def mirror(tmp_path):
    """A folder whose entries link to the repository's top-level entries (not .git, .venv,
    out, site): relative paths of the examples resolve, writes to tracked paths reach them."""
    for entry in ROOT.iterdir():
        if entry.name in (".git", ".venv", "out", "site", "build", ".pytest_cache", ".hypothesis"):
            continue
        (tmp_path / entry.name).symlink_to(entry)
    return tmp_path


#: runs a page's lines in one interpreter (one import of coiltrack per page, not per command):
#: ``coiltrack`` lines through ``coiltrack.tools.cli.main``, the others through the shell; prints
#: one JSON line per command with its exit status
RUNNER = r"""
import json, shlex, subprocess, sys
from coiltrack.tools.cli import main
for cmd in json.loads(sys.argv[1]):
    argv = shlex.split(cmd)
    if argv[0] == "coiltrack":
        try:
            code = main(argv[1:])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    else:
        code = subprocess.run(cmd, shell=True).returncode
    sys.stdout.flush(); sys.stderr.flush()
    print("@@status " + json.dumps([cmd, code]), flush=True)
    if code != 0:
        break
"""


@pytest.mark.slow
@pytest.mark.skipif(not _have_git(), reason="needs git and the repository's .git")
@pytest.mark.parametrize("path", list(_cases()))
def test_examples_run_and_change_no_tracked_file(path, mirror):
    """The blocks of one page, in order, in one folder (a later block may read what an earlier
    one wrote); a page whose every block is marked is reported as skipped."""
    before = git_state()
    cmds, skipped = [], []
    for line, block, mark in blocks(path):
        if mark == "skip" or (mark == "long" and not LONG):
            skipped.append(f"{line} ({mark})")
            continue
        cmds += [shorten(c) for c in block if c.split()[0] in RUN]
    if cmds:
        env = dict(os.environ, MPLBACKEND="Agg")
        p = subprocess.run([sys.executable, "-c", RUNNER, json.dumps(cmds)], cwd=mirror, env=env,
                           capture_output=True, text=True, timeout=600)
        done = [json.loads(x[len("@@status "):]) for x in p.stdout.splitlines() if x.startswith("@@status ")]
        bad = [(c, code) for c, code in done if code != 0]
        assert not bad and len(done) == len(cmds) and p.returncode == 0, (
            f"{path.name}: {bad or 'the runner stopped'}\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}")
    assert git_state() == before, f"{path.name}: an example changed files of the repository"
    if not cmds:
        pytest.skip(f"every block marked: lines {', '.join(skipped)}")
