"""Monte Carlo sweeps: independent in-process bench runs as tasks on an executor.

A :class:`Task` is one run: a scenario name, a seed, a duration and the
firmware configuration overrides of one grid point. :func:`run_task` is a
top-level function of the task alone, which rebuilds scenario, configuration,
world and firmware inside whatever process runs it, so a task gives the same
figures on a local process pool, a Dask cluster or Ray (the bench is seeded
by ``numpy.random.SeedSequence(seed)`` and keeps no state between runs).

Executors (:data:`EXECUTORS`) yield ``(task index, result)`` as runs finish;
:func:`run_tasks` puts the results back in task order. :func:`summarize`
gives, per grid point, the median, p90 and worst of every figure.

A scenario may instead be a measurement-level :class:`Experiment` (registered by its
scenario module, e.g. ``tools/scenarios/gietler.py``): its tasks run the experiment's
own ``run`` on the same executors, and its ``tables`` add keys to the sweep's document.
"""
from __future__ import annotations

import contextlib
import functools
import itertools
import math
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from coiltrack.firmware.config import config_from_dict

from .. import scenarios
from ..scenarios import EXPERIMENTS
from ..scenarios.base import Experiment, override_dict  # noqa: F401  (here for the callers of sweep)
from ..stopping import Stopped
from ..outputs.report import is_wall_clock

#: figures where a larger value is the better one (their worst is the minimum, their p90 the
#: 10th percentile); for every other figure (errors, energy, counts of faults) worst is the maximum
HIGHER_IS_BETTER = frozenset({
    "poses", "magnetic_poses", "fixed_poses", "pose_rate_hz", "magnetic_pose_rate_hz", "frames_rx",
    "mag_samples", "projected_runtime_h", "fixed_projected_runtime_h", "pulse_windows_checked",
    "pulse_window_min_margin_us", "command_lead_min_ms",
})

#: figures the printed summary shows when a run has them (JSON and CSV have every figure)
HEADLINE = ("position_rms_mm", "position_p95_mm", "orientation_rms_deg", "crlb_position_rms_mm",
            "magnetic_position_rms_mm", "magnetic_orientation_rms_deg", "poses", "poses_invalid",
            "coil_energy_j", "position_rms_ratio", "energy_ratio", "frames_bad", "pulse_window_violations")

#: report keys that are not figures of a run (they are the task's own inputs)
_INPUT_KEYS = ("seed", "duration_s")


class SweepError(RuntimeError):
    """A run of the sweep failed in its worker."""


def experiment(name: str) -> Experiment | None:
    """The scenario's :class:`Experiment`, or None for a bench scenario."""
    return EXPERIMENTS.get(name)


# ---------------------------------------------------------------- parsing the command line

def parse_seeds(text: str, max_count: int = 100_000) -> list[int]:
    """``"1-100"``, ``"7"`` or ``"1-4,10,20-22"``: seeds >= 0, each range ascending, at most
    ``max_count`` in all."""
    seeds: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("-")
        if not (lo.isdecimal() and (hi.isdecimal() if sep else True)):
            raise ValueError(f"'{part}' is not N or A-B with integers >= 0")
        a, b = int(lo), int(hi) if sep else int(lo)
        if b < a:
            raise ValueError(f"range '{part}' is descending")
        if len(seeds) + b - a + 1 > max_count:
            raise ValueError(f"more than {max_count} seeds")
        seeds.extend(range(a, b + 1))
    if len(set(seeds)) != len(seeds):
        raise ValueError("a seed is listed twice")
    return seeds


def parse_value(text: str):
    """A configuration value: true/false, an integer, a finite number, else the string itself."""
    low = text.strip().lower()
    if low in ("true", "false"):
        return low == "true"
    for kind in (int, float):
        try:
            v = kind(text)
        except ValueError:
            continue
        if not math.isfinite(v):
            raise ValueError(f"'{text}' is not a finite number")
        return v
    return text.strip()


def parse_set(text: str) -> tuple[str, list]:
    """``section.key=v1,v2,...`` -> (key, [values])."""
    key, sep, values = text.partition("=")
    key = key.strip()
    parts = values.split(",")
    if not sep or not key or any(not p.strip() for p in parts):
        raise ValueError(f"'{text}' is not KEY=V1,V2,... (KEY a config key, e.g. fusion.mag_sigma_t)")
    try:
        return key, [parse_value(p) for p in parts]
    except ValueError as exc:
        raise ValueError(f"{key}: {exc}") from None


def grid(sets: list[tuple[str, list]]) -> list[tuple[tuple[str, object], ...]]:
    """Every combination of the ``--set`` values, as ((key, value), ...) in the order given."""
    keys = [k for k, _ in sets]
    return [tuple(zip(keys, combo)) for combo in itertools.product(*(v for _, v in sets))]


# ---------------------------------------------------------------- one run

#: the one ``--set`` key that is not a firmware key: the bench's noise draw
#: (``runner.BenchSetup`` ``noise_draw``; 0 the seed's own), a sweep axis over repeats of each trajectory
NOISE_DRAW_KEY = "bench.noise_draw"


def split_noise_draw(overrides) -> tuple[int, tuple]:
    """(noise draw, the firmware overrides without it); a draw that is no integer >= 0 is a
    :class:`ConfigError` naming the key."""
    from coiltrack.firmware.config import ConfigError

    draw, rest = 0, []
    for key, value in overrides:
        if key != NOISE_DRAW_KEY:
            rest.append((key, value))
        elif isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ConfigError(NOISE_DRAW_KEY, f"'{value}' is not an integer >= 0")
        else:
            draw = value
    return draw, tuple(rest)


def scenario_with(name: str, overrides=()):
    """The named scenario with its firmware configuration overridden (a :class:`ConfigError`
    naming the key when an override is unknown or out of range); ``bench.noise_draw`` is checked
    and left out (:func:`split_noise_draw`)."""
    overrides = split_noise_draw(overrides)[1]
    sc = scenarios.get(name)
    exp = experiment(name)
    if exp is not None:
        exp.check(name, tuple(overrides))
        return sc
    if not overrides:
        return sc
    cfg = config_from_dict(override_dict(overrides), sc.firmware_config())
    return replace(sc, firmware_config=lambda: cfg)


@dataclass(frozen=True)
class Task:
    scenario: str
    seed: int
    duration_s: float
    overrides: tuple[tuple[str, object], ...] = ()


def figures(rep: dict) -> dict:
    """The numeric top-level keys of a bench report that depend on the run alone (not the
    wall-clock timing figures); NaN becomes None (strict JSON)."""
    out = {}
    for k, v in rep.items():
        if isinstance(v, bool) or not (v is None or isinstance(v, (int, float))):
            continue
        if k in _INPUT_KEYS or is_wall_clock(k):
            continue
        out[k] = None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v
    return out


def run_task(task: Task) -> dict:
    """One bench run (as ``coiltrack bench --transport inproc``, with the fixed-cycle
    comparison of an actuation-policy scenario): ``{"seed", "params", "figures"}``."""
    # imported where used here and below: the world's physics (magpylib) loads only when a run starts
    from .runner import add_fixed_comparison, run_inproc

    try:
        exp = experiment(task.scenario)
        if exp is not None:
            return {"seed": task.seed, "params": dict(task.overrides),
                    "figures": exp.run(task.scenario, task.seed, task.duration_s, task.overrides)}
        sc = scenario_with(task.scenario, task.overrides)
        draw = split_noise_draw(task.overrides)[0]
        rep = run_inproc(sc, task.seed, task.duration_s, noise_draw=draw)
        add_fixed_comparison(rep, sc, task.seed, task.duration_s, noise_draw=draw)
    except Exception as exc:
        # sent back as a plain message: an exception whose constructor takes other arguments than
        # its message (ConfigError) cannot be unpickled, which would break the process pool
        raise SweepError(f"{type(exc).__name__}: {exc}") from None
    return {"seed": task.seed, "params": dict(task.overrides), "figures": figures(rep)}


# ---------------------------------------------------------------- executors

def need_extra(module: str, extra: str, executor: str):
    """Import an executor's package, or an ImportError whose one-line message names the extra."""
    try:
        return __import__(module)
    except ImportError:
        raise ImportError(f"--executor {executor} needs {module}: pip install 'coiltrack[{extra}]'") from None


def _named(task: Task, result):
    """``result()``, an error raised in the worker named with the task's seed and parameters."""
    try:
        return result()
    except Exception as exc:
        where = " ".join([f"seed {task.seed}", *(f"{k}={v}" for k, v in task.overrides)])
        detail = exc if isinstance(exc, SweepError) else f"{type(exc).__name__}: {exc}"
        raise SweepError(f"run {where} failed: {detail}") from exc


def _worker_ignores_sigint() -> None:
    """A worker leaves Ctrl-C (SIGINT to the terminal's whole process group) to the sweep,
    which keeps the finished runs and stops the workers itself (SIGTERM)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _local(tasks, workers, scheduler):
    # spawned (not forked) workers: nothing inherited from this process's state or threads
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_worker_ignores_sigint)
    try:
        index = {pool.submit(run_task, t): i for i, t in enumerate(tasks)}
        for fut in as_completed(index):
            yield index[fut], _named(tasks[index[fut]], fut.result)
    except BaseException:  # interrupted, closed early or a run failed: stop the runs under way now
        for proc in list((getattr(pool, "_processes", None) or {}).values()):   # no public way before 3.14
            proc.terminate()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


@contextlib.contextmanager
def dask_client(workers: int | None, scheduler: str | None):
    """A Dask client: of the scheduler at ``scheduler``, else of a LocalCluster on 127.0.0.1
    with ``workers`` single-threaded worker processes (closed on exit)."""
    need_extra("distributed", "sweep", "dask")
    import logging

    from dask.distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None, silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
        yield client


def _dask(tasks, workers, scheduler):
    from dask.distributed import as_completed as dask_completed

    with dask_client(workers, scheduler) as client:
        futs = client.map(run_task, tasks, pure=False)
        index = {f.key: i for i, f in enumerate(futs)}
        try:
            for fut in dask_completed(futs):
                yield index[fut.key], _named(tasks[index[fut.key]], fut.result)
        except BaseException:  # interrupted, closed early or a run failed: drop the runs not done
            client.cancel(futs)
            raise


def _ray(tasks, workers, scheduler):
    ray = need_extra("ray", "ray", "ray")
    ray.init(address=scheduler, num_cpus=None if scheduler else workers, include_dashboard=False,
             _node_ip_address=None if scheduler else "127.0.0.1", configure_logging=False, log_to_driver=False)
    try:
        remote = ray.remote(num_cpus=1)(run_task)
        refs = [remote.remote(t) for t in tasks]
        index = {r: i for i, r in enumerate(refs)}
        pending = list(refs)
        while pending:
            (ref,), pending = ray.wait(pending, num_returns=1)
            yield index[ref], _named(tasks[index[ref]], functools.partial(ray.get, ref))
    finally:
        ray.shutdown()


EXECUTORS = {"local": _local, "dask": _dask, "ray": _ray}


class SweepInterrupted(KeyboardInterrupt):
    """Raised by :func:`run_tasks` on KeyboardInterrupt or a signal (``tools.stopping``);
    ``partial``: the results so far (None for the runs not done); ``exit_code``: 130 for
    SIGINT (Ctrl-C), 143 for SIGTERM; ``reason``: the signal's name."""

    def __init__(self, partial: list[dict | None], exit_code: int = 130, reason: str = "SIGINT"):
        super().__init__("interrupted")
        self.partial = partial
        self.exit_code = exit_code
        self.reason = reason


def run_tasks(tasks: list[Task], executor: str = "local", workers: int | None = None,
              scheduler: str | None = None, on_result=None) -> list[dict]:
    """Run the tasks on an executor of :data:`EXECUTORS`; the results in task order.
    ``on_result(n_done)`` is called after each run."""
    results: list[dict | None] = [None] * len(tasks)
    runs = EXECUTORS[executor](tasks, workers, scheduler)
    try:
        for n, (i, res) in enumerate(runs, 1):
            results[i] = res
            if on_result is not None:
                on_result(n)
    except KeyboardInterrupt:
        raise SweepInterrupted(results) from None
    except Stopped as exc:       # SIGINT or SIGTERM turned into Interrupted by the command line
        raise SweepInterrupted(results, exc.exit_code, exc.reason) from None
    except SweepError:
        raise
    except Exception as exc:  # the executor itself failed (a cluster lost, a worker killed)
        raise SweepError(f"{executor} executor failed: {type(exc).__name__}: {exc}") from exc
    finally:
        runs.close()
    return results


# ---------------------------------------------------------------- progress

class ProgressBar:
    """``[#####.....] 3/8 runs  0:05 elapsed  ETA 0:08`` on a stream (time injected)."""

    def __init__(self, total: int, enabled: bool, stream=None, clock=time.monotonic, width: int = 30):
        self.total, self.enabled, self.width = total, enabled, width
        self.stream = stream if stream is not None else sys.stderr
        self.clock = clock
        self.t0 = clock()

    def line(self, done: int) -> str:
        elapsed = self.clock() - self.t0
        fill = self.width * done // self.total if self.total else self.width
        eta = _hms(elapsed / done * (self.total - done)) if done else "?"
        return f"[{'#' * fill}{'.' * (self.width - fill)}] {done}/{self.total} runs  {_hms(elapsed)} elapsed  ETA {eta}"

    def update(self, done: int) -> None:
        if self.enabled:
            self.stream.write("\r" + self.line(done) + "\033[K")
            self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()


def _hms(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


# ---------------------------------------------------------------- summary

def stats(name: str, values: list) -> dict:
    """median, p90 and worst of one figure over runs (None and NaN left out and counted as
    ``missing``); for a figure of :data:`HIGHER_IS_BETTER` p90 is the 10th percentile and
    worst the minimum, so both are on the bad side."""
    x = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    out = {"median": None, "p90": None, "worst": None, "missing": len(values) - int(x.size)}
    if x.size:
        up = name not in HIGHER_IS_BETTER
        out.update(median=float(np.median(x)), p90=float(np.percentile(x, 90 if up else 10)),
                   worst=float(x.max() if up else x.min()))
    return out


def summarize(runs: list[dict]) -> list[dict]:
    """Per grid point (in the order first met): runs and the statistics of every figure."""
    groups: dict[tuple, list[dict]] = {}
    for r in runs:
        groups.setdefault(tuple(r["params"].items()), []).append(r)
    out = []
    for key, rs in groups.items():
        names = list(dict.fromkeys(k for r in rs for k in r["figures"]))
        out.append({"params": dict(key), "runs": len(rs),
                    "figures": {n: stats(n, [r["figures"].get(n) for r in rs]) for n in names}})
    return out


def format_summary(summary: list[dict], names=HEADLINE) -> str:
    """The printed table: one line per grid point and headline figure."""
    rows = [("parameters", "figure", "runs", "median", "p90", "worst")]
    for g in summary:
        label = " ".join(f"{k}={v}" for k, v in g["params"].items()) or "-"
        for n in (n for n in names if n in g["figures"]):
            s = g["figures"][n]
            rows.append((label, n, str(g["runs"]), *(_num(s[c]) for c in ("median", "p90", "worst"))))
            label = ""
    if len(rows) == 1:
        return "  (no run finished)"
    w = [max(len(r[i]) for r in rows) for i in range(6)]
    return "\n".join("  " + "  ".join(c.ljust(w[i]) if i < 2 else c.rjust(w[i]) for i, c in enumerate(r))
                     for r in rows)


def _num(v) -> str:
    return "-" if v is None else f"{v:.4g}"
