"""Figures of a bench run (matplotlib, Agg backend, PNG).

From the pose table (``tools.outputs.posecsv``): the trajectory, true against
estimated, in three views (xy, xz, yz); position and orientation error
against time; position error against range with the Cramer-Rao bound (RMS
per 5 cm band of the per-pose bounds). From a report alone
(``bench --json``): the per-range bands of the report, error against its
CRLB.
"""
from __future__ import annotations

import numpy as np

#: width of the range bands of the error-against-range panel, mm
BAND_MM = 50.0
_STYLE = {"magnetic": dict(color="tab:blue", s=9, alpha=0.8), "fused": dict(color="tab:orange", s=2, alpha=0.5)}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _kinds(table):
    valid = np.isfinite(table["pos_err_mm"])
    for kind in ("magnetic", "fused"):
        sel = valid & (table["kind"] == kind)
        if np.any(sel):
            yield kind, sel


def _trajectory(axes, table) -> None:
    order = np.argsort(table["t_us"], kind="stable")
    for ax, (a, b) in zip(axes, (("x", "y"), ("x", "z"), ("y", "z"))):
        ax.plot(table[f"true_{a}_mm"][order], table[f"true_{b}_mm"][order], color="0.2", lw=0.8, label="true")
        for kind, sel in _kinds(table):
            ax.scatter(table[f"{a}_mm"][sel], table[f"{b}_mm"][sel], label=kind, **_STYLE[kind])
        ax.set_xlabel(f"{a} (mm)")
        ax.set_ylabel(f"{b} (mm)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"trajectory {a}{b}")
    axes[0].legend(loc="best", fontsize=8)


def _against_time(ax, table, col: str, label: str) -> None:
    for kind, sel in _kinds(table):
        ax.scatter(table["t_s"][sel], table[col][sel], label=kind, **_STYLE[kind])
    ax.set_xlabel("time (s)")
    ax.set_ylabel(label)
    ax.set_title(f"{label} against time")
    ax.grid(alpha=0.3)


def band_rms(range_mm: np.ndarray, values: np.ndarray, band_mm: float = BAND_MM):
    """(band centres, RMS of ``values`` in each band) over the bands that have values."""
    ok = np.isfinite(values)
    r, v = range_mm[ok], values[ok]
    if not r.size:
        return np.array([]), np.array([])
    k = np.floor(r / band_mm).astype(int)
    ks = np.unique(k)
    return (ks + 0.5) * band_mm, np.array([np.sqrt(np.mean(v[k == j] ** 2)) for j in ks])


def _against_range(ax, table) -> None:
    for kind, sel in _kinds(table):
        ax.scatter(table["range_mm"][sel] / 10, table["pos_err_mm"][sel], label=kind, **_STYLE[kind])
        c, rms = band_rms(table["range_mm"][sel], table["pos_err_mm"][sel])
        ax.plot(c / 10, rms, "-o", ms=3, color=_STYLE[kind]["color"], label=f"{kind} RMS")
    c, cb = band_rms(table["range_mm"], table["crlb_mm"])
    if c.size:
        ax.plot(c / 10, cb, "--s", ms=5, color="tab:red", lw=1.5, label="CRLB")
    ax.set_xlabel("range (cm)")
    ax.set_ylabel("position error (mm)")
    ax.set_yscale("log")
    ax.set_title("position error against range")
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="best", fontsize=8)


def _report_bands(ax, rep: dict) -> None:
    bands = rep.get("magnetic_by_range") or rep.get("by_range") or {}
    names = list(bands)
    mids = [sum(float(x) for x in n[:-2].split("-")) / 2 for n in names]
    ax.plot(mids, [bands[n]["position_rms_mm"] for n in names], "-o", color="tab:blue", label="magnetic RMS")
    ax.plot(mids, [bands[n]["crlb_position_rms_mm"] for n in names], "--o", color="tab:red", label="CRLB")
    fused = rep.get("by_range", {}) if "magnetic_by_range" in rep else {}
    if fused:
        ax.plot(mids, [fused[n]["position_rms_mm"] for n in names if n in fused], "-o", color="tab:orange",
                label="fused RMS")
    ax.set_xlabel("range (cm)")
    ax.set_ylabel("position RMS (mm)")
    ax.set_title("position error against range (report bands)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def written_path(path) -> str:
    """The file :func:`plot_run` writes for ``path``: ``path`` itself when its suffix names a
    format matplotlib writes (``.png``, ``.svg``, ``.pdf``, ...), ``path`` + ``.png`` when it has
    no suffix (as matplotlib's ``savefig`` does); ValueError for another suffix."""
    from pathlib import Path

    from matplotlib.backend_bases import FigureCanvasBase

    suffix = Path(path).suffix.lower().lstrip(".")
    if not suffix:
        return f"{path}.png"
    if suffix not in FigureCanvasBase.get_supported_filetypes():
        raise ValueError(f"'{path}': matplotlib writes no .{suffix} file; give a .png path (or .svg, .pdf)")
    return str(path)


def _counts(table) -> str:
    """Poses of the table by kind, with the RMS position error of each kind."""
    n = len(table["t_us"])
    parts = []
    for kind, sel in _kinds(table):
        rms = float(np.sqrt(np.mean(table["pos_err_mm"][sel] ** 2)))
        parts.append(f"{int(sel.sum())} {kind} ({rms:.2f} mm RMS)")
    valid = int(np.isfinite(table["pos_err_mm"]).sum())
    if valid < n:
        parts.append(f"{n - valid} without an error")
    return f"{n} poses" + (": " + ", ".join(parts) if parts else "")


def _title(rep: dict | None, table, source: str | None = None) -> str:
    """The figure's title: the file drawn, the run (scenario, seed, transport) when a
    report names it, the pose counts of the table and the report's headline figures."""
    head = [source] if source else []
    if rep is not None:
        head.append(f"{rep.get('scenario')} seed {rep.get('seed')} ({rep.get('transport')})")
    parts = [_counts(table)] if table is not None else []
    if rep is not None:
        parts.append(f"position RMS {rep.get('position_rms_mm')} mm, orientation RMS "
                     f"{rep.get('orientation_rms_deg')} deg, CRLB {rep.get('crlb_position_rms_mm')} mm")
    return ", ".join(head) + (": " if head and parts else "") + "; ".join(parts)


def plot_run(path, table: dict | None = None, rep: dict | None = None, dpi: int = 80,
             source: str | None = None) -> str:
    """Write the figure of a run (the full figure from a pose table, the per-range panel
    from a report alone), titled with ``source`` (the file drawn) when given; returns the
    name of the file written (:func:`written_path`)."""
    path = written_path(path)
    plt = _pyplot()
    if table is None:
        fig, ax = plt.subplots(figsize=(7, 5))
        _report_bands(ax, rep or {})
    else:
        fig, axes = plt.subplots(2, 3, figsize=(15, 9))
        _trajectory(axes[0], table)
        _against_time(axes[1, 0], table, "pos_err_mm", "position error (mm)")
        _against_time(axes[1, 1], table, "ori_err_deg", "orientation error (deg)")
        _against_range(axes[1, 2], table)
    import textwrap

    title = _title(rep, table, source) if table is not None or rep or source else ""
    fig.suptitle(textwrap.fill(title, 150 if table is not None else 75), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
