"""Node clocks (offset, drift, steps, reboot) and the node-side time sync."""
from __future__ import annotations

import numpy as np
import pytest

from coiltrack.hil.clock import NodeClock, NodeSync, SimClock


def test_node_clock_drift_and_offset():
    c = NodeClock(offset_us=1_000_000, drift_ppm=100.0)
    assert c.local(0) == 1_000_000
    assert c.local(10_000_000) == 1_000_000 + 10_000_000 + 1_000      # 100 ppm of 10 s = 1 ms
    for t in (0, 123_457, 10_000_000, 59_999_999):
        assert c.true(c.local(t)) == t


def test_node_clock_true_is_first_instant_reaching_local():
    c = NodeClock(offset_us=-5, drift_ppm=-73.0)
    for loc in range(1000, 200_000, 997):
        t = c.true(loc)
        assert c.local(t) >= loc and c.local(t - 1) < loc


def test_clock_steps_forward_and_back():
    c = NodeClock(offset_us=0, drift_ppm=0.0)
    c.add_step(1_000_000, 5_000)
    c.add_step(2_000_000, -3_000)
    assert c.local(999_999) == 999_999
    assert c.local(1_000_000) == 1_005_000
    assert c.local(2_000_000) == 2_002_000
    # a timer armed for a local time the forward step jumps over fires at the step
    assert c.true(1_002_000, after_us=500_000) == 1_000_000
    # after the backward step the counter repeats local times: the timer fires at the first instant after
    assert c.true(2_001_000, after_us=2_000_000) == 2_000_000
    assert c.true(2_003_000, after_us=2_000_000) == 2_001_000
    with pytest.raises(ValueError):
        c.add_step(1_500_000, 1)


def test_reboot_before_a_scheduled_step_keeps_the_step_a_jump():
    """A clock step scheduled at 20 s and a reboot at 10 s (a fault schedule with a
    node outage before a clock step): the counter restarts at 10 s and still jumps
    by +5 ms at 20 s. Catches the bench refusing the reboot (a soak schedule with
    both crashed the bench at the reboot)."""
    c = NodeClock(offset_us=1_000, drift_ppm=0.0)
    c.add_step(20_000_000, 5_000)
    c.reboot(10_000_000, start_local_us=2_000)
    assert c.local(10_000_000) == 2_000
    assert c.local(19_999_999) == 2_000 + 9_999_999
    assert c.local(20_000_000) == 2_000 + 10_000_000 + 5_000


def test_reboot_restarts_counter():
    c = NodeClock(offset_us=3_000_000, drift_ppm=20.0)
    c.reboot(10_000_000, start_local_us=1_234)
    assert c.local(10_000_000) == 1_234
    assert c.local(11_000_000) == pytest.approx(1_234 + 1_000_020, abs=1)


def _run_sync(clock: NodeClock, period_us: int, n: int, jitter_us: float = 0.0, seed: int = 0, latency_us: int = 0):
    rng = np.random.default_rng(seed)
    s = NodeSync()
    for k in range(n):
        t = k * period_us                      # master = true here
        rx = t + latency_us + int(abs(rng.normal(0.0, jitter_us))) if jitter_us else t + latency_us
        s.update(clock.local(rx), t)
    return s


def test_sync_learns_offset_and_drift_exactly_without_jitter():
    clock = NodeClock(offset_us=2_345_678, drift_ppm=87.0)
    s = _run_sync(clock, 250_000, 40)
    assert s.drift_ppb == pytest.approx(87_000, abs=100)
    # master time of any local instant within the next second: error < 2 us
    for t in range(10_000_000, 11_000_000, 50_000):
        assert abs(s.to_master(clock.local(t)) - t) <= 2
        assert abs(clock.true(s.to_local(t)) - t) <= 2


def test_sync_under_reception_jitter():
    """200 us rms one-sided reception jitter: offset within ~150 us, drift within 50 ppm, and no
    wild drift from a short span (the drift is only fitted once the points span 1 s)."""
    clock = NodeClock(offset_us=-40_000, drift_ppm=-95.0)
    early = _run_sync(clock, 250_000, 3, jitter_us=200.0, seed=1)
    assert early.drift_ppb == 0
    s = _run_sync(clock, 250_000, 60, jitter_us=200.0, seed=1)
    assert abs(s.drift_ppb - (-95_000)) < 50_000
    t = 60 * 250_000
    assert abs(s.to_master(clock.local(t)) - t) < 400
    assert s.steps == 0


def test_forward_step_needs_three_agreeing_broadcasts():
    """A forward step of the node's clock looks like late frames: taken when three broadcasts agree."""
    clock = NodeClock(offset_us=0, drift_ppm=30.0)
    clock.add_step(5_100_000, 5_000)
    s = NodeSync()
    steps = []
    for k in range(40):
        t = k * 250_000
        steps.append(s.update(clock.local(t), t))
    # broadcasts at 5.25 and 5.5 s are held, the one at 5.75 s confirms
    assert steps.count(True) == 1 and steps.index(True) == 23
    assert s.steps == 1 and s.rejected == 2
    assert abs(s.to_master(clock.local(10_000_000)) - 10_000_000) <= 3


def test_backward_step_is_taken_at_once():
    """A broadcast cannot arrive early: one that does means the clock stepped back."""
    clock = NodeClock(offset_us=0, drift_ppm=-20.0)
    clock.add_step(5_100_000, -4_000)
    s = NodeSync()
    steps = [s.update(clock.local(k * 250_000), k * 250_000) for k in range(40)]
    assert steps.count(True) == 1 and steps.index(True) == 21
    assert abs(s.to_master(clock.local(6_000_000)) - 6_000_000) <= 3


def test_sync_ignores_late_and_stale_broadcasts():
    """Late broadcasts (one 20 ms late; two 4-5 ms late in a row, as a stalled link delivers them)
    are not steps; a stale one (older master time) is ignored; the estimate is untouched."""
    clock = NodeClock(offset_us=777, drift_ppm=-40.0)
    s = NodeSync()
    late = {12: 20_000, 15: 4_000, 16: 5_000}
    for k in range(20):
        t = k * 250_000
        assert not s.update(clock.local(t + late.get(k, 0)), t)
    assert not s.update(clock.local(5_000_000), 4_000_000)          # stale
    assert s.steps == 0 and s.rejected == 4
    assert abs(s.to_master(clock.local(5_000_000)) - 5_000_000) <= 3


def test_acquisition_follows_the_lower_envelope():
    """The first broadcast arrived 5 ms late (the node was busy starting): the next ones, on time,
    move the line down without counting a step."""
    clock = NodeClock(offset_us=123_456, drift_ppm=10.0)
    s = NodeSync()
    for k in range(10):
        t = k * 250_000
        assert not s.update(clock.local(t + (5_000 if k == 0 else 0)), t)
    assert s.steps == 0
    assert abs(s.to_master(clock.local(2_500_000)) - 2_500_000) <= 2


def test_unsynced_maps_identity_and_simclock():
    s = NodeSync()
    assert not s.synced and s.to_master(123) == 123 and s.to_local(456) == 456
    c = SimClock(10)
    c.sleep(0.000_5)
    assert c.now() == 510
    with pytest.raises(ValueError):
        c.advance_to(0)
