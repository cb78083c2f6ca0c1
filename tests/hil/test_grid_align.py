"""The wall-clock loop's grid moved onto the sample that completes a burst (``[timing] align_us``).

The loop (``tools.bench.realtime.firmware_loop``) reads after each tick when the firmware expects
the sample that completes the open burst (``Firmware.completing_sample_us``) and moves its next
slots, by at most ``align_slew_us`` a tick, so that a tick starts ``align_us`` after it. Pinned
here on an injected clock against hand-computed slots, and the firmware's hint against the
sample that then completes each burst on the in-process bench (virtual clock).
"""
from __future__ import annotations

import numpy as np
import pytest

from coiltrack.firmware.loop import Firmware
from coiltrack.firmware.measure.pulse import NO_TIME_US
from coiltrack.hil.clock import SimClock
from coiltrack.protocol.schema import STAMP_LSB_US
from coiltrack.tools import scenarios
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.realtime import firmware_loop, grid_shift
from coiltrack.tools.bench.runner import BenchSetup


@pytest.mark.parametrize("slot, want, shift", [
    (1000, 1300, 300),       # the grid's ticks lie 700 us after the wanted instant: 300 later is shorter
    (1000, 1700, -300),      # 300 us after it: 300 earlier
    (5000, 5000, 0),         # already on it
    (1000, 1500, -500),      # half a tick either way: earlier
    (3000, 123_456, 456),    # any slot of the grid counts, not only the next one
    (3000, -750, 250),       # instants before the slot too
])
def test_the_grid_moves_the_shorter_way_onto_the_wanted_instant(slot, want, shift):
    assert grid_shift(slot, want, 1000) == shift
    assert (slot + shift - want) % 1000 == 0


class _Hinting:
    """Each tick takes 10 us of the simulated clock; after the tick at ``at`` the firmware hints
    that the burst's completing sample comes at ``due`` (until then, and after it, no hint)."""

    def __init__(self, clock, at, due):
        self.clock, self.at, self.due, self.ticks = clock, at, due, []

    def tick(self, now):
        self.ticks.append(now)
        self.clock.now_us += 10

    def completing_sample_us(self):
        t = self.ticks[-1] if self.ticks else -1
        return self.due if self.at <= t < self.due else NO_TIME_US


def _run(fw, clock, **kw):
    return firmware_loop(fw, clock, 30_000, 1000, spin_us=0, **kw)


def test_a_tick_starts_align_us_after_the_hinted_sample_and_no_period_moves_more_than_the_slew():
    clock = SimClock(0)
    fw = _Hinting(clock, at=2000, due=9_840)       # wanted 9_840 + 300 = 10_140: 140 us later
    out = _run(fw, clock, align_us=300, slew_us=100)
    t = np.array(fw.ticks)
    assert 10_140 in fw.ticks
    assert fw.ticks[:3] == [0, 1000, 2000]           # nothing moves before the hint
    per = np.diff(t)
    assert per.min() == 1000 and per.max() == 1100   # 100 + 40: later, never more than the slew
    assert list(per).count(1100) == 1 and list(per).count(1040) == 1
    assert t[-1] % 1000 == 140                       # and the grid stays there
    assert out["tick_align_moves"] == 2 and out["tick_align_moved_us"] == 140
    assert out["deadline_misses"] == 0


def test_an_earlier_grid_shortens_periods_by_the_slew_at_most():
    clock = SimClock(0)
    fw = _Hinting(clock, at=1000, due=9_350)       # wanted 9_650: the grid 350 us earlier
    _run(fw, clock, align_us=300, slew_us=100)
    per = np.diff(fw.ticks)
    assert 9_650 in fw.ticks
    assert per.min() == 900 and sorted(set(per)) == [900, 950, 1000]


def test_without_a_hint_or_with_align_off_the_grid_stays():
    clock = SimClock(0)
    fw = _Hinting(clock, at=10**9, due=10**9 + 1)   # never hints
    out = _run(fw, clock, align_us=300, slew_us=100)
    assert all(t % 1000 == 0 for t in fw.ticks) and out["tick_align_moves"] == 0
    clock = SimClock(0)
    fw = _Hinting(clock, at=2000, due=9_840)
    out = _run(fw, clock, align_us=0, slew_us=100)
    assert all(t % 1000 == 0 for t in fw.ticks) and "tick_align_moves" not in out


def _hints_and_completions(name: str, seconds: float = 6.0):
    """The in-process bench on the virtual clock: each distinct hint the firmware gave, and for
    each burst the time of the sample that completed it (the first sensor's newest sample in the
    tick its last window closed)."""
    sc = scenarios.get(name)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, seconds + 1.0, emu_end)
    fw = Firmware(sc.firmware_config(), fw_end)
    ch = fw.channels[0]
    hints, done = [], []
    was = False
    t = 0
    while t < seconds * 1e6:
        bench.emulator.step(t)
        fw.tick(t)
        h = fw.completing_sample_us()
        if h != NO_TIME_US and (not hints or hints[-1] != h):
            hints.append(h)
        closed = bool(ch.done[-1])
        if closed and not was:
            done.append(ch.extractor._ring.latest_t_us)
        was = closed
        t += fw.cfg.timing.tick_us
    return hints, done


def test_the_hint_is_the_sample_that_then_completes_the_burst():
    """Every burst of roetenberg-bench (one sensor, 120 Hz) completes with the sample hinted one
    interval before, to the stamps' resolution: the prediction is the newest interval again, and
    the node's stamps step by ``STAMP_LSB_US`` (8 us), so the two differ by one step at most.
    Fails with the newest sample in place of the next (8.3 ms off), the threshold's side swapped
    (no hint, or one a sample early), or a hint outside the last window (more hints than bursts)."""
    hints, done = _hints_and_completions("roetenberg-bench")
    assert len(done) >= 8
    assert len(hints) == len(done)                   # one hint a burst: none between bursts
    err = np.abs(np.array(hints) - np.array(done))
    assert err.max() <= STAMP_LSB_US and np.count_nonzero(err == 0) >= len(done) // 2


def test_pipelines_without_pulse_windows_give_no_hint():
    hints, done = _hints_and_completions("raab-ac", seconds=2.0)
    assert hints == []
