"""README.md and docs/ name no configuration key, section, class or module that does not exist.

The names are read where the docs mark them as code: inline spans (`` `section.key` ``,
`` `[section] key` ``, `` `cfg.section.key` ``, `` `coiltrack.x.y` ``, `` `ClassName` ``,
`` `firmware_py/x.py` ``), ``--set section.key=`` in command blocks, and ``toml`` blocks made of
firmware sections (read as a configuration file would be). ``CHANGELOG.md`` (included as
``docs/changelog.md``) is history and keeps the names of its day; generated pages are not in git.
"""
from __future__ import annotations

import ast
import importlib
import re
import tomllib
from dataclasses import fields
from pathlib import Path

import pytest

from coiltrack.firmware import core
from coiltrack.firmware.config import MERGED_SECTIONS, MOVED, SECTION_OF, SECTIONS, ConfigError, config_from_dict
from coiltrack.tools.bench.gietler import GietlerFilterConfig

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md"] + sorted(p for p in (ROOT / "docs").rglob("*.md")
                                     if p.name != "changelog.md" and "reference" not in p.parts)
#: sweep-only sections: the Gietler experiment's filter (``--set gietler.KEY``) and noise
SWEEP_KEYS = {"gietler": {f.name for f in fields(GietlerFilterConfig)}, "noise": {"var"}}
#: class-like names the docs use that are not classes of this code: other programs' names
#: (PLUS, PX4, Python, dask) and OpenIGTLink device and field names
EXTERNAL = {"NaN", "LocalCluster", "ProcessPoolExecutor", "IntegratorConing", "UseReceivedTimestamps",
            "OpenIGTLinkTracker", "StatusBits", "CovarianceDiagonal", "TimestampUs"}
DEVICE = re.compile(r"Sensor\d+(Mag)?ToSource")
#: the optional compiled extension (setup.py): importable only where a compiler built it, so its names
#: are checked there and taken as they are elsewhere (a `CC=/bin/false pip install .`)
OPTIONAL_EXT = "coiltrack.firmware._core"
CONFIG_WORDS = set(SECTION_OF) | set(MOVED)


def _spans(text: str):
    """(line, inline code span) of a markdown text, fenced blocks left out."""
    out, fenced = [], False
    for i, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            out.extend((i, m.group(1)) for m in re.finditer(r"`+([^`\n]+?)`+", line))
    return out


def _blocks(text: str):
    """(language, first line, body) of each fenced block."""
    return [(m.group(1), text[:m.start()].count("\n") + 1, m.group(2))
            for m in re.finditer(r"^```(\w*)[^\n]*\n(.*?)^```", text, re.M | re.S)]


def _config_errors(span: str) -> list[str]:
    bad = []
    for m in re.finditer(r"\[\[?([\w.]+)\]\]?(?:`*\s+`*(\w+))?", span):
        sec, key = m.group(1), m.group(2)
        if sec in MERGED_SECTIONS:
            bad.append(f"section [{sec}] (merged into [{MERGED_SECTIONS[sec]}])")
        elif sec == "gietler":
            bad.append("section [gietler] (not a firmware section: --set gietler.KEY)")
        elif sec in SECTIONS and key in CONFIG_WORDS and key not in SECTIONS[sec]:
            bad.append(f"[{sec}] {key} (the key is in [{SECTION_OF.get(key, '?')}])")
    for m in re.finditer(r"(?<![\w./-])cfg\.([a-z_]\w*)\b", span):
        if m.group(1) in SECTION_OF and m.group(1) not in SECTIONS:
            bad.append(f"cfg.{m.group(1)} (a key without its section: cfg.{SECTION_OF[m.group(1)]}.{m.group(1)})")
    for m in re.finditer(r"(?<![\w./-])(cfg\.)?([a-z_]+)\.([a-z_][a-z0-9_]*)\b", span):
        cfg, sec, key = m.groups()
        if sec in SWEEP_KEYS:
            if key not in SWEEP_KEYS[sec]:
                bad.append(f"{sec}.{key}")
        elif (sec in SECTIONS or sec in MERGED_SECTIONS) and key in CONFIG_WORDS and key not in SECTIONS.get(sec, ()):
            bad.append(f"{sec}.{key} (the key is in [{SECTION_OF.get(key, '?')}])")
        elif cfg and sec in SECTIONS and key not in SECTIONS[sec]:
            bad.append(f"cfg.{sec}.{key}")
    return bad


def _module_errors(span: str) -> list[str]:
    bad = []
    for m in re.finditer(r"\bcoiltrack(?:\.[A-Za-z_]\w*)+", span):
        parts = m.group(0).split(".")
        if any(p.isupper() for p in parts) or span[m.end():m.end() + 1] in "/" and m.end() < len(span) \
                or parts[-1] in ("dbc", "toml", "json", "csv", "py"):
            continue                                   # a placeholder (NAME) or a file name
        if (m.group(0) + ".").startswith(OPTIONAL_EXT + ".") and not core.available():
            continue
        obj, i = None, len(parts)
        while i > 1 and obj is None:
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ImportError:
                i -= 1
        for a in parts[i:]:
            if obj is None or not hasattr(obj, a):
                bad.append(m.group(0))
                break
            obj = getattr(obj, a)
        if obj is None:
            bad.append(m.group(0))
    return bad


def _class_names() -> set[str]:
    names = set()
    for pkg in ("firmware_py", "hil", "protocol", "tools"):
        for p in (ROOT / pkg).rglob("*.py"):
            names.update(n.name for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, ast.ClassDef))
    return names


CLASSES = _class_names()


def _name_errors(span: str) -> list[str]:
    bad = []
    if re.fullmatch(r"[A-Z][a-z0-9]+[A-Z]\w*", span) and span not in CLASSES and span not in EXTERNAL \
            and not DEVICE.fullmatch(span):
        bad.append(f"class {span}")
    m = re.fullmatch(r"((?:firmware_py|hil|protocol|tools|tests)/[\w/]+\.py)(?::\d+)?", span)
    if m and not (ROOT / m.group(1)).exists():
        bad.append(f"file {m.group(1)}")
    return bad


def _block_errors(lang: str, body: str) -> list[str]:
    bad = []
    for m in re.finditer(r"--set[ =]([a-z_]+\.[a-z_0-9]+)=", body):
        bad.extend(_config_errors(m.group(1)))
    if lang == "toml":
        try:
            d = tomllib.loads(body)
        except tomllib.TOMLDecodeError:
            return bad + ["a toml block that is not TOML"]
        if d and all(k in SECTIONS or k in MERGED_SECTIONS for k in d):
            try:
                config_from_dict(d)
            except ConfigError as exc:
                if "must" not in exc.message:       # an example of a refused value is fine
                    bad.append(str(exc))
    return bad


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_doc_names_only_what_exists(path):
    text = path.read_text()
    bad = []
    for line, span in _spans(text):
        bad.extend(f"line {line}: {e}" for e in _config_errors(span) + _module_errors(span) + _name_errors(span))
    for lang, line, body in _blocks(text):
        bad.extend(f"block at line {line}: {e}" for e in _block_errors(lang, body))
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("span, found", [
    ("[adaptive_policy] nis_feedback", "merged"),          # config-codemod: keep
    ("body_motion.baseline_gyro", "[body]"),               # config-codemod: keep
    ("[pose] lm_cost_tol", None),
    ("[timing] mag_sigma_t", "[pulse]"),
    ("pulse.mag_sigma_t", None),
    ("fusion.mag_sigma_t", "[pulse]"),
    ("cfg.pulse_us", "cfg.timing.pulse_us"),               # config-codemod: keep
    ("cfg.timing.pulse_us", None),
    ("cfg.timing.pulse_usx", "cfg.timing.pulse_usx"),
    ("gietler.gietler_iterations", None),
    ("[gietler]", "not a firmware section"),
    ("coiltrack.firmware.config.FirmwareConfig", None),
    ("coiltrack.firmware.config.FirmwareConfigs", "coiltrack"),
    ("coiltrack.firmware.nosuchmodule", "coiltrack"),
    ("SchepersEKF", None),
    ("SchepersEKG", "class"),
    ("firmware_py/config.py", None),
    ("firmware_py/konfig.py", "file"),
])
def test_the_checks_catch_a_wrong_name(span, found):
    """Each rule flags the kind of slip it is for, and passes the right name."""
    bad = _config_errors(span) + _module_errors(span) + _name_errors(span)
    if found is None:
        assert bad == []
    else:
        assert any(found in b for b in bad), bad
