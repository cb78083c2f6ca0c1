"""Fixtures for the protocol tests: the emulator's real nodes (hil.nodes,
hil.emulator, hil.world) run on the wall clock in a thread on any byte link
(pty master, CanLink), so the conformance suite talks to them exactly as it
would to a board."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from coiltrack.hil.emulator import Emulator
from coiltrack.hil.nodes import CoilDriverNode, DriverLimits, Recorder, SensorNode
from coiltrack.protocol.schema import NODE_COIL_DRIVER, NODE_SENSOR_BASE


def make_world():
    """The thesis source and a sensor at rest 25 cm away (hil's own physics)."""
    from coiltrack.hil import motion, physics
    from coiltrack.hil.world import World

    return World(physics.thesis_source(), motion.StaticPose(np.array([0.25, 0.05, -0.04]), np.eye(3)))


class EmulatorThread:
    """An Emulator (coil driver + one sensor) stepping on the wall clock."""

    def __init__(self, link, verifier=None, limits: DriverLimits | None = None, rate_hz: float = 120.0,
                 step_s: float = 0.0005, seed: int = 3, sensor_cls=SensorNode):
        self.world = make_world()
        self.link = link
        self.driver = CoilDriverNode(NODE_COIL_DRIVER, self.world, limits=limits, seed=seed)
        self.sensor = sensor_cls(NODE_SENSOR_BASE, self.world, rate_hz=rate_hz, seed=seed + 1)
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
            self._thread = None
        if self.error is not None:
            err, self.error = self.error, None
            raise err

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


class Lockstep:
    """Injected time for a conformance run on an in-process link: the tester's
    ``sleep`` advances a simulated clock and steps the emulator (not started
    as a thread) to it, so what happens does not depend on the machine's
    speed. ``now`` and ``sleep`` are the tester's clock and sleep; without an
    emulator the clock just advances (a scripted node answers on every read)."""

    def __init__(self, emu: EmulatorThread | None = None, step_s: float = 0.0005):
        self.emu = emu
        self.step_s = step_s
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        end = self.t + max(seconds, 0.0)
        while True:
            self.t = min(self.t + self.step_s, end)
            if self.emu is not None:
                self.emu.emulator.step(int(round(self.t * 1e6)))
            if self.t >= end:
                return


@pytest.fixture
def sim_clock():
    """A :class:`Lockstep` without an emulator: injected time for scripted nodes."""
    return Lockstep()


@pytest.fixture
def lockstep():
    """``lockstep(link, **emulator_kw)`` -> a :class:`Lockstep` with the emulator on ``link``."""
    return lambda link, **kw: Lockstep(EmulatorThread(link, **kw))


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


class PipeEnd:
    """One end of an in-memory full-duplex byte pipe (simulated clock tests)."""

    def __init__(self, rx: bytearray, tx: bytearray):
        self._rx, self._tx = rx, tx

    def read(self) -> bytes:
        data = bytes(self._rx)
        self._rx.clear()
        return data

    def write(self, data: bytes) -> None:
        self._tx += data


def pipe_pair() -> tuple[PipeEnd, PipeEnd]:
    a, b = bytearray(), bytearray()
    return PipeEnd(b, a), PipeEnd(a, b)


#: pulse command lead of conformance runs against a node on the wall clock (ms)
WALL_LEAD_MS = 200.0

#: fast settings for conformance runs in tests (a full run takes 1-2 s)
FAST = dict(observe_s=0.4, discover_s=0.4, lead_ms=50.0, pulse_ms=10.0, silence_s=0.12, optional_wait_s=0.1,
            answer_timeout_s=0.3, sync_period_s=1.0, grid_observe_s=0.6)


@pytest.fixture
def pipes():
    """``pipes()`` -> two connected in-memory byte Ports."""
    return pipe_pair


@pytest.fixture
def world_factory():
    """``world_factory()`` -> a fresh hil World (thesis source, static sensor)."""
    return make_world


@pytest.fixture
def fast():
    """Fast ConformOptions keyword arguments for tests."""
    return dict(FAST)


@pytest.fixture
def wall():
    """FAST for runs against a node on the wall clock (a thread or a process):
    an answer may take as long as the machine needs (the wait ends when it
    comes), and pulses are commanded 200 ms ahead, so that a command held up
    by a loaded machine still arrives before its start: a loaded machine
    makes the run slower, not failed."""
    return dict(FAST, answer_timeout_s=5.0, lead_ms=WALL_LEAD_MS)
