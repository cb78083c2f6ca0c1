"""``bench --poses PATH``: one CSV row per POSE the firmware sent (magnetic and
fused, valid or not), beside the true pose at its time stamp.

Columns (``COLUMNS``): ``t_us`` and ``t_s`` (pose time, firmware clock),
``sensor`` (node id), ``kind`` (``magnetic`` or ``fused``), ``status`` (POSE_*
bits) and ``status_bits`` (their names joined by ``+``); the estimate
``x_mm y_mm z_mm qw qx qy qz`` and the truth ``true_x_mm ... true_qz``
(quaternions (w, x, y, z) mapping sensor to source, the true one on the
estimate's hemisphere); ``pos_err_mm`` (distance between the positions),
``ori_err_deg`` (angle of the rotation between the orientations),
``range_mm`` (true distance to the source), ``crlb_mm`` (the Cramer-Rao
bound of the position, magnetic poses only, as in the report; empty
otherwise); the covariance diagonal ``var_px_m2 var_py_m2 var_pz_m2
var_rx_rad2 var_ry_rad2 var_rz_rad2``. Errors of a pose without
``POSE_VALID`` are ``nan``.
"""
from __future__ import annotations

import csv
import math

import numpy as np

from coiltrack.firmware.rotation import angle_between, matrix_from_quat, quat_from_matrix
from coiltrack.protocol import schema
from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID
from ..inputs.infile import InputFileError, read_bytes, text_lines

COLUMNS = ("t_us", "t_s", "sensor", "kind", "status", "status_bits",
           "x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz",
           "true_x_mm", "true_y_mm", "true_z_mm", "true_qw", "true_qx", "true_qy", "true_qz",
           "pos_err_mm", "ori_err_deg", "range_mm", "crlb_mm",
           "var_px_m2", "var_py_m2", "var_pz_m2", "var_rx_rad2", "var_ry_rad2", "var_rz_rad2")
#: columns that are text; every other column is a number
TEXT = ("kind", "status_bits")

_BITS = sorted((getattr(schema, k), k[len("POSE_"):].lower()) for k in dir(schema)
               if k.startswith("POSE_") and isinstance(getattr(schema, k), int))


def pose_bit_names(status: int) -> list[str]:
    """Names of the POSE_* bits set in ``status``, lowest bit first."""
    return [name for bit, name in _BITS if status & bit]


def pose_row(rp: dict) -> dict:
    """One row of the table from a recorder pose (``hil.nodes.Recorder.poses``)."""
    m = rp["msg"]
    q = np.array([m.qw, m.qx, m.qy, m.qz])
    p = np.array([m.px, m.py, m.pz])
    tq = quat_from_matrix(rp["true_R"])
    if float(np.dot(tq, q)) < 0.0:
        tq = -tq
    valid = bool(m.status & POSE_VALID)
    nan = float("nan")
    row = {"t_us": m.t_us, "t_s": m.t_us * 1e-6, "sensor": m.node,
           "kind": "fused" if m.status & POSE_FUSED else "magnetic", "status": m.status,
           "status_bits": "+".join(pose_bit_names(m.status)),
           "pos_err_mm": float(np.linalg.norm(p - rp["true_p"])) * 1e3 if valid else nan,
           "ori_err_deg": math.degrees(angle_between(matrix_from_quat(q / np.linalg.norm(q)), rp["true_R"]))
           if valid else nan,
           "range_mm": float(np.linalg.norm(rp["true_p"])) * 1e3,
           "crlb_mm": rp["crlb_m"] * 1e3 if "crlb_m" in rp else nan}
    for k, v in zip(("x_mm", "y_mm", "z_mm", "true_x_mm", "true_y_mm", "true_z_mm"), (*p, *rp["true_p"])):
        row[k] = float(v) * 1e3
    for k, v in zip(("qw", "qx", "qy", "qz", "true_qw", "true_qx", "true_qy", "true_qz"), (*q, *tq)):
        row[k] = float(v)
    for k, f in zip(COLUMNS[-6:], ("var_px", "var_py", "var_pz", "var_rx", "var_ry", "var_rz")):
        row[k] = float(getattr(m, f))
    return row


def pose_table(recorder_poses) -> dict[str, np.ndarray]:
    """The table as columns (numbers as float arrays, text as object arrays)."""
    rows = [pose_row(rp) for rp in recorder_poses]
    return {c: np.array([r[c] for r in rows], dtype=object if c in TEXT else float) for c in COLUMNS}


def _cell(v) -> str:
    if isinstance(v, str):
        return v
    if v != v:
        return "nan"
    return repr(int(v)) if float(v).is_integer() and abs(v) < 2**53 else f"{v:.9g}"


def write_csv(table: dict, path) -> int:
    """Write the table; returns the number of rows."""
    n = len(table["t_us"])
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS)
        for i in range(n):
            w.writerow([_cell(table[c][i]) for c in COLUMNS])
    return n


#: columns that hold a finite number in every row: the clock, the node, the status and the truth
FINITE = ("t_us", "t_s", "sensor", "status", "true_x_mm", "true_y_mm", "true_z_mm",
          "true_qw", "true_qx", "true_qy", "true_qz", "range_mm")
#: columns of whole numbers
INTEGER = ("t_us", "sensor", "status")
#: the values of ``kind``
KINDS = ("magnetic", "fused")


def _row(cells: list[str], header: list[str]) -> dict | str:
    """One row of values, or what is wrong with it (a str)."""
    if len(cells) != len(header):
        return f"{len(cells)} cells, the header has {len(header)}"
    row = dict(zip(header, cells))
    out = {}
    for c in COLUMNS:
        v = row[c]
        if c == "kind":
            if v not in KINDS:
                return f"column kind: '{v}' is neither {' nor '.join(KINDS)}"
            out[c] = v
            continue
        if c in TEXT:
            out[c] = v
            continue
        if v == "" and c not in FINITE:
            out[c] = math.nan
            continue
        try:
            x = float(v)
        except ValueError:
            return f"column {c}: '{v}' is not a number"
        if c in FINITE and not math.isfinite(x):
            return f"column {c}: must be a finite number, got '{v}'"
        if math.isinf(x) and not c.startswith("var_"):
            return f"column {c}: must not be infinite, got '{v}'"
        if c in INTEGER and not x.is_integer():
            return f"column {c}: must be a whole number, got '{v}'"
        out[c] = x
    return out


def read_csv(path, on_damage=None) -> dict[str, np.ndarray]:
    """Read a table written by :func:`write_csv`, strictly (``tools.inputs.infile``).

    Refused with an :class:`~coiltrack.tools.inputs.infile.InputFileError` naming the file (and the
    line): unreadable, not UTF-8, empty, a header without a column of :data:`COLUMNS` or with
    one twice, no pose row. A damaged row (cut short, a cell missing, a value not a number,
    not finite where it must be, an unknown kind) ends the table: with ``on_damage(message)``
    the rows before it are returned and the message says where it stops; without, the
    damage is refused too."""
    data = read_bytes(path)
    lines, damage = text_lines(data, path)
    if not data.strip():
        raise InputFileError(path, "is empty: no pose table in it")
    if not lines:
        raise InputFileError(path, damage[1], line=damage[0])
    header = next(csv.reader([lines[0][1]]))
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise InputFileError(path, f"not a pose table (no column {missing[0]})", line=1)
    twice = [c for c in header if header.count(c) > 1]
    if twice:
        raise InputFileError(path, f"column {twice[0]} given twice", line=1)
    rows = []
    for n, text in lines[1:]:
        if not text.strip():
            continue
        r = _row(next(csv.reader([text])), header)
        if isinstance(r, str):
            damage = (n, r)
            break
        rows.append(r)
    if damage and (on_damage is None or not rows):
        raise InputFileError(path, damage[1] + ("" if rows else " (no pose row before it)"), line=damage[0])
    if not rows:
        raise InputFileError(path, "no pose row (a header alone)")
    if damage:
        on_damage(f"line {damage[0]}: {damage[1]}: using the {len(rows)} rows before it")
    return {c: np.array([r[c] for r in rows], dtype=object if c in TEXT else float) for c in COLUMNS}
