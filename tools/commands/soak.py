"""Soak: long bench runs (default one hour of simulated time) under a seeded random
schedule of every fault switch (``tools.bench.soak.random_schedule``: the link faults at
small rates throughout, and node outages, saturation, open and shorted coils, an
overheated coil, supply sag, metal and clock steps one after the other), on
several seeds. Per seed: crashes, the recovery time of every fault window
(``fault_recovery_s``), overconfident poses, the events raised against the faults
injected, and the firmware's memory over the run (no net growth after warm-up,
state bytes constant)."""
from __future__ import annotations

import json
import sys

from .. import args as A
from .. import scenarios
from ..bench.soak import soak_run, random_schedule, passed
from ..bench.sweep import parse_seeds
from ..scenarios import get
from ..stopping import held_signals, Interrupted, Stopped

HELP = "long bench runs under a seeded random schedule of every fault switch"
EXIT = {1: "a soak condition failed (a crash, a fault unreported or not recovered from within 3 s, more than "
           "1 % overconfident poses, or memory growth): the table names it",
        130: "stopped by SIGINT (Ctrl-C): the seeds run, the one under way to where it stopped, are printed and "
             "written, marked interrupted", 143: "stopped by SIGTERM: likewise"}
#: most seeds one call runs
MAX_SEEDS = 64


def add_arguments(p) -> None:
    p.add_argument("--scenario", type=scenarios.known, default="roetenberg-fusion",
                   help="scenario name (default roetenberg-fusion)")
    p.add_argument("--seeds", default="1-3", help="seeds: A-B, N or a comma list of both (default 1-3)")
    p.add_argument("--duration", type=A.bench_seconds, default=3600.0,
                   help=f"simulated seconds per seed, (0, {A.MAX_BENCH_S:g}] (default 3600)")
    p.add_argument("--workers", type=A.integer(1, 64), default=1, help="seeds run in parallel (default 1)")
    p.add_argument("--json", type=A.output_path, metavar="PATH", help="write the per-seed reports as JSON")
    p.add_argument("--print-schedule", action="store_true", help="print each seed's fault schedule and exit")


def _one(job):
    name, seed, duration = job
    return soak_run(get(name), seed, duration)


def summary_row(rep: dict) -> dict:
    """The figures of one seed's soak that the table and the README give."""
    rec = {k: v for k, v in rep.get("fault_recovery_s", {}).items()}
    known = [v for v in rec.values() if v is not None]
    ev = rep.get("faults", {}).get("reported", {}).get("events", {})
    return {
        "seed": rep["seed"], "duration_s": rep["duration_s"], "crashed": rep["crashed"],
        "position_rms_mm": rep.get("position_rms_mm"), "magnetic_position_rms_mm": rep.get("magnetic_position_rms_mm"),
        "fault_windows": len(rec), "recovery_s_max": max(known) if known else None,
        "recovery_s_median": sorted(known)[len(known) // 2] if known else None,
        "not_recovered": [k for k, v in rec.items() if v is None],
        "poses_overconfident": rep.get("poses_overconfident"),
        "overconfident_fraction": rep.get("overconfident_fraction"),
        "faults_unreported": rep.get("faults_unreported"), "events": sum(ev.values()),
        "fusion_recoveries": rep.get("fusion", {}).get("fusion_recoveries"),
        "state_bytes": rep["memory"][-1]["state_bytes"] if rep.get("memory") else None,
        "state_bytes_growth": rep.get("state_bytes_growth"), "items_growth": rep.get("items_growth"),
    }


def format_rows(rows: list[dict]) -> str:
    head = ("seed", "crash", "fused mm", "faults", "rec max s", "rec med s", "not rec", "overconf", "unrep",
            "events", "restarts", "state B", "growth B/items")
    lines = ["  ".join(f"{h:>9}" for h in head)]
    for r in rows:
        vals = (r["seed"], "yes" if r["crashed"] else "no", r["position_rms_mm"], r["fault_windows"],
                r["recovery_s_max"], r["recovery_s_median"], len(r["not_recovered"]),
                f'{r["overconfident_fraction"]}', len(r["faults_unreported"] or ()), r["events"],
                r["fusion_recoveries"], r["state_bytes"], f'{r["state_bytes_growth"]}/{r["items_growth"]}')
        lines.append("  ".join(f"{str(v):>9}" for v in vals))
    return "\n".join(lines)


def run(args) -> int:
    try:
        seeds = parse_seeds(args.seeds, MAX_SEEDS)
    except ValueError as exc:
        print(f"coiltrack soak: --seeds: {exc}", file=sys.stderr)
        return 2
    sc = get(args.scenario)
    if args.print_schedule:
        for s in seeds:
            print(f"seed {s}: {random_schedule(s, args.duration, len(sc.firmware_config().source.coils))}")
        return 0
    jobs = [(args.scenario, s, args.duration) for s in seeds]
    stopped = None
    try:
        reps = _run_jobs(jobs, args.workers)
    except _SoakStopped as exc:
        reps, stopped = exc.reps, exc.stopped
        print(f"coiltrack soak: stopped by {stopped.reason} with {len(exc.reps)} of {len(jobs)} seeds run "
              "(the one under way to where it stopped); writing them", file=sys.stderr)
    with held_signals():        # a second signal waits for the report to be written
        code = _finish(args, seeds, reps, stopped)
    return code


class _SoakStopped(Exception):
    """The seeds' reports done when a signal stopped the soak (a seed under way: its
    report to where it stopped, marked ``interrupted``), and the signal."""

    def __init__(self, reps, stopped):
        super().__init__(stopped.reason)
        self.reps, self.stopped = reps, stopped


#: a worker stopped by its parent runs no further seed
_worker_stopped = False


def _note_stop(signum, frame) -> None:
    global _worker_stopped
    _worker_stopped = True


def _worker_setup() -> None:
    """A worker leaves Ctrl-C to the parent; SIGTERM from the parent between seeds marks the
    worker stopped (it runs no further seed), during one stops it (:func:`_one_stoppable`)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _note_stop)


def _one_stoppable(job):
    """:func:`_one` in a worker: SIGTERM from the parent stops the seed, whose report to
    where it stopped (marked interrupted) is returned; None once stopped."""
    import signal

    def stop(signum, frame):
        _note_stop(signum, frame)
        signal.signal(signal.SIGTERM, _note_stop)
        raise Interrupted(signum)

    signal.signal(signal.SIGTERM, stop)
    try:
        if _worker_stopped:           # checked after the handler is in place: no signal falls between
            return None
        return _one(job)
    except Stopped as exc:
        return exc.partial
    finally:
        signal.signal(signal.SIGTERM, _note_stop)


#: longest wait for a stopped worker's report (a hang guard)
STOP_WAIT_S = 120.0


def _run_jobs(jobs, workers: int) -> list[dict]:
    """Every seed's report in order; a SIGINT or SIGTERM (``Stopped``) becomes
    :class:`_SoakStopped` with the reports finished and those of the seeds under way to
    where they stopped."""
    reps = []
    if workers > 1 and len(jobs) > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        ex = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_worker_setup)
        futs = [ex.submit(_one_stoppable, j) for j in jobs]
        try:
            for f in futs:
                reps.append(f.result())
        except Stopped as exc:
            with held_signals():        # a second signal waits for the workers' reports
                for f in futs:
                    f.cancel()
                for proc in list((getattr(ex, "_processes", None) or {}).values()):
                    proc.terminate()    # SIGTERM: the seed under way stops with its report
                for f in futs[len(reps):]:
                    if f.cancelled():
                        continue
                    try:
                        r = f.result(timeout=STOP_WAIT_S)
                    except Exception:    # noqa: BLE001 - a worker lost: its seed is not reported
                        continue
                    if r is not None:
                        reps.append(r)
                for proc in list((getattr(ex, "_processes", None) or {}).values()):
                    if proc.is_alive():
                        proc.kill()     # a worker that did not answer: the pool must not wait for it
            raise _SoakStopped(sorted(reps, key=lambda r: r["seed"]), exc) from None
        finally:
            ex.shutdown(wait=True, cancel_futures=True)
        return reps
    for j in jobs:
        try:
            reps.append(_one(j))
        except Stopped as exc:
            if exc.partial is not None:
                reps.append(exc.partial)
            raise _SoakStopped(reps, exc) from None
    return reps


def _finish(args, seeds, reps: list[dict], stopped) -> int:
    """The table printed and the JSON written of the seeds run; the exit status."""
    rows = [summary_row(r) for r in reps]
    print(f"coiltrack soak: {args.scenario}, {args.duration:g} s per seed, seeds {', '.join(map(str, seeds))}"
          + (f" (stopped by {stopped.reason}: {len(reps)} seeds reported)" if stopped else ""))
    print(format_rows(rows))
    bad = []
    for r in reps:
        v = r["verdict"]
        if not passed(v):
            bad.append(f"seed {r['seed']}: " + ", ".join(k for k, val in v.items() if k != "slow_recoveries"
                                                          and not val)
                       + (f" (slow: {', '.join(v['slow_recoveries'])})" if v["slow_recoveries"] else ""))
    for b in bad:
        print(f"  FAILED {b}")
    if args.json:
        doc = {"scenario": args.scenario, "duration_s": args.duration, "seeds": seeds, "summary": rows, "runs": reps}
        if stopped is not None:
            doc.update(interrupted=True, stopped_by=stopped.reason)
        with open(args.json, "w") as fh:
            json.dump(doc, fh, indent=1, default=str)
        print(f"report written to {args.json}")
    if stopped is not None:
        return stopped.exit_code
    return 1 if bad else 0
