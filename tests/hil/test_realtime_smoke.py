"""One short smoke run of the two-process wall-clock bench (``coiltrack bench
--transport pty``): firmware and emulator in separate processes over a
pseudo-terminal for 2 s. The loops themselves are tested on an injected
clock in ``test_timing.py``; this only shows the processes start, talk,
synchronise and report."""
from __future__ import annotations

import os

import pytest

from coiltrack.tools import scenarios
from coiltrack.tools.realtime import run_pty


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals")
def test_pty_bench_smoke():
    rep = run_pty(scenarios.get("static"), seed=1, duration_s=2.0)
    assert rep["firmware_exit_code"] == 0
    assert rep["poses"] >= 2 and rep["poses_invalid"] == 0
    assert rep["frames_bad"] == 0 and rep["pulse_window_violations"] == 0
    for k in ("tick_jitter_us_median", "tick_jitter_us_p99", "tick_jitter_us_max", "deadline_misses",
              "latency_ms_p99", "faults"):
        assert rep.get(k) is not None, k
    assert rep["ticks"] >= 1900
    assert rep["faults"]["reported"]["firmware"]["sync_replies"] > 0


def test_slcan_bench_smoke():
    """Firmware and emulator as two processes on a CAN bus: python-can's slcan
    interface on both sides of a pseudo-terminal bridge."""
    rep = run_pty(scenarios.get("static"), seed=1, duration_s=3.0, transport="slcan")
    assert rep["transport"] == "slcan" and rep["firmware_exit_code"] == 0
    assert rep["poses"] >= 2
    assert rep["frames_bad"] == 0 and rep["pulse_window_violations"] == 0
