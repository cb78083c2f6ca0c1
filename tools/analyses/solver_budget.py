"""Work and time of the firmware pose solver per solve, per unit and per tick.

Measures ``coiltrack.firmware.pose.solver.PoseSolver`` on the source of the
roetenberg-bench scenario (``config.thesis_coils()``: three orthogonal coils,
50 turns, r = 5.5 cm, 1.5 A) at sensor distances 15-80 cm (random directions
in the +x hemisphere, random orientations, noise 0.5e-7 T / sqrt(5) per
element: one pulse window of about five samples):

* cold solves (acquisition + LM) and warm solves (LM from the true pose
  displaced by ``--warm-mm`` and rotated by ``--warm-deg``): field
  evaluations and microseconds, median and max;
* every unit of work, timed alone (``step`` with a budget of one unit):
  LM step, invariant-fit step, grid evaluations, Kuipers, covariance, in
  evaluations and microseconds (with ``--near`` extra poses at 8.5-11 cm,
  where the grid search runs);
* per budget B (evaluations per tick): the time of ``step(B)`` calls over
  whole solves, median, 99th percentile and max.

Wall-clock figures depend on this machine and its load; evaluations do not.

    .venv/bin/python -m coiltrack.tools.analyses.solver_budget [--poses 200] [--seed 1]
"""
from __future__ import annotations

import argparse
import time
from collections import defaultdict

import numpy as np

from coiltrack.firmware.config import thesis_coils
from coiltrack.firmware.linalg import exp_rotvec
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.pose.reference import measurement_model
from coiltrack.firmware.pose.solver import SOLVE_RUNNING, PoseSolver

SIGMA = 0.5e-7 / np.sqrt(5.0)
BUDGETS = (3, 6, 9, 12, 18, 30, 45)


def rotation(w):
    R = np.zeros((3, 3))
    exp_rotvec(*w, R)
    return R


def cases(rng, k, warm_mm, warm_deg, rmin=0.15, rmax=0.80):
    cfg = thesis_coils()
    coils = [Coil(c.center, c.axis, c.radius, c.turns) for c in cfg]
    cur = np.array([c.current for c in cfg])
    out = []
    for _ in range(k):
        u = rng.normal(size=3)
        u[0] = abs(u[0])
        p = rng.uniform(rmin, rmax) * u / np.linalg.norm(u)
        R = rotation(rng.normal(size=3) * 2.0)
        S = measurement_model(p, R, coils, cur) + rng.normal(0.0, SIGMA, (3, 3))
        d = rng.normal(size=3)
        w = rng.normal(size=3)
        x0p = p + warm_mm * 1e-3 * d / np.linalg.norm(d)
        x0R = R @ rotation(np.radians(warm_deg) * w / np.linalg.norm(w))
        out.append((np.linalg.norm(p), S, x0p, x0R))
    return coils, cur, out


def unit_name(ps):
    name = ps.next_unit.__name__
    return ps._acq.next_unit.__name__ if name == "_unit_acquire" else name


def timed_solve(ps, S, cur, sig, hemi, x0p=None, x0R=None, budget=1 << 62, per_unit=None):
    t0 = time.perf_counter()
    st = ps.begin(S, cur, sig, hemi, x0p, x0R)
    steps = []
    while st == SOLVE_RUNNING:
        name = unit_name(ps) if per_unit is not None else None
        t1 = time.perf_counter()
        st = ps.step(budget)
        dt = (time.perf_counter() - t1) * 1e6
        steps.append(dt)
        if per_unit is not None:
            per_unit[name].append((ps.evals_last_step, dt))
    return (time.perf_counter() - t0) * 1e6, steps


def summary(label, evals, us):
    evals, us = np.asarray(evals), np.asarray(us)
    print(f"{label:<32s} n {evals.size:5d}  evals median {np.median(evals):5.0f} max {evals.max():5.0f}   "
          f"us median {np.median(us):6.0f} p90 {np.percentile(us, 90):6.0f} max {us.max():6.0f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--warm-mm", type=float, default=1.0)
    ap.add_argument("--warm-deg", type=float, default=0.5)
    ap.add_argument("--near", type=int, default=30, help="extra poses at 8.5-11 cm for the unit timings")
    a = ap.parse_args()
    if a.poses < 1 or a.near < 0:
        ap.error("--poses must be >= 1 and --near >= 0")
    coils, cur, cs = cases(np.random.default_rng(a.seed), a.poses, a.warm_mm, a.warm_deg)
    ps = PoseSolver(coils, "exact")
    sig = np.full((3, 3), SIGMA)
    hemi = np.array([1.0, 0.0, 0.0])
    timed_solve(ps, cs[0][1], cur, sig, hemi)                       # warm-up
    res = defaultdict(list)
    for r, S, x0p, x0R in cs:
        us, _ = timed_solve(ps, S, cur, sig, hemi)
        near = "near (< 22 cm)" if r < 0.22 else "far (>= 22 cm)"
        res["cold"].append((ps.solve_evals, us))
        res[f"cold {near}"].append((ps.solve_evals, us))
        us, _ = timed_solve(ps, S, cur, sig, hemi, x0p, x0R)
        res[f"warm ({a.warm_mm} mm, {a.warm_deg} deg)"].append((ps.solve_evals, us))
        res["warm reacquired"].append((int(ps.status & 32 != 0), 0.0))
    print(f"{a.poses} poses at 15-80 cm, thesis source, sigma {SIGMA:.3g} T")
    for k, v in res.items():
        if k != "warm reacquired":
            summary(k, [e for e, _ in v], [t for _, t in v])
    print(f"warm starts reacquired: {sum(e for e, _ in res['warm reacquired'])}")
    near = cases(np.random.default_rng(a.seed + 1), a.near, a.warm_mm, a.warm_deg, 0.085, 0.11)[2]
    ev, us = [], []
    for _, S, _, _ in near:
        us.append(timed_solve(ps, S, cur, sig, hemi)[0])
        ev.append(ps.solve_evals)
    if near:
        summary("cold at 8.5-11 cm", ev, us)
        print(f"  of which grid searches (> 500 evaluations): {sum(e > 500 for e in ev)}")
    per_unit = defaultdict(list)
    for _, S, x0p, x0R in cs + near:
        timed_solve(ps, S, cur, sig, hemi, budget=1, per_unit=per_unit)
        timed_solve(ps, S, cur, sig, hemi, x0p, x0R, budget=1, per_unit=per_unit)
    print(f"units of work (step with budget 1 = one unit; with {a.near} more poses at 8.5-11 cm for the grid):")
    for k, v in sorted(per_unit.items()):
        summary(f"  {k.lstrip('_')}", [e for e, _ in v], [t for _, t in v])
    for k in ("_unit_radius", "_unit_lm_step"):
        if per_unit[k]:
            print(f"  median {np.median([t / e for e, t in per_unit[k]]):.1f} us per field evaluation in {k[6:]}")
    print("per tick: time of step(B) over whole cold and warm solves at 15-80 cm")
    ps.reset_step_stats()
    for b in BUDGETS:
        t = []
        for _, S, x0p, x0R in cs:
            t += timed_solve(ps, S, cur, sig, hemi, budget=b)[1]
            t += timed_solve(ps, S, cur, sig, hemi, x0p, x0R, budget=b)[1]
        t = np.asarray(t)
        print(f"  B = {b:3d} evals: {t.size:6d} steps, us median {np.median(t):6.0f} "
              f"p99 {np.percentile(t, 99):6.0f} max {t.max():6.0f}   max evals/step {ps.max_evals_per_step}")
        ps.reset_step_stats()


if __name__ == "__main__":
    main()
