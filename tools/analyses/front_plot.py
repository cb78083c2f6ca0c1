"""The energy-accuracy front against the fixed cycle, with the least-energy bound on the same axes.

    python -m coiltrack.tools.analyses.front_plot --sweep-json adaptive.json [--sweep-json ...]
        [--fixed-json fixed-910.json --sweep-json fixed-640.json ...] --bound bound.json [--bound ...]
        [--bound-columns 'fixed,chosen aligned'] --png out/front.png

Both axes are ratios to the fixed X, Y, Z cycle of the same seed: coil energy (median over the seeds)
and position or orientation RMS (median over the seeds, the worst seed as the bar's end). A sweep of
an actuation-policy scenario carries its own fixed cycle (``fixed_*`` figures, ``coiltrack sweep
--scenario schepers-adaptive``), one point per grid point (e.g. ``pulse_length`` fixed or chosen,
``fixed_accuracy_ratio``); a sweep of a fixed cycle (``schepers-fixed-640``) is divided by the
``--fixed-json`` sweep (its first grid point) seed by seed. The fixed cycle is the point (1, 1). A bound file
(``python -m coiltrack.tools.analyses.energy_bound --json``) holds, per column (60 ms pulses; pulse
length chosen; chosen with long baselines), the least energy of every seed at RMS at most ``ratio``
times the fixed cycle's: drawn at height ``ratio``, the median with a bar to the worst seed; several
files at several ``--ratio`` draw the bound as a line. A bound of pulses timed to the magnetometer's
samples (``--sample-phase aligned``: the floor of ``pulse_length = "chosen"``, whose starts are put on
the sample clock) is drawn as a column of its own. Nothing left of a bound's line at its height keeps
that accuracy (within the bound's model). Settings every sweep point shares are printed once and left
out of the labels.

Exit status: 0 written; 2 a bad argument or an unreadable file (nothing written).
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

from ..inputs.sweepfile import read_json

_COLUMN_LABELS = {"fixed": "bound, 60 ms pulses", "chosen": "bound, pulse length chosen",
                  "chosen-long": "bound, length and baseline chosen",
                  "fixed aligned": "bound, 60 ms pulses timed to the samples",
                  "chosen aligned": "bound, pulse length chosen, timed to the samples",
                  "chosen-long aligned": "bound, length and baseline chosen, timed to the samples"}


def _by_seed(runs) -> dict:
    return {int(r["seed"]): r["figures"] for r in runs if r and r.get("figures")}


def reference(path: str) -> dict:
    """The figures per seed of the fixed cycle in ``path``: the runs of its first grid point
    (``fixed-910.json`` swept over ``timing.cycle_us`` starts with the 600 ms cycle)."""
    runs = read_json(path)["runs"]
    first = runs[0]["params"] if runs else {}
    return _by_seed(r for r in runs if r["params"] == first)


def _param_items(params) -> tuple:
    return tuple(sorted((k.split(".")[-1], str(v)) for k, v in (params or {}).items()))


def sweep_points(path: str, fixed: dict | None, common: frozenset = frozenset()) -> list[dict]:
    """One point per grid point of a sweep file: energy ratio median, RMS ratios median and worst.
    The label names the file and the grid point's settings except those in ``common``."""
    d = read_json(path)
    groups: dict[str, list] = {}
    for r in d["runs"]:
        if r and r.get("figures"):
            groups.setdefault(" ".join(f"{k}={v}" for k, v in _param_items(r["params"]) if (k, v) not in common),
                              []).append(r)
    out = []
    for label, runs in groups.items():
        e, p, o = [], [], []
        for s, f in _by_seed(runs).items():
            if f.get("fixed_coil_energy_j") is not None:
                ref = (f["fixed_coil_energy_j"], f["fixed_position_rms_mm"], f["fixed_orientation_rms_deg"])
            elif fixed is not None and s in fixed:
                g = fixed[s]
                ref = (g["coil_energy_j"], g["position_rms_mm"], g["orientation_rms_deg"])
            else:
                continue
            e.append(f["coil_energy_j"] / ref[0])
            p.append(f["position_rms_mm"] / ref[1])
            o.append(f["orientation_rms_deg"] / ref[2])
        if e:
            out.append({"label": f"{Path(path).stem} {label}".strip(), "energy": statistics.median(e),
                        "position": (statistics.median(p), max(p)), "orientation": (statistics.median(o), max(o))})
    return out


def common_settings(paths) -> frozenset:
    """The (key, value) settings every grid point of every sweep file shares (left out of the labels)."""
    sets = [frozenset(_param_items(r["params"])) for p in paths for r in read_json(p)["runs"] if r and r.get("figures")]
    return frozenset.intersection(*sets) if sets else frozenset()


def bound_points(paths) -> dict:
    """Per column of the bound files: [(ratio, median, worst)] sorted by ratio; a file of pulses timed
    to the samples (``--sample-phase aligned``) has its own columns (``chosen aligned``)."""
    from ..inputs.infile import InputFileError, load_json

    out: dict[str, list] = {}
    for path in paths:
        d = load_json(path, "energy bound")
        try:
            tag = " aligned" if d.get("sample_phase") == "aligned" else ""
            rows = [(col + tag, float(d["ratio"]), float(fig["median"]), float(fig["worst"]))
                    for col, fig in d["summary"].items()]
        except (KeyError, TypeError, AttributeError, ValueError) as exc:
            raise InputFileError(path, f"not an energy_bound --json file ({exc!r:.60})") from None
        for col, r, med, worst in rows:
            out.setdefault(col, []).append((r, med, worst))
    return {k: sorted(v) for k, v in out.items()}


def plot_front_with_bound(points: list[dict], bound: dict, path: str) -> None:
    """The figure: per panel (position, orientation) the sweeps' points, the fixed cycle at (1, 1) and
    the bound's columns at their ratios (median, bar to the worst seed)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), sharex=True)
    for ax, key in zip(axes, ("position", "orientation")):
        ax.plot([1.0], [1.0], "ks", ms=8, label="fixed X/Y/Z cycle, 0.91 A")
        for pt in points:
            med, worst = pt[key]
            ax.errorbar([pt["energy"]], [med], yerr=[[0.0], [worst - med]], fmt="o", capsize=3, label=pt["label"])
        for col, rows in bound.items():
            r, med, worst = (list(t) for t in zip(*rows))
            line = ax.plot(med, r, "--", marker="v", lw=1.5, label=_COLUMN_LABELS.get(col, col))[0]
            ax.errorbar(med, r, xerr=[[0.0] * len(r), [w - m for w, m in zip(worst, med)]], fmt="none",
                        ecolor=line.get_color(), capsize=3)
        ax.set_xlabel("coil energy / fixed cycle's")
        ax.set_ylabel(f"{key} RMS / fixed cycle's")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6.5, loc="upper right")
    fig.suptitle("schepers-adaptive: energy against accuracy, ratios to the fixed cycle of the same seed "
                 "(median of seeds, bar to the worst)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m coiltrack.tools.analyses.front_plot", description=__doc__.split("\n")[0])
    ap.add_argument("--sweep-json", action="append", default=[], help="a coiltrack sweep --json file (repeatable)")
    ap.add_argument("--fixed-json", help="the 0.91 A fixed cycle's sweep, to divide fixed-cycle sweeps by")
    ap.add_argument("--bound", action="append", default=[], help="an energy_bound --json file (repeatable)")
    ap.add_argument("--bound-columns", help="draw only these bound columns, a comma list (e.g. 'fixed,chosen aligned')")
    ap.add_argument("--png", required=True, help="write the figure here (under out/)")
    a = ap.parse_args(argv)
    if not a.sweep_json and not a.bound:
        print("front_plot: give --sweep-json or --bound", file=sys.stderr)
        return 2
    try:
        fixed = reference(a.fixed_json) if a.fixed_json else None
        common = common_settings(a.sweep_json) if len(a.sweep_json) > 1 else frozenset()
        points = [pt for p in a.sweep_json for pt in sweep_points(p, fixed, common)]
        bound = bound_points(a.bound)
        if a.bound_columns:
            keep = [c.strip() for c in a.bound_columns.split(",")]
            unknown = [c for c in keep if c not in bound]
            if unknown:
                raise ValueError(f"--bound-columns: no column {unknown} in the bound files (they have {sorted(bound)})")
            bound = {c: bound[c] for c in keep}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"front_plot: cannot read the files: {exc}", file=sys.stderr)
        return 2
    if common:
        print("settings of every sweep point: " + " ".join(f"{k}={v}" for k, v in sorted(common)))
    for pt in points:
        print(f"{pt['label']}: energy {pt['energy']:.3f}, position {pt['position'][0]:.3f} (worst {pt['position'][1]:.3f}), "
              f"orientation {pt['orientation'][0]:.3f} (worst {pt['orientation'][1]:.3f})")
    for col, rows in bound.items():
        print(f"{col}: " + ", ".join(f"ratio {r:g}: median {m:.3f}, worst {w:.3f}" for r, m, w in rows))
    plot_front_with_bound(points, bound, a.png)
    print(f"figure written to {a.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
