"""Shared helpers of the HIL tests: run a scenario's bench with the firmware
on the simulated clock (no wall-clock sleeps), optionally with fault
switches, a changed firmware configuration, or a hook on the firmware."""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest

from coiltrack.firmware.loop import Firmware
from coiltrack.hil.faults import BenchFaults
from coiltrack.tools.outputs import report as report_mod
from coiltrack.tools import scenarios
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup


def flag_inside_step(node) -> list:
    """Wrap ``node.step``; the returned one-item list is True while the node's step runs (what
    a sampling-path probe counts)."""
    inside = [False]
    real_step = node.step

    def step(now_us, send):
        inside[0] = True
        try:
            real_step(now_us, send)
        finally:
            inside[0] = False
    node.step = step
    return inside


def capture_writes(end) -> bytearray:
    """Wrap ``end.write`` so every byte written is also kept in the returned bytearray."""
    sent = bytearray()
    real_write = end.write

    def write(data):
        sent.extend(data)
        real_write(data)
    end.write = write
    return sent


def run_bench(scenario="static", seed=1, duration_s=10.0, faults="", cfg=None, setup=None, scenario_obj=None):
    """Run firmware and emulator in one process; return bench, firmware, config and the report.

    ``cfg``: dict of FirmwareConfig overrides; ``setup(fw, bench)``: called before the run
    (e.g. to wrap the firmware's send or change its supervisor).
    """
    sc = scenario_obj or scenarios.get(scenario)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, seed, duration_s, emu_end, BenchFaults.parse(faults) if isinstance(faults, str) else faults)
    config = sc.firmware_config()
    if cfg:
        config = config.with_keys(**cfg)
    fw = Firmware(config, fw_end)
    if setup is not None:
        setup(fw, bench)
    tick = config.timing.tick_us
    end = int(duration_s * 1e6)
    t = 0
    while t <= end:
        bench.emulator.step(t)
        fw.tick(t)
        t += tick
    bench.emulator.step(t)
    rep = report_mod.build(bench, fw.status(), duration_s, transport="inproc", cfg=config)
    return SimpleNamespace(bench=bench, fw=fw, cfg=config, rep=rep, scenario=sc)


@pytest.fixture(scope="session")
def bench_runner():
    return run_bench
