"""Injected microsecond clocks for the bench.

``SimClock`` is advanced by the runner (deterministic, faster than real
time); ``WallClock`` reads CLOCK_MONOTONIC, which every process on the
machine shares, so two processes given the same epoch agree on time.
``NodeClock`` is a node's own oscillator: offset and drift against true time.
"""
from __future__ import annotations

import time


class SimClock:
    def __init__(self, start_us: int = 0):
        self.now_us = int(start_us)

    def now(self) -> int:
        return self.now_us

    def advance_to(self, t_us: int) -> None:
        if t_us < self.now_us:
            raise ValueError("simulated time cannot run backwards")
        self.now_us = int(t_us)


class WallClock:
    def __init__(self, epoch_ns: int | None = None):
        self.epoch_ns = time.monotonic_ns() if epoch_ns is None else int(epoch_ns)

    def now(self) -> int:
        return (time.monotonic_ns() - self.epoch_ns) // 1000


class NodeClock:
    """A node oscillator: ``local = true * (1 + drift_ppm*1e-6) + offset_us``.

    ``step_us`` can be added at run time to emulate a clock step fault.
    """

    def __init__(self, offset_us: int = 0, drift_ppm: float = 0.0):
        self.offset_us = int(offset_us)
        self.drift_ppm = float(drift_ppm)

    def local(self, true_us: int) -> int:
        return int(true_us + true_us * self.drift_ppm * 1e-6) + self.offset_us

    def true(self, local_us: int) -> int:
        return int(round((local_us - self.offset_us) / (1.0 + self.drift_ppm * 1e-6)))
