"""Cost per update of the burst trackers' pose solvers on the same recorded inputs.

For each solver (``[pose] pose_solver``: ``lm``, ``raab``) the recorded frames
are replayed into a fresh firmware with that solver (the fixed X, Y, Z cycle
does not depend on the solver, so every solver sees the same signals), and
each burst's magnetic solve (``tracker.solver``: ``begin`` then ``step``
until done) is measured: its field evaluations (``solve_evals``, one coil's
field and gradient at one point, machine-independent) and the wall time of
its ``begin`` and ``step`` calls, wall clock and the thread's CPU time (which
leaves out what a loaded machine spends on other work). Used by ``coiltrack
perf --solver``.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
from ..bench.framelog import replay

__all__ = ["solver_costs", "format_solver_costs"]


def _one(header: dict, reads, solver: str, warm_us: int) -> dict:
    from coiltrack.firmware.loop import Firmware
    from coiltrack.firmware.pose.solver import SOLVE_RUNNING

    evals, times, cpus, iters = [], [], [], []
    clk, cpu = time.perf_counter_ns, time.thread_time_ns
    state = {"ns": 0, "cpu": 0, "t": 0}

    def factory(cfg, port):
        fw = Firmware(cfg.with_(pose={"pose_solver": solver}), port)
        sv = fw.tracker.solver
        begin, step = sv.begin, sv.step

        def timed_begin(*a, **k):
            c0, t0 = cpu(), clk()
            st = begin(*a, **k)
            state["ns"], state["cpu"] = clk() - t0, cpu() - c0
            return st

        def timed_step(budget):
            c0, t0 = cpu(), clk()
            st = step(budget)
            state["ns"] += clk() - t0
            state["cpu"] += cpu() - c0
            if not st & SOLVE_RUNNING and state["t"] >= warm_us:
                evals.append(sv.solve_evals)
                times.append(state["ns"])
                cpus.append(state["cpu"])
                iters.append(sv.iterations)
            return st
        sv.begin, sv.step = timed_begin, timed_step
        return fw

    def on_tick(fw, t):
        state["t"] = t

    replay(factory, header, reads, on_tick)
    e, t, it = np.asarray(evals, float), np.asarray(times, float) / 1e3, np.asarray(iters, float)
    c = np.asarray(cpus, float) / 1e3
    if e.size == 0:
        return {"updates": 0}
    return {"updates": int(e.size), "evals_median": float(np.median(e)), "evals_mean": round(float(e.mean()), 2),
            "evals_max": int(e.max()), "us_median": round(float(np.median(t)), 1),
            "us_p90": round(float(np.percentile(t, 90)), 1), "cpu_us_median": round(float(np.median(c)), 1),
            "iterations_median": float(np.median(it))}


def solver_costs(header: dict, reads, solvers, warmup_s: float) -> dict:
    """``{solver: figures}`` and, with both, the ratios raab / lm: field
    evaluations (means) ``raab_lm_eval_ratio`` and time (medians)
    ``raab_lm_time_ratio`` (also as ``raab_to_lm_evals`` / ``raab_to_lm_time``)."""
    out = {s: _one(header, reads, s, int(warmup_s * 1e6)) for s in solvers}
    if "lm" in out and "raab" in out and out["lm"].get("updates") and out["raab"].get("updates"):
        lm, ra = out["lm"], out["raab"]
        out["raab_to_lm_evals"] = round(ra["evals_mean"] / lm["evals_mean"], 3)
        out["raab_to_lm_time"] = round(ra["us_median"] / lm["us_median"], 3)
        # the same ratios under the names of the cost criterion (issue 12: at most 1/3 each)
        out["raab_lm_eval_ratio"] = out["raab_to_lm_evals"]
        out["raab_lm_time_ratio"] = out["raab_to_lm_time"]
        # the thread's CPU time (time.thread_time_ns): the time a loaded machine spends elsewhere left out
        out["raab_lm_cpu_ratio"] = round(ra["cpu_us_median"] / lm["cpu_us_median"], 3)
    return out


def format_solver_costs(d: dict) -> str:
    lines = []
    for s in ("lm", "raab"):
        f = d.get(s)
        if not f:
            continue
        if not f.get("updates"):
            lines.append(f"  pose solve ({s:<4})     no burst solved after the warm-up")
            continue
        lines.append(f"  pose solve ({s:<4})     {f['updates']} updates: field evaluations median {f['evals_median']:g}"
                     f" (mean {f['evals_mean']}, max {f['evals_max']}), {f['us_median']} us median "
                     f"(p90 {f['us_p90']}), CPU {f['cpu_us_median']} us median, {f['iterations_median']:g} iterations")
    if "raab_to_lm_evals" in d:
        lines.append(f"  raab / lm per update  {d['raab_to_lm_evals']} of the evaluations, {d['raab_to_lm_time']} "
                     f"of the time (wall clock: machine load shows), {d['raab_lm_cpu_ratio']} of the CPU time")
    return "\n".join(lines)
