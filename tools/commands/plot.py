"""Draw a bench run as a PNG: from its pose table (``bench --poses``) the
trajectory true against estimated (xy, xz, yz), error against time and error
against range with the Cramer-Rao bound; from its report (``bench --json``)
the same when the report names its pose table (``poses_csv``), else the
report's per-range bands against their CRLB.

Exit status: 0 written; 2 bad arguments or an unreadable input."""
from __future__ import annotations

import sys
from pathlib import Path
from ..inputs.infile import InputFileError, load_json, warn
from ..outputs.plot import plot_run, written_path
from ..outputs.posecsv import read_csv
from ..outputs.sinks import OutputError, check_writable

HELP = "draw a bench run (pose table or report) as a PNG"


def add_arguments(p) -> None:
    p.add_argument("file", help="pose table (.csv, from bench --poses) or report (.json, from bench --json)")
    p.add_argument("-o", "--out", metavar="PATH", help="PNG to write (default: FILE with the suffix .png)")
    p.add_argument("--dpi", type=int, default=80, help="resolution (20..300, default 80)")


def _check_report(rep, path) -> None:
    """The parts of a bench report the figure reads, of the right types."""
    if not isinstance(rep, dict) or "scenario" not in rep:
        raise InputFileError(path, "not a bench report (no 'scenario')")
    for key in ("magnetic_by_range", "by_range"):
        bands = rep.get(key)
        if bands is None:
            continue
        if not isinstance(bands, dict):
            raise InputFileError(path, "must be an object of range bands", key=key)
        for name, band in bands.items():
            try:
                lo, hi = (float(x) for x in name[:-2].split("-"))
            except ValueError:
                raise InputFileError(path, "not a range band such as '10-15cm'", key=f"{key}.{name}") from None
            if not isinstance(band, dict):
                raise InputFileError(path, "must be an object", key=f"{key}.{name}")
            for fig in ("position_rms_mm", "crlb_position_rms_mm"):
                v = band.get(fig)
                if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
                    raise InputFileError(path, f"must be a number, got {v!r}", key=f"{key}.{name}.{fig}")
    table = rep.get("poses_csv")
    if table is not None and not isinstance(table, str):
        raise InputFileError(path, f"must be a path, got {table!r}", key="poses_csv")


def load(path: str):
    """(pose table or None, report or None) of a .csv table or a .json report, read strictly
    (``tools.inputs.infile``): a damaged file is an InputFileError naming it; a pose table cut
    short is used up to the damage, with a warning line."""
    def damaged(which):
        return lambda msg: warn("plot", which, msg)

    p = Path(path)
    if p.suffix.lower() != ".json":
        return read_csv(p, damaged(p)), None
    rep = load_json(p, "bench report")
    _check_report(rep, p)
    table = rep.get("poses_csv")
    for cand in ((Path(table), p.parent / Path(table).name) if table else ()):
        if cand.is_file():
            return read_csv(cand, damaged(cand)), rep
    return None, rep


def run(args) -> int:
    out = args.out or str(Path(args.file).with_suffix(".png"))
    try:
        if not 20 <= args.dpi <= 300:
            raise OutputError(f"--dpi: must be 20..300 (got {args.dpi})")
        try:
            out = written_path(out)
        except ValueError as exc:
            raise OutputError(f"--out: {exc}") from None
        check_writable("--out", out)
        table, rep = load(args.file)
    except (OSError, ValueError) as exc:      # OutputError and json's errors are ValueErrors
        print(f"coiltrack plot: {exc}", file=sys.stderr)
        return 2
    out = plot_run(out, table, rep, dpi=args.dpi, source=Path(args.file).name)
    print(f"figure written to {out}")
    return 0
