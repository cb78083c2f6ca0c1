"""Raab's tracker beside the least-squares solve on the same runs.

For each scenario and seed, the in-process bench (``tools.bench.runner.run_inproc``,
simulated clock) runs twice on the same trajectory, noise and seed, once with
``[pose] pose_solver = "lm"`` and once with ``"raab"`` (the rest of the
scenario's configuration unchanged), and reports per solver, over the seeds:
position RMS against the Cramer-Rao bound of the bench's magpylib physics
(all magnetic poses, and after the acquisition), orientation RMS,
``acquisition_updates`` (updates until the estimate stays within three
standard deviations of the truth), ``hemisphere_flips`` and the cost per
update: field evaluations of each burst's solve (machine-independent) and
its wall time (``begin`` plus the ``step`` calls; the machine's load shows in
it).

    .venv/bin/python -m coiltrack.tools.analyses.raab_compare --scenario raab-acquire helix-hemisphere static \\
        --seeds 1-4 [--duration S] [--json PATH]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time

import numpy as np

from coiltrack.firmware.pose.raab import RaabTracker
from coiltrack.firmware.pose.solver import SOLVE_RUNNING, PoseSolver

from .. import scenarios
from ..bench.runner import run_inproc
from ..scenarios.raab import tracking_figures

SOLVERS = (("lm", PoseSolver), ("raab", RaabTracker))


def _instrument(cls, sink):
    """Wrap ``cls.begin``/``cls.step`` to collect (evals, ns) per finished solve."""
    begin, step = cls.begin, cls.step
    acc = {}

    def b(self, *a, **k):
        t0 = time.perf_counter_ns()
        st = begin(self, *a, **k)
        acc[id(self)] = time.perf_counter_ns() - t0
        return st

    def s(self, budget):
        t0 = time.perf_counter_ns()
        st = step(self, budget)
        acc[id(self)] = acc.get(id(self), 0) + time.perf_counter_ns() - t0
        if not st & SOLVE_RUNNING:
            sink.append((self.solve_evals, acc.pop(id(self), 0)))
        return st
    cls.begin, cls.step = b, s
    return begin, step


def run_one(name: str, seed: int, duration: float, solver: str) -> dict:
    sc = scenarios.get(name)
    if sc.report_extra is None:
        sc = dataclasses.replace(sc, report_extra=tracking_figures)
    cfg = sc.firmware_config().with_(pose={"pose_solver": solver})
    sink = []
    saved = [(cls, _instrument(cls, sink)) for _, cls in SOLVERS]
    try:
        rep = run_inproc(sc, seed, duration, cfg=cfg)
    finally:
        for cls, (b, s) in saved:
            cls.begin, cls.step = b, s
    ev = np.array([e for e, _ in sink], float)
    us = np.array([t for _, t in sink], float) / 1e3
    rep["solve_evals_mean"] = float(ev.mean()) if ev.size else None
    rep["solve_us_median"] = float(np.median(us)) if us.size else None
    return rep


def _seeds(spec: str):
    out = []
    for part in spec.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", nargs="+", default=["raab-acquire", "helix-hemisphere"])
    ap.add_argument("--seeds", default="1-4")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    table = {}
    print(f"{'scenario':<18} {'solver':<5} {'pos RMS mm':>10} {'CRLB mm':>8} {'after acq.':>10} {'CRLB':>6} "
          f"{'ori deg':>7} {'acq. upd':>8} {'flips':>5} {'evals/upd':>9} {'us/upd':>7}")
    for name in a.scenario:
        sc = scenarios.get(name)
        dur = a.duration or sc.duration_s
        for solver, _ in SOLVERS:
            reps = [run_one(name, s, dur, solver) for s in _seeds(a.seeds)]

            def med(k):
                v = [r[k] for r in reps if r.get(k) is not None]
                return float(np.median(v)) if v else None

            def rmsk(k):
                v = [r[k] for r in reps if r.get(k) is not None]
                return math.sqrt(float(np.mean(np.square(v)))) if v else None

            acq = [r.get("acquisition_updates") for r in reps]
            row = {"position_rms_mm": rmsk("position_rms_mm"), "crlb_position_rms_mm": rmsk("crlb_position_rms_mm"),
                   "after_acquisition_position_rms_mm": rmsk("after_acquisition_position_rms_mm"),
                   "after_acquisition_crlb_position_rms_mm": rmsk("after_acquisition_crlb_position_rms_mm"),
                   "orientation_rms_deg": rmsk("orientation_rms_deg"),
                   "acquisition_updates": acq, "acquisition_updates_max": max((v for v in acq if v is not None),
                                                                             default=None),
                   "hemisphere_flips": sum(r.get("hemisphere_flips", 0) for r in reps),
                   "solve_evals_mean": med("solve_evals_mean"), "solve_us_median": med("solve_us_median"),
                   "seeds": _seeds(a.seeds), "duration_s": dur}
            table.setdefault(name, {})[solver] = row
            f = lambda v, p=2: "-" if v is None else f"{v:.{p}f}"  # noqa: E731
            print(f"{name:<18} {solver:<5} {f(row['position_rms_mm']):>10} {f(row['crlb_position_rms_mm']):>8} "
                  f"{f(row['after_acquisition_position_rms_mm']):>10} "
                  f"{f(row['after_acquisition_crlb_position_rms_mm']):>6} {f(row['orientation_rms_deg']):>7} "
                  f"{str(row['acquisition_updates_max']):>8} {row['hemisphere_flips']:>5} "
                  f"{f(row['solve_evals_mean'], 1):>9} {f(row['solve_us_median'], 0):>7}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(table, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
