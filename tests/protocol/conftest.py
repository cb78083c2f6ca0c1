"""Fixtures for the protocol tests: the emulator's real nodes (hil.nodes,
hil.emulator) on a small analytic world, run on the wall clock in a thread
on any byte link (pty master, CanLink), so the conformance suite can talk to
them exactly as it would to a board."""
from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from hil.emulator import Emulator
from hil.nodes import CoilDriverNode, DriverLimits, Recorder, SensorNode
from protocol.schema import NODE_COIL_DRIVER, NODE_SENSOR_BASE


class StubCurrent:
    """First-order (L/R) coil current: rises and falls with time constant tau."""

    def __init__(self, tau_us: float = 500.0):
        self.tau_us = tau_us
        self.pulses: list[tuple[int, int, float]] = []

    def schedule(self, start_us: int, duration_us: int, amps: float) -> None:
        self.pulses.append((start_us, duration_us, amps))
        del self.pulses[:-32]

    def current_at(self, t_us: int) -> float:
        i = 0.0
        for s, d, a in self.pulses:
            if t_us < s:
                continue
            on = min(t_us, s + d) - s
            v = a * (1.0 - math.exp(-on / self.tau_us))
            if t_us > s + d:
                v *= math.exp(-(t_us - s - d) / self.tau_us)
            i += v
        return i


class StubWorld:
    """Three coils, a constant earth field and fixed unit fields."""

    def __init__(self):
        self.coils = [0, 1, 2]
        self.currents = [StubCurrent() for _ in self.coils]
        self.earth = np.array([18e-6, 2e-6, -45e-6])
        self.unit = np.array([[4e-6, 1e-6, 0.5e-6], [1e-6, 3e-6, 0.2e-6], [0.3e-6, 0.1e-6, 5e-6]])

    def pose(self, t_us):
        return np.zeros(3), np.eye(3)

    def field_sensor_frame(self, t_us: int) -> np.ndarray:
        I = np.array([c.current_at(t_us) for c in self.currents])
        return self.earth + I @ self.unit


class EmulatorThread:
    """An Emulator (coil driver + one sensor) stepping on the wall clock."""

    def __init__(self, link, verifier=None, limits: DriverLimits | None = None, rate_hz: float = 120.0,
                 step_s: float = 0.0005, seed: int = 3):
        self.world = StubWorld()
        self.link = link
        self.driver = CoilDriverNode(NODE_COIL_DRIVER, self.world, limits=limits, seed=seed)
        self.sensor = SensorNode(NODE_SENSOR_BASE, self.world, rate_hz=rate_hz, seed=seed + 1)
        self.recorder = Recorder(self.world)
        self.emulator = Emulator(self.world, link, self.driver, [self.sensor], self.recorder, verifier=verifier)
        self.step_s = step_s
        self._stop = threading.Event()
        self._thread = None
        self.error: BaseException | None = None
        self.epoch_ns = time.monotonic_ns()

    def now_us(self) -> int:
        return (time.monotonic_ns() - self.epoch_ns) // 1000

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                self.emulator.step(self.now_us())
                flush = getattr(self.link, "flush", None)
                if flush is not None:
                    flush()
                time.sleep(self.step_s)
        except BaseException as exc:  # surfaced by stop()
            self.error = exc

    def start(self) -> "EmulatorThread":
        self.epoch_ns = time.monotonic_ns()
        self._thread = threading.Thread(target=self._run, name="emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self.error is not None:
            raise self.error

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


@pytest.fixture
def emulator_factory():
    started = []

    def make(link, **kw) -> EmulatorThread:
        e = EmulatorThread(link, **kw).start()
        started.append(e)
        return e

    yield make
    for e in started:
        e.stop()
