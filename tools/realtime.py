"""Wall-clock loops: the firmware at a fixed tick and the emulator beside it,
as two processes joined by a pseudo-terminal."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from hil.clock import WallClock

from . import report as report_mod
from .links import FdLink, make_raw_pty
from .runner import BenchSetup, Progress


def firmware_loop(fw, clock: WallClock, duration_us: int, tick_us: int) -> dict:
    """Run ``fw.tick`` every ``tick_us`` of wall time; measure period jitter,
    tick execution time and deadline misses (a tick that starts a whole
    period late or runs longer than a period). Buffers are sized up front."""
    n_max = duration_us // tick_us + 2
    starts = np.zeros(n_max, dtype=np.int64)
    exec_us = np.zeros(n_max, dtype=np.int64)
    n = 0
    misses = 0
    next_tick = max(0, clock.now())
    next_tick -= next_tick % tick_us
    while n < n_max:
        now = clock.now()
        if now >= duration_us:
            break
        if now < next_tick:
            rem = next_tick - now
            if rem > 150:
                time.sleep((rem - 100) * 1e-6)
            continue
        t0 = now
        fw.tick(t0)
        t1 = clock.now()
        starts[n] = t0
        exec_us[n] = t1 - t0
        n += 1
        if t0 - next_tick >= tick_us or t1 - t0 >= tick_us:
            misses += 1
        next_tick += tick_us
        if next_tick <= t1 - tick_us:          # fell behind: skip missed slots, count them
            skipped = (t1 - next_tick) // tick_us
            misses += int(skipped)
            next_tick += skipped * tick_us
    periods = np.diff(starts[:n])
    jitter = np.abs(periods - tick_us) if periods.size else np.zeros(1)
    return {
        "ticks": int(n),
        "tick_us": tick_us,
        "tick_period_us_median": float(np.median(periods)) if periods.size else None,
        "tick_jitter_us_median": float(np.median(jitter)),
        "tick_jitter_us_p99": float(np.percentile(jitter, 99)),
        "tick_jitter_us_max": float(np.max(jitter)),
        "tick_exec_us_median": float(np.median(exec_us[:n])) if n else None,
        "tick_exec_us_p99": float(np.percentile(exec_us[:n], 99)) if n else None,
        "deadline_misses": int(misses),
    }


def emulator_loop(emulator, link, clock: WallClock, duration_us: int, progress=None, step_us: int = 500) -> None:
    while True:
        now = clock.now()
        if now > duration_us:
            break
        if now >= 0:
            emulator.step(now)
            if hasattr(link, "flush"):
                link.flush()
            if progress is not None:
                progress.update(now * 1e-6, len(emulator.recorder.poses))
        time.sleep(step_us * 1e-6)


def run_pty(scenario, seed: int, duration_s: float, faults=None, progress: bool = False) -> dict:
    """Firmware in a child process (``coiltrack firmware``) on the slave side of
    a raw pseudo-terminal; emulator here on the master side; both on
    CLOCK_MONOTONIC from a shared epoch."""
    master, slave, slave_name = make_raw_pty()
    epoch_ns = time.monotonic_ns() + 1_500_000_000      # give the child time to start
    duration_us = int(duration_s * 1e6)
    stats_fd, stats_path = tempfile.mkstemp(suffix=".json", prefix="coiltrack-fw-")
    os.close(stats_fd)
    cmd = [sys.executable, "-m", "tools.cli", "firmware", "--port", slave_name,
           "--scenario", scenario.name, "--epoch-ns", str(epoch_ns),
           "--duration", str(duration_s + 0.5), "--stats-json", stats_path]
    child = subprocess.Popen(cmd)
    link = FdLink(master)
    bench = BenchSetup(scenario, seed, duration_s, link, faults)
    clock = WallClock(epoch_ns)
    prog = Progress(progress, duration_s, scenario.name + " (pty)")
    try:
        emulator_loop(bench.emulator, bench.link, clock, duration_us + 300_000, prog)
    finally:
        prog.done()
        try:
            child.wait(timeout=30)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        os.close(master)
        os.close(slave)
    try:
        with open(stats_path) as fh:
            fw_stats = json.load(fh)
    except (OSError, ValueError):
        fw_stats = {"status": {}, "timing": {}}
    finally:
        if os.path.exists(stats_path):
            os.unlink(stats_path)
    cfg = scenario.firmware_config()
    rep = report_mod.build(bench, fw_stats.get("status", {}), duration_s, transport="pty", cfg=cfg)
    rep.update({k: v for k, v in fw_stats.get("timing", {}).items()})
    rep["firmware_exit_code"] = child.returncode
    return rep
