"""Pulse windows are closed a budget at a time (``[budget] windows_budget``).

With sixteen sensors every pulse's sixteen windows are ready in the same tick; closing them all
there made one tick 1.2 ms long (``coiltrack perf --scenario multi16``: measure max 1215 us).
"""
import numpy as np

from coiltrack.firmware.measure.burst import BurstMeasurement


class _Schedule:
    n = 3

    def __init__(self):
        self.burst_start = 0
        self.commanded = 3
        self.start = np.array([0, 100, 200])
        self.end = np.array([60, 160, 260])
        self.pulse_id = np.array([7, 8, 9])


class _Channel:
    def __init__(self):
        self.done = [False, False, False]


class _Closer:
    """Every window ready; closing one marks it done and counts it."""

    def __init__(self):
        self.closed = []

    def ready(self, start, end, now_us):
        return True

    def ready_upto(self, start, end, now_us, first):
        return 1 << 20

    def close_one(self, ch, coil, pulse_id, start, end):
        ch.done[coil] = True
        self.closed.append((id(ch), coil, pulse_id))
        return 0


def test_sixteen_channels_close_four_windows_a_tick():
    """48 ready windows, budget 4: 4 per tick, the burst complete in the 12th tick and not before,
    each window closed once. Catches a budget that is ignored, a burst declared complete with
    windows still open (its amplitudes then missing), and a window closed twice."""
    chans = [_Channel() for _ in range(16)]
    closer = _Closer()
    m = BurstMeasurement(chans, _Schedule(), closer, budget=4)
    per_tick = []
    for tick in range(12):
        before = len(closer.closed)
        assert not m.complete
        m.step(1000 + tick)
        per_tick.append(len(closer.closed) - before)
    assert per_tick == [4] * 12
    assert m.complete
    assert len(set(closer.closed)) == 48
    m.step(2000)
    assert len(closer.closed) == 48


def test_default_budget_closes_everything_at_once():
    """Without a budget the measurement closes every ready window in one tick (the old behaviour)."""
    chans = [_Channel() for _ in range(2)]
    closer = _Closer()
    m = BurstMeasurement(chans, _Schedule(), closer)
    m.step(1000)
    assert len(closer.closed) == 6 and m.complete
