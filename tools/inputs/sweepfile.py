"""Reading back what ``coiltrack sweep`` wrote (``--json``, ``--csv``), strictly.

Through ``tools.inputs.infile``: a file that is not UTF-8, empty, not JSON (or with a
``NaN``, or a key twice), or whose runs are of the wrong shape is refused with
an :class:`~coiltrack.tools.inputs.infile.InputFileError` naming the file and the key
(``runs[3].seed``) or line. A CSV damaged after some good rows (cut short, a
row with a cell missing or a figure not a number) gives the rows before the
damage and says where it stops (``on_damage``).
"""
from __future__ import annotations

import csv
import math

from .infile import InputFileError, load_json, read_bytes, text_lines


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def check_run(r, path, where: str) -> None:
    """One run ``{"seed", "params", "figures"}``, of the right types."""
    if not isinstance(r, dict):
        raise InputFileError(path, f"must be an object {{seed, params, figures}}, got {r!r:.40}", key=where)
    seed = r.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise InputFileError(path, f"must be a seed (a whole number >= 0), got {seed!r}", key=f"{where}.seed")
    for part in ("params", "figures"):
        if not isinstance(r.get(part), dict):
            raise InputFileError(path, f"must be an object, got {r.get(part)!r:.40}", key=f"{where}.{part}")
    for k, v in r["params"].items():
        if not (isinstance(v, (bool, str)) or _number(v)):
            raise InputFileError(path, f"must be a configuration value, got {v!r:.40}", key=f"{where}.params.{k}")
    for k, v in r["figures"].items():
        if isinstance(v, (str, bool)):
            raise InputFileError(path, f"must be a number or null, got {v!r:.40}", key=f"{where}.figures.{k}")


def read_json(path) -> dict:
    """A ``sweep --json`` document: ``scenario`` a name, ``runs`` a list of runs (see
    :func:`check_run`; a ``null`` for a run not done is dropped), ``interrupted`` a bool."""
    doc = load_json(path, "sweep")
    if not isinstance(doc, dict):
        raise InputFileError(path, "not a sweep (not a JSON object)")
    if not isinstance(doc.get("scenario"), str):
        raise InputFileError(path, f"must be a scenario name, got {doc.get('scenario')!r:.40}", key="scenario")
    runs = doc.get("runs")
    if not isinstance(runs, list):
        raise InputFileError(path, f"must be a list of runs, got {runs!r:.40}", key="runs")
    for i, r in enumerate(runs):
        if r is not None:
            check_run(r, path, f"runs[{i}]")
    if not isinstance(doc.get("interrupted", False), bool):
        raise InputFileError(path, f"must be true or false, got {doc.get('interrupted')!r:.40}", key="interrupted")
    doc["runs"] = [r for r in runs if r is not None]
    return doc


def read_csv(path, on_damage=None) -> list[dict]:
    """The runs of a ``sweep --csv`` file (the columns before ``seed`` are the parameters,
    those after it the figures; an empty figure is None). A damaged row ends the runs: with
    ``on_damage(message)`` the rows before it are returned, without it is refused; a file
    with no run is refused."""
    # imported where used here and below: the sweep engine and its scenarios (scipy underneath) load only when needed
    from ..bench.sweep import parse_value

    data = read_bytes(path)
    if not data.strip():
        raise InputFileError(path, "is empty: no sweep runs in it")
    lines, damage = text_lines(data, path)
    if not lines:
        raise InputFileError(path, damage[1], line=damage[0])
    header = next(csv.reader([lines[0][1]]))
    if header.count("seed") != 1:
        raise InputFileError(path, "not a sweep table (no column 'seed', or two)", line=1)
    twice = [c for c in header if header.count(c) > 1]
    if twice or any(not c for c in header):
        raise InputFileError(path, f"column '{twice[0] if twice else ''}' given twice or empty", line=1)
    at = header.index("seed")
    runs = []
    for n, text in lines[1:]:
        if not text.strip():
            continue
        cells = next(csv.reader([text]))
        why = None
        if len(cells) != len(header):
            why = f"{len(cells)} cells, the header has {len(header)}"
        elif not cells[at].isdecimal():
            why = f"column seed: '{cells[at]}' is not a seed"
        else:
            try:
                params = {k: parse_value(v) for k, v in zip(header[:at], cells[:at])}
                figs = {}
                for k, v in zip(header[at + 1:], cells[at + 1:]):
                    x = None if v == "" else float(v)
                    if x is not None and not math.isfinite(x):
                        raise ValueError(f"column {k}: must be a finite number or empty, got '{v}'")
                    figs[k] = int(x) if x is not None and v.lstrip("-").isdecimal() else x
            except ValueError as exc:
                why = str(exc) if str(exc).startswith("column") else f"a value is not a number ({exc})"
        if why:
            damage = (n, why)
            break
        runs.append({"seed": int(cells[at]), "params": params, "figures": figs})
    if damage and (on_damage is None or not runs):
        raise InputFileError(path, damage[1] + ("" if runs else " (no run before it)"), line=damage[0])
    if not runs:
        raise InputFileError(path, "no run (a header alone)")
    if damage:
        on_damage(f"line {damage[0]}: {damage[1]}: using the {len(runs)} runs before it")
    return runs
