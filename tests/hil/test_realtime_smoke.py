"""One short smoke run of the two-process wall-clock bench (``coiltrack bench
--transport pty`` and ``--transport slcan``): firmware and emulator in
separate processes for 2-3 s of wall clock.

How much happens in those seconds depends on the machine: the firmware
process may start late, ticks are skipped on a loaded machine, a command
that arrives late is refused by the coil driver and its pose is marked
invalid. So nothing here counts ticks, poses or sync round trips. What is
asserted holds at any speed: the firmware process exits cleanly, the report
is complete, no frame arrives corrupted, no sample inside a pulse's edge is
used, and the firmware counts no more TIME_SYNC replies than its two nodes
can give. The loops' behaviour (ticks,
poses, synchronisation, deadline misses) is tested on an injected clock in
``test_timing.py`` and on the simulated clock of ``conftest.run_bench``."""
from __future__ import annotations

import os

import pytest

from coiltrack.tools import scenarios
from coiltrack.tools.bench.realtime import run_pty

REPORT_KEYS = ("poses", "poses_invalid", "frames_rx", "frames_bad", "pulse_window_violations", "ticks",
               "tick_jitter_us_median", "tick_jitter_us_p99", "tick_jitter_us_max", "deadline_misses",
               "latency_ms_p99", "faults", "firmware_exit_code")


def assert_ran_and_reported(rep: dict, transport: str) -> None:
    assert rep["transport"] == transport
    assert rep["firmware_exit_code"] == 0
    missing = [k for k in REPORT_KEYS if k not in rep]
    assert not missing, missing
    assert rep["frames_bad"] == 0 and rep.get("link_errors", 0) == 0
    assert rep["pulse_window_violations"] == 0
    fw = rep["faults"]["reported"]["firmware"]
    nodes = 2                                       # coil driver and one sensor answer each TIME_SYNC
    assert fw.get("sync_replies", 0) <= nodes * fw.get("sync_sent", 0)


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals")
def test_pty_bench_smoke():
    assert_ran_and_reported(run_pty(scenarios.get("static"), seed=1, duration_s=2.0), "pty")


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals")
def test_slcan_bench_smoke():
    """Firmware and emulator as two processes on a CAN bus: python-can's slcan
    interface on both sides of a pseudo-terminal bridge."""
    rep = run_pty(scenarios.get("static"), seed=1, duration_s=3.0, transport="slcan")
    assert_ran_and_reported(rep, "slcan")
