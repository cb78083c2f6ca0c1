"""Solving ahead for many sensors (firmware_py/core/src/ahead.c, py_ahead.c) against its Python
reference, ``MagneticTracker._ahead_scan``.

* ``ext.AheadScan`` on multi16's sixteen sensors in random states (windows closed or not, a window
  before the last missing, a sensor whose solve ahead is already given its turn, fusion filters
  running or not, rings of 0, 1 or many samples, marks equal to the channel's changes or not):
  the same answer and, bit for bit, the same turns and marks as the reference on a copy of the state.
* A hand-made case checked against its expected answer (independent of both): the first sensor
  missing a window, the second already had its turn, the third's next sample expected exactly at
  the window's end (not complete), the fourth's one microsecond after it (complete).
* A time beyond the kernel's range is answered by the reference.
Seeded; skipped without the extension."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.estimate.magnetic_inertial import FS_INIT
from coiltrack.firmware.loop import Firmware
from coiltrack.firmware.track.magnetic import AHEAD_NONE, AHEAD_SEEN, NO_BURST, MagneticTracker
from coiltrack.tools import scenarios

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")


class _NullPort:
    def read(self) -> bytes:
        return b""

    def write(self, data: bytes) -> None:
        pass


@pytest.fixture(scope="module")
def tracker():
    cfg = scenarios.get("multi16").firmware_config().with_(core={"impl": "compiled"}).validate()
    tr = Firmware(cfg, _NullPort()).tracker
    assert tr._ahead_scan.__func__ is MagneticTracker._ahead_scan_compiled
    return tr


def _arrays(tr):
    out = [tr._ahead_st, tr._ahead_idle]
    for ch in tr.channels:
        ring = ch.extractor._ring
        out += [ch.done, ch.cnt, ring.t, ring.hc, tr.inertial[ch.node].fusion.fs]
    return out


def _fill_ring(ring, rng, t_end):
    """A fresh ring with 0, 1 or several samples ending near ``t_end`` at a random interval."""
    ring.hc[:] = 0
    ring.t[:] = 0
    ring.hc[2] = -(1 << 62)
    n = int(rng.choice([0, 1, 2, 5, ring.capacity + 3]))
    dt = int(rng.integers(1, 20))
    t0 = t_end - dt * n + int(rng.integers(-2 * dt, 2 * dt + 1))
    for i in range(n):
        ring.push(t0 + i * dt, 0.0, 0.0, 0.0, False, 0)


def _randomize(tr, rng, burst, j, end):
    n = tr._ahead_st.shape[0]
    had = float(rng.choice([0.2, 0.97]))             # some states with nearly every turn had
    for k, ch in enumerate(tr.channels):
        ch.done[:] = rng.random(ch.done.shape[0]) < 0.8
        if rng.random() < 0.5:
            ch.done[:j] = True
        ch.cnt[1] = int(rng.integers(0, 50))
        tr.inertial[ch.node].fusion.fs[FS_INIT] = int(rng.random() < (0.3 if had < 0.5 else 0.6))
        _fill_ring(ch.extractor._ring, rng, end + int(ch.extractor._fall_us + ch.extractor._baseline_us))
        r = rng.random()
        tr._ahead_st[k] = (burst if r < had else NO_BURST if r < had + (1 - had) / 2 else burst - 1000,
                           int(rng.integers(0, 2)))
        r = rng.random()
        tr._ahead_idle[k] = ch.cnt[1] if r < 0.3 else -1 if r < 0.6 else int(rng.integers(0, 50))
    assert n == 16


def test_the_scan_equals_the_reference_on_random_states(tracker):
    """400 random states of sixteen sensors: the compiled scan's answer, turns and marks equal the
    reference's bit for bit. Catches a test dropped or reordered (a not-wanted sensor counted as
    unseen, the marks not set on a missing window), the ring's previous sample taken at the wrong
    slot, ``>=`` for ``>``, a write into the next sensor's turn."""
    tr = tracker
    rng = np.random.default_rng(3030)
    answers = set()
    for _ in range(400):
        burst = int(rng.integers(0, 1 << 40))
        j = int(rng.integers(0, tr.channels[0].done.shape[0]))
        start = int(rng.integers(0, 1 << 40))
        end = start + int(rng.integers(100, 5000))
        _randomize(tr, rng, burst, j, end)
        before = [a.copy() for a in _arrays(tr)]
        ref = MagneticTracker._ahead_scan(tr, burst, j, start, end)
        ref_state = [a.copy() for a in _arrays(tr)]
        for a, b in zip(_arrays(tr), before):
            a[...] = b
        got = tr._ahead_scan(burst, j, start, end)
        assert got == ref
        for a, b in zip(_arrays(tr), ref_state):
            assert np.array_equal(a, b)
        answers.add(ref if ref < 0 else "channel")
    assert answers == {AHEAD_NONE, AHEAD_SEEN, "channel"}


def _hand_made(tr):
    """Sensors 0-3 wanted; 4-15 with a running fusion filter (not wanted). Window [1000, 2000] of
    coil 2, fall + baseline = extra."""
    extra = int(tr.channels[0].extractor._fall_us + tr.channels[0].extractor._baseline_us)
    burst, j, start, end = 500, 2, 1000, 2000
    tr._ahead_st[:] = (NO_BURST, 0)
    tr._ahead_idle[:] = -1
    for k, ch in enumerate(tr.channels):
        ch.done[:] = False
        ch.done[:j] = True
        ch.cnt[1] = 7
        tr.inertial[ch.node].fusion.fs[FS_INIT] = 0 if k < 4 else 1
        ring = ch.extractor._ring
        ring.hc[:] = 0
        ring.hc[2] = -(1 << 62)
    tr.channels[0].done[1] = False                  # a window before the last missing
    tr._ahead_st[1] = (burst, 1)                     # already had its turn (its solve ahead done)
    for k, newest in ((2, end + extra), (3, end + extra + 1)):
        ring = tr.channels[k].extractor._ring
        ring.push(newest - 10, 0.0, 0.0, 0.0, False, 0)
        ring.push(newest - 5, 0.0, 0.0, 0.0, False, 0)
        ring.push(newest, 0.0, 0.0, 0.0, False, 0)   # the next expected at newest + 5
    # sensor 2: next at end + extra + 5 > end + extra: complete. Make it exactly end + extra:
    ring = tr.channels[2].extractor._ring
    ring.hc[:] = 0
    ring.hc[2] = -(1 << 62)
    ring.push(end + extra - 10, 0.0, 0.0, 0.0, False, 0)
    ring.push(end + extra - 5, 0.0, 0.0, 0.0, False, 0)
    return burst, j, start, end


@pytest.mark.parametrize("compiled", [False, True])
def test_a_hand_made_scan(tracker, compiled):
    """Sensor 0 misses window 1, sensor 1 has had its turn, sensor 2's next sample is expected at
    exactly end + fall + baseline (the window reads it: not complete), sensor 3's after it: sensor
    3 is given its turn; 0 and 2 are marked with their changes; 4-15 (fusion running) are given
    their turns only by a scan that reaches them. A second scan, with sensor 3 then done, finds
    every wanted sensor marked or had: none; once 0 and 2 are marked, AHEAD_NONE stays until their
    changes move."""
    tr = tracker
    scan = tr._ahead_scan if compiled else (lambda *a: MagneticTracker._ahead_scan(tr, *a))
    burst, j, start, end = _hand_made(tr)
    assert scan(burst, j, start, end) == 3
    assert list(tr._ahead_st[3]) == [burst, 0] and list(tr._ahead_st[1]) == [burst, 1]
    assert tr._ahead_idle[0] == 7 and tr._ahead_idle[2] == 7 and tr._ahead_idle[1] == -1
    assert all(tr._ahead_st[k, 0] == NO_BURST for k in range(4, 16))
    assert scan(burst, j, start, end) == AHEAD_NONE             # 0, 2 marked; 4-15 had their turns now
    assert all(tr._ahead_st[k, 0] == burst for k in range(4, 16))
    tr._ahead_st[0] = tr._ahead_st[2] = (burst, 0)
    assert scan(burst, j, start, end) == AHEAD_SEEN


def test_a_time_beyond_the_kernels_range_is_answered_by_the_reference(tracker):
    """A window ending at 2^62 us: the kernel asks, the reference answers (the same as it gives)."""
    tr = tracker
    burst, j, start, end = _hand_made(tr)
    big = 1 << 62
    before = [a.copy() for a in _arrays(tr)]
    ref = MagneticTracker._ahead_scan(tr, burst, j, big, big + 1000)
    for a, b in zip(_arrays(tr), before):
        a[...] = b
    assert tr._scan_k(burst, j, big, big + 1000) == -3
    for a, b in zip(_arrays(tr), before):
        a[...] = b
    assert tr._ahead_scan(burst, j, big, big + 1000) == ref
