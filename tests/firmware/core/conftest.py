"""Shared set-up of the compiled-core tests: a link that records the frames written (and fails
every ``fail_every``-th write), and a Python/compiled pair of transmitters on two such links."""
from __future__ import annotations

import pytest

from coiltrack.firmware import core
from coiltrack.firmware.transmit import Transmitter
from coiltrack.protocol import FrameDecoder


class RecordingPort:
    """A byte link keeping every frame written; every ``fail_every``-th write raises (a full link)."""

    def __init__(self, fail_every: int = 0):
        self.frames = []
        self.fail_every = fail_every
        self.n = 0

    def read(self) -> bytes:
        return b""

    def write(self, data: bytes) -> None:
        self.n += 1
        if self.fail_every and self.n % self.fail_every == 0:
            raise OSError("link full")
        self.frames.append(bytes(data))


@pytest.fixture
def transmitter_pair():
    """``make(fail_every=0) -> (ref, got)``: node 7's transmitters on the Python and the compiled core."""
    def make(fail_every: int = 0):
        ref = Transmitter(RecordingPort(fail_every), 7, 100_000, FrameDecoder(), core=core.PYTHON)
        got = Transmitter(RecordingPort(fail_every), 7, 100_000, FrameDecoder(), core=core.load("compiled"))
        assert (ref.core, got.core) == ("python", "compiled")
        return ref, got
    return make
