"""The runner that puts a world, its nodes and a firmware on one link.

It is the only place where ``hil`` and ``firmware_py`` meet, and they meet
only through protocol frames on a link.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from firmware_py.firmware import Firmware
from hil.emulator import Emulator
from hil.faults import FaultyLink, LinkFaults
from hil.nodes import CoilDriverNode, Recorder, SensorNode
from protocol.schema import NODE_COIL_DRIVER, NODE_SENSOR_BASE

from . import report as report_mod
from .links import inproc_pair
from .scenarios import Scenario


class BenchSetup:
    """World, nodes and recorder of a scenario for one seed."""

    def __init__(self, scenario: Scenario, seed: int, duration_s: float, link, faults: LinkFaults | None = None):
        ss = np.random.SeedSequence(seed)
        s_world, s_driver, s_sensor, s_faults = (int(s.generate_state(1)[0]) for s in ss.spawn(4))
        self.scenario = scenario
        self.seed = seed
        self.duration_s = duration_s
        self.world = scenario.build_world(s_world, duration_s)
        self.faults = faults or LinkFaults()
        self.link = FaultyLink(link, self.faults, seed=s_faults) if self.faults.active() else link
        self.driver = CoilDriverNode(NODE_COIL_DRIVER, self.world, seed=s_driver)
        self.sensor = SensorNode(NODE_SENSOR_BASE, self.world, rate_hz=scenario.sensor.rate_hz,
                                 noise_t=scenario.sensor.noise_t, seed=s_sensor)
        self.recorder = Recorder(self.world)
        self.emulator = Emulator(self.world, self.link, self.driver, [self.sensor], self.recorder)


class Progress:
    def __init__(self, enabled: bool, total_s: float, label: str):
        self.enabled = enabled and sys.stderr.isatty()
        self.total_s = total_s
        self.label = label
        self.last = 0.0

    def update(self, sim_s: float, poses: int, extra: str = "") -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self.last < 0.2:
            return
        self.last = now
        sys.stderr.write(f"\r{self.label}: t={sim_s:7.1f}/{self.total_s:.0f} s  poses={poses:5d} {extra}\033[K")
        sys.stderr.flush()

    def done(self) -> None:
        if self.enabled:
            sys.stderr.write("\r\033[K")
            sys.stderr.flush()


def run_inproc(scenario: Scenario, seed: int, duration_s: float, faults: LinkFaults | None = None,
               progress: bool = False, cfg=None, transport: str = "inproc") -> dict:
    """Run firmware and emulator in one process on the simulated clock."""
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(scenario, seed, duration_s, emu_end, faults)
    cfg = cfg or scenario.firmware_config()
    fw = Firmware(cfg, fw_end)
    tick = cfg.tick_us
    end_us = int(duration_s * 1e6)
    prog = Progress(progress, duration_s, scenario.name)
    wall0 = time.perf_counter()
    t = 0
    while t <= end_us:
        bench.emulator.step(t)
        fw.tick(t)
        if (t // tick) % 1000 == 0:
            prog.update(t * 1e-6, fw.poses)
        t += tick
    bench.emulator.step(t)  # deliver the last frames to the recorder
    prog.done()
    wall = time.perf_counter() - wall0
    rep = report_mod.build(bench, fw.status(), duration_s, transport=transport, cfg=cfg)
    rep["wall_s"] = round(wall, 2)
    rep["speedup"] = round(duration_s / wall, 1) if wall > 0 else None
    return rep
