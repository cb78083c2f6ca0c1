"""The robustness sweep (``coiltrack check``): every scenario on a range of seeds, short runs,
counting what must not happen.

:func:`check_run` runs one (scenario, seed) on the simulated clock, as ``coiltrack bench
--transport inproc`` does (a measurement-level experiment such as ``gietler-air`` through its
own ``run``), and never raises for what the run does: an exception anywhere in the bench or the
firmware becomes the run's ``exception`` (type and message), ``where`` (the innermost frame of
the traceback, file:line in function) and ``side`` (``bench``: the emulated world and nodes,
``firmware``, ``tools`` or ``other``: the innermost frame's package) and ``origin`` (the innermost
frame of the bench or the firmware, when the exception was raised further in: the emulator's
node whose message the codec refused). A run that finished gives
its ``poses``, ``poses_invalid`` and, with a fault, ``faults_unreported`` (the fault switches that
raised none of the FAULT_EVENTs they should, ``tools.outputs.faultreport``).

:func:`one_fault` gives the ``--faults one`` schedule: a single timed fault per run, its kind
chosen by the seed (every kind in turn over consecutive seeds), on from 30 % of the run for 20 %
of it (a driver outage at least 3 s: the firmware waits 2.5 s before it declares the driver
lost, so ``--faults one`` wants runs of 5 s or more).
"""
from __future__ import annotations

import fnmatch
import math
import traceback
from pathlib import Path

#: the timed fault kinds of ``--faults one``, in turn by seed (``hil.faults`` syntax; {c} a coil)
ONE_FAULT_KINDS = ("sat={w}", "node_off=sensor@{w}", "node_off=driver@{w}", "open_circuit={c}@{w}",
                   "short={c}@{w}", "overheat={c}@{w}", "sag=0.6@{w}", "metal={w}")
#: the shortest driver outage of ``--faults one`` (s): ``HealthConfig.driver_timeout_us`` is 2.5 s
DRIVER_OFF_MIN_S = 3.0
#: packages of the tree, by the folder a frame's file lies in
_SIDES = (("hil", "bench"), ("firmware_py", "firmware"), ("firmware", "firmware"), ("tools", "tools"),
          ("protocol", "protocol"))


def select(patterns: str | None, names) -> list[str]:
    """The scenario names matching a comma list of names or shell patterns (``roetenberg-walking-*``),
    in sorted order; all of ``names`` for None. ValueError naming a pattern that matches nothing."""
    names = sorted(names)
    if patterns is None:
        return names
    out: list[str] = []
    for p in (p.strip() for p in patterns.split(",")):
        if not p:
            raise ValueError("an empty name in the list")
        hit = [n for n in names if fnmatch.fnmatchcase(n, p)]
        if not hit:
            raise ValueError(f"'{p}' matches no scenario")
        out += [n for n in hit if n not in out]
    return sorted(out)


def one_fault(seed: int, duration_s: float, n_coils: int) -> str:
    """The ``--faults one`` schedule of ``seed``: kind ``ONE_FAULT_KINDS[seed % 8]``, on from 30 %
    of the run for 20 % of it (a driver outage for at least ``DRIVER_OFF_MIN_S``: the firmware
    declares the driver lost after 2.5 s of silence), on coil ``seed // 8 % n_coils``."""
    kind = ONE_FAULT_KINDS[seed % len(ONE_FAULT_KINDS)]
    length = 0.2 * duration_s
    if kind.startswith("node_off=driver"):
        length = max(length, DRIVER_OFF_MIN_S)
    t0 = 0.3 * duration_s
    w = f"{t0:.3f}s-{t0 + length:.3f}s"
    return kind.format(w=w, c=(seed // len(ONE_FAULT_KINDS)) % max(1, n_coils))


def _side(filename: str) -> str:
    parts = Path(filename).parts
    for folder, side in _SIDES:
        if folder in parts:
            return side
    return "other"


def _frame(f) -> str:
    return f"{'/'.join(Path(f.filename).parts[-2:])}:{f.lineno} in {f.name}"


def _where(tb) -> tuple[str, str, str | None]:
    """(innermost frame of the project as ``file:line in function``, its side, and the innermost
    frame of the bench or the firmware when that is another: the code whose call raised)."""
    frames = traceback.extract_tb(tb)
    ours = [f for f in frames if _side(f.filename) != "other"] or frames
    if not ours:
        return "?", "other", None
    f = ours[-1]
    inner = [g for g in ours if _side(g.filename) in ("bench", "firmware")]
    origin = _frame(inner[-1]) if inner and inner[-1] is not f else None
    return _frame(f), _side(f.filename), origin


def check_run(scenario: str, seed: int, duration_s: float, faults: str = "none") -> dict:
    """One run of the sweep (module docstring): a dict that is always JSON-able."""
    import time

    out: dict = {"scenario": scenario, "seed": int(seed), "duration_s": float(duration_s), "faults": None,
                 "exception": None, "where": None, "side": None, "origin": None, "poses": None,
                 "poses_invalid": None, "faults_unreported": [], "wall_s": None}
    t0 = time.perf_counter()
    try:
        from .. import scenarios
        from . import sweep

        exp = sweep.experiment(scenario)
        if exp is not None:
            exp.run(scenario, int(seed), float(duration_s), ())
        else:
            from .runner import parse_faults, run_inproc

            sc = scenarios.get(scenario)
            lf = None
            if faults != "none":
                text = faults
                if faults == "one":
                    text = one_fault(seed, duration_s, len(sc.firmware_config().source.coils))
                out["faults"] = text
                lf = parse_faults(text, sc)
            rep = run_inproc(sc, int(seed), float(duration_s), faults=lf)
            out["poses"] = int(rep.get("poses") or 0) + int(rep.get("poses_invalid") or 0)
            out["poses_invalid"] = int(rep.get("poses_invalid") or 0)
            out["faults_unreported"] = list(rep.get("faults_unreported") or [])
            for k in ("position_rms_mm", "overconfident_fraction"):
                v = rep.get(k)
                out[k] = v if v is None or (isinstance(v, (int, float)) and math.isfinite(v)) else None
    except Exception as exc:  # what the sweep counts, not what stops it
        out["exception"] = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
        out["where"], out["side"], out["origin"] = _where(exc.__traceback__)
        out["traceback"] = traceback.format_exc()[-4000:]
    out["wall_s"] = round(time.perf_counter() - t0, 2)
    return out


def _job(job) -> dict:
    return check_run(*job)


def _ignore_sigint() -> None:
    """A worker leaves Ctrl-C to its parent, which stops it (the terminal sends it to all)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def summarize(runs: list[dict]) -> dict:
    """The sweep's figures over the runs done."""
    exc = [r for r in runs if r["exception"]]
    done = [r for r in runs if not r["exception"]]
    by_kind: dict[str, int] = {}
    for r in exc:
        key = f"{r['exception'].split(':')[0]} at {r['where']}"
        by_kind[key] = by_kind.get(key, 0) + 1
    return {
        "runs": len(runs),
        "exceptions": len(exc),
        "exception_kinds": by_kind,
        "runs_with_invalid_poses": sum(1 for r in done if r["poses_invalid"]),
        "poses": sum(r["poses"] or 0 for r in done),
        "poses_invalid": sum(r["poses_invalid"] or 0 for r in done),
        "faults_injected": sum(1 for r in done if r["faults"]),
        "faults_unreported": sum(len(r["faults_unreported"]) for r in done),
        "scenarios": len({r["scenario"] for r in runs}),
        "wall_s_sum": round(sum(r["wall_s"] or 0.0 for r in runs), 1),
    }


def run_jobs(jobs: list[tuple], workers: int, on_result=None) -> list[dict]:
    """Every job ``(scenario, seed, duration_s, faults)`` through :func:`check_run`, on ``workers``
    spawned processes (1: in this process); results in job order, None for a job not done.
    Stopped (KeyboardInterrupt or :class:`tools.stopping.Stopped`), the runs under way are
    stopped and the exception carries the results so far as ``partial``."""
    results: list[dict | None] = [None] * len(jobs)
    if workers <= 1 or len(jobs) <= 1:
        try:
            for i, j in enumerate(jobs):
                results[i] = _job(j)
                if on_result is not None:
                    on_result(results[i])
        except BaseException as exc:
            exc.partial = results
            raise
        return results
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    pool = ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=multiprocessing.get_context("spawn"),
                               initializer=_ignore_sigint)
    try:
        index = {pool.submit(_job, j): i for i, j in enumerate(jobs)}
        for fut in as_completed(index):
            i = index[fut]
            try:
                results[i] = fut.result()
            except Exception as exc:   # the worker itself died (killed, out of memory)
                sc, seed, dur, faults = jobs[i]
                results[i] = {"scenario": sc, "seed": seed, "duration_s": dur, "faults": None,
                              "exception": f"{type(exc).__name__}: {exc}"[:300], "where": "worker process",
                              "side": "other", "poses": None, "poses_invalid": None, "faults_unreported": [],
                              "wall_s": None}
            if on_result is not None:
                on_result(results[i])
    except BaseException as exc:
        for proc in list((getattr(pool, "_processes", None) or {}).values()):   # no public way before 3.14
            proc.terminate()
        exc.partial = results
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return results
