"""Energy against accuracy from ``coiltrack sweep --json`` files: the fixed cycles and the
adaptive policy (README "Adaptive actuation", ``docs/adaptive.md``).

    python -m coiltrack.tools.analyses.pareto SWEEP.json [SWEEP.json ...] [--bound BOUND.json ...]
        [--png PATH] [--markdown]

Per grid point of every sweep: the median over its seeds of the position and orientation RMS,
the coil energy and the charge drawn from the battery; a point is on the front when no other
point has at most its energy and both RMS at most its own. For a sweep of an actuation-policy
scenario (runs carrying ``fixed_*``), per grid point the worst seed's ratios to the fixed cycle
of the same seed and the median and worst energy ratio: the issue's acceptance figures. With
``--bound`` (``python -m coiltrack.tools.analyses.energy_bound --json``: the least energy per seed,
a fraction of the fixed cycle's, e.g. one file for 60 ms pulses and one for chosen lengths), the
per-seed energy ratios of every adaptive sweep beside each floor and their quotient, and a third
panel of the figure with both on one plot. An ``energy_bound`` file given among the sweeps (the
folder's ``docs/adaptive-sweeps/*.json``) is read as ``--bound``: one floor per column.

Exit status: 0 done; 2 a bad argument or an unreadable file (nothing written).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from ..inputs.sweepfile import read_json


def load(paths) -> list[dict]:
    """One row per grid point of every sweep file."""
    rows = []
    for path in paths:
        d = read_json(path)          # strictly: a damaged file is refused naming it and the key
        groups: dict[str, list[dict]] = {}
        for r in d["runs"]:
            if r is None or not r.get("figures"):
                continue
            key = json.dumps(r["params"], sort_keys=True)
            groups.setdefault(key, []).append(r)
        for key, runs in groups.items():
            f = [r["figures"] for r in runs]
            med = lambda k: statistics.median(x[k] for x in f if x.get(k) is not None)  # noqa: E731
            row = {"series": Path(path).stem, "scenario": d["scenario"], "params": json.loads(key), "seeds": sorted(r["seed"] for r in runs),
                   "position_rms_mm": med("position_rms_mm"), "orientation_rms_deg": med("orientation_rms_deg"),
                   "coil_energy_j": med("coil_energy_j"), "coil_charge_c": med("coil_charge_c"),
                   "pulses_per_s": med("pulses_per_s")}
            if all(x.get("fixed_position_rms_mm") is not None for x in f):
                pr = [x["position_rms_mm"] / x["fixed_position_rms_mm"] for x in f]
                orr = [x["orientation_rms_deg"] / x["fixed_orientation_rms_deg"] for x in f]
                er = [x["coil_energy_j"] / x["fixed_coil_energy_j"] for x in f]
                cr = [x["coil_charge_c"] / x["fixed_coil_charge_c"] for x in f]
                row.update(position_ratio_worst=max(pr), orientation_ratio_worst=max(orr),
                           energy_ratio_median=statistics.median(er), energy_ratio_worst=max(er),
                           charge_ratio_median=statistics.median(cr),
                           per_seed=[(r["seed"], round(p, 3), round(o, 3), round(e, 3))
                                     for r, p, o, e in sorted(zip(runs, pr, orr, er), key=lambda t: t[0]["seed"])])
            rows.append(row)
    return rows


def is_bound_file(path: str) -> bool:
    """Whether ``path`` is an ``energy_bound --json`` file (seeds and summary, no runs), not a sweep."""
    with open(path) as fh:
        d = json.load(fh)
    return isinstance(d, dict) and "runs" not in d and "seeds" in d and "summary" in d


def load_bounds(paths) -> dict[str, dict[int, float]]:
    """Per bound file and column: seed -> least energy fraction of the fixed cycle. A file of
    ``energy_bound --json`` has one floor per column (``modes``: fixed, chosen, chosen-long), named
    ``STEM COLUMN`` (``aligned`` added for pulses timed to the samples); a file of one floor per seed
    (``energy_fraction``) is named by its stem."""
    out = {}
    for path in paths or ():
        with open(path) as fh:
            d = json.load(fh)
        tag = " aligned" if d.get("sample_phase") == "aligned" else ""
        for r in d["seeds"]:
            if "modes" in r:
                for col, fig in r["modes"].items():
                    out.setdefault(f"{Path(path).stem} {col}{tag}", {})[int(r["seed"])] = float(fig["energy_fraction"])
            else:
                out.setdefault(Path(path).stem, {})[int(r["seed"])] = float(r["energy_fraction"])
    return out


def bound_table(rows, bounds) -> str:
    """Seed by seed: each floor, and each adaptive sweep's energy ratio and its quotient by each floor."""
    acc = [r for r in rows if "per_seed" in r]
    if not acc or not bounds:
        return ""
    head = "| seed | " + " | ".join(f"floor `{b}`" for b in bounds) + " | " + " | ".join(
        f"`{label(r)}` energy / fixed (/ each floor)" for r in acc) + " |"
    out = [head, "|" + " --- |" * (1 + len(bounds) + len(acc))]
    seeds = sorted({s for r in acc for s, *_ in r["per_seed"]})
    for s in seeds:
        cells = [f"{bounds[b][s]:.3f}" if s in bounds[b] else "" for b in bounds]
        for r in acc:
            e = {x[0]: x[3] for x in r["per_seed"]}.get(s)
            q = " / ".join(f"{e / bounds[b][s]:.2f}" for b in bounds if s in bounds[b]) if e is not None else ""
            cells.append(f"{e:.3f} ({q})" if e is not None else "")
        out.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def on_front(rows) -> None:
    for a in rows:
        a["front"] = not any(b is not a and b["coil_energy_j"] <= a["coil_energy_j"]
                             and b["position_rms_mm"] <= a["position_rms_mm"]
                             and b["orientation_rms_deg"] <= a["orientation_rms_deg"]
                             and (b["coil_energy_j"], b["position_rms_mm"], b["orientation_rms_deg"])
                             != (a["coil_energy_j"], a["position_rms_mm"], a["orientation_rms_deg"])
                             for b in rows)


def label(row) -> str:
    p = " ".join(f"{k.split('.')[-1]}={v}" for k, v in row["params"].items())
    return f"{row['scenario']} {p} ({row['series']})".replace("  ", " ")


def markdown(rows) -> str:
    out = ["| run (median of seeds) | position RMS | orientation RMS | coil energy | charge | pulses/s | front |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in sorted(rows, key=lambda r: r["coil_energy_j"]):
        out.append(f"| `{label(r)}` | {r['position_rms_mm']:.2f} mm | {r['orientation_rms_deg']:.3f} deg | "
                   f"{r['coil_energy_j']:.2f} J | {r['coil_charge_c']:.2f} C | {r['pulses_per_s']:.2f} | "
                   f"{'yes' if r['front'] else ''} |")
    acc = [r for r in rows if "energy_ratio_median" in r]
    if acc:
        out += ["", "| adaptive run | worst seed: position / fixed | worst seed: orientation / fixed | "
                    "energy / fixed, median | worst | charge / fixed, median |",
                "| --- | --- | --- | --- | --- | --- |"]
        for r in acc:
            out.append(f"| `{label(r)}` | {r['position_ratio_worst']:.3f} | {r['orientation_ratio_worst']:.3f} | "
                       f"{r['energy_ratio_median']:.3f} | {r['energy_ratio_worst']:.3f} | "
                       f"{r['charge_ratio_median']:.3f} |")
    return "\n".join(out)


def plot(rows, path: str, bounds=None) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    acc = [r for r in rows if "per_seed" in r]
    third = bool(acc)
    fig, axes = plt.subplots(1, 3 if third else 2, figsize=(16 if third else 11, 4.2))
    if third:
        ax = axes[2]
        for r in acc:
            ax.plot([x[0] for x in r["per_seed"]], [x[3] for x in r["per_seed"]], "o-", label=label(r))
        for b, per in (bounds or {}).items():
            ks = sorted(per)
            ax.plot(ks, [per[k] for k in ks], "k--" if "chosen" not in b else "k:", label=f"floor {b}")
        ax.set_xlabel("seed")
        ax.set_ylabel("coil energy / fixed cycle's")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    for ax, key, unit in ((axes[0], "position_rms_mm", "mm"), (axes[1], "orientation_rms_deg", "deg")):
        for scen in sorted({r["series"] for r in rows}):         # one line per sweep file
            pts = sorted((r for r in rows if r["series"] == scen), key=lambda r: r["coil_energy_j"])
            adaptive = "energy_ratio_median" in pts[0]
            ax.plot([r["coil_energy_j"] for r in pts], [r[key] for r in pts], "o-" if adaptive else "s--",
                    label=scen, lw=2 if adaptive else 1)
            for r in pts:
                ax.annotate(" ".join(f"{v}" for v in r["params"].values()), (r["coil_energy_j"], r[key]),
                            fontsize=6, xytext=(3, 3), textcoords="offset points")
        front = sorted((r for r in rows if r["front"]), key=lambda r: r["coil_energy_j"])
        ax.plot([r["coil_energy_j"] for r in front], [r[key] for r in front], "k:", lw=1, label="front")
        ax.set_xlabel("coil energy, 60 s (J, median of seeds)")
        ax.set_ylabel(f"{key.split('_')[0]} RMS ({unit}, median of seeds)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("schepers-adaptive against fixed X/Y/Z cycles, 60 ms pulses, same filter")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m coiltrack.tools.analyses.pareto", description=__doc__.split("\n\n")[0])
    p.add_argument("sweeps", nargs="+", help="coiltrack sweep --json files")
    p.add_argument("--bound", action="append", help="energy_bound --json file (repeatable)")
    p.add_argument("--png", help="write the figure here")
    p.add_argument("--markdown", action="store_true", help="print the tables as markdown")
    a = p.parse_args(argv)
    try:
        # energy_bound files among the sweeps (a folder's *.json) are floors, not sweeps
        floors = [p for p in a.sweeps if is_bound_file(p)]
        rows = load([p for p in a.sweeps if p not in floors])
        bounds = load_bounds((a.bound or []) + floors)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"pareto: cannot read the sweeps: {exc}", file=sys.stderr)
        return 2
    if not rows:
        print("pareto: no runs in the sweeps", file=sys.stderr)
        return 2
    on_front(rows)
    print(markdown(rows))
    table = bound_table(rows, bounds)
    if table:
        print()
        print(table)
    for r in rows:
        if "per_seed" in r:
            print(f"{label(r)}: per seed (seed, position ratio, orientation ratio, energy ratio): {r['per_seed']}")
    if a.png:
        plot(rows, a.png, bounds)
        print(f"figure written to {a.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
