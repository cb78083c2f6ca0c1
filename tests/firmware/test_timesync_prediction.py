"""The master's prediction of a node's clock offset (``supervise.timesync``) against the closed form.

A node whose oscillator runs ``d`` ppm fast has the offset (node - master)
``o(t) = o0 + d t`` (``hil.clock.NodeClock``: ``local = true + d t + o0``), so
from a reply at ``t1`` (offset ``o(t1)``, drift ``d``) the next one at ``t2``
is predicted ``o(t1) + d (t2 - t1)`` (the module's docstring). A quartz
oscillator is specified to 20-100 ppm; the bus form carries drifts up to 131
ppm (``protocol.busform``). Between broadcasts a quarter of a second apart the
drift moves the offset by at most 33 us, far under the step threshold (1.5
ms), so a prediction with the drift's sign flipped (``o - d dt``) goes
unnoticed there. A node heard only every 20 s (broadcasts lost, a node busy,
a quiet bus) moves 2.4 ms between replies at 120 ppm: the prediction must
carry the drift, in the right direction, or a steady clock is reported as
stepping (flipped sign: 4.8 ms off, three times the threshold; dropped term:
2.4 ms off).

No wall clock: reply times and offsets are given.
"""
from __future__ import annotations

import pytest

from coiltrack.firmware.supervise.timesync import _ACQUIRE, TimeSyncMaster
from coiltrack.protocol import MSG

NODE = 16
THRESHOLD_US = 1500
GAP_US = 20_000_000          # one reply every 20 s
OFFSET0_US = 3_544_628
#: the prediction's tolerance against the closed form: the reported offset is rounded to 1 us and
#: the master's drift term is floored to 1 us
TOL_US = 2

Reply = MSG["TIME_SYNC_REPLY"]


def _truth(t_us: int, drift_ppb: int) -> int:
    """The node's offset at master time ``t_us`` (closed form, rounded as a node reports it)."""
    return OFFSET0_US + round(drift_ppb * t_us / 1e9)


def _acquired(drift_ppb: int, replies: int):
    """A master that has booked ``replies`` replies of a steady node, one every ``GAP_US``; returns
    the master, the time of the last reply and whether any of them was judged a step."""
    m = TimeSyncMaster((NODE,), step_threshold_us=THRESHOLD_US)
    stepped = False
    t = 0
    for k in range(replies):
        t = 1_000 + k * GAP_US
        stepped |= m.on_reply(Reply(NODE, k, t + _truth(t, drift_ppb), _truth(t, drift_ppb), drift_ppb), t)
    return m, t, stepped


@pytest.mark.parametrize("drift_ppm", [120, -120, 50, -50])
def test_a_steady_drifting_clock_heard_rarely_is_not_a_step(drift_ppm):
    """Replies every 20 s from a clock at +-50 and +-120 ppm (1.0 and 2.4 ms of drift between
    replies, beside the 1.5 ms threshold): after acquisition none is judged a step. At 120 ppm the
    drift's sign flipped puts the prediction 4.8 ms off and the drift dropped 2.4 ms; at 50 ppm
    the flipped sign is 2.0 ms off."""
    drift_ppb = drift_ppm * 1000
    m, _, stepped = _acquired(drift_ppb, _ACQUIRE + 6)
    assert not stepped and m.steps[0] == 0, m.steps
    assert m.replies[0] == _ACQUIRE + 6


@pytest.mark.parametrize("drift_ppm", [120, -120])
@pytest.mark.parametrize("sign", [1, -1])
def test_predicted_offset_matches_the_closed_form(drift_ppm, sign):
    """The prediction's error against ``o(t1) + d (t2 - t1)``, read through the step test: a reply
    whose offset is the closed form plus ``s`` is a step exactly when ``|s - e| > threshold``,
    ``e`` the prediction's error. Steps of ``threshold - TOL`` (either sign) are taken as steady
    and steps of ``threshold + TOL`` are reported, so ``|e| <= TOL`` = 2 us (the integer
    rounding), against the 2.4 ms the drift moves the offset over the 20 s gap."""
    drift_ppb = drift_ppm * 1000
    for s, expected in ((THRESHOLD_US - TOL_US, False), (THRESHOLD_US + TOL_US, True)):
        m, t, stepped = _acquired(drift_ppb, _ACQUIRE + 1)
        assert not stepped
        t2 = t + GAP_US
        off = _truth(t2, drift_ppb) + sign * s
        got = m.on_reply(Reply(NODE, _ACQUIRE + 1, t2 + off, off, drift_ppb), t2)
        assert got is expected, (s * sign, drift_ppm)
        assert m.steps[0] == int(expected)


def test_a_real_step_on_a_drifting_clock_is_reported_once():
    """A 3 ms step of the counter on a 120 ppm clock heard every 20 s: the reply after the step is
    judged a step, the next (steady from the stepped offset) is not."""
    drift_ppb = 120_000
    m, t, _ = _acquired(drift_ppb, _ACQUIRE + 1)
    flags = []
    for k in range(1, 4):
        tk = t + k * GAP_US
        off = _truth(tk, drift_ppb) + 3_000
        flags.append(m.on_reply(Reply(NODE, _ACQUIRE + k, tk + off, off, drift_ppb), tk))
    assert flags == [True, False, False]
    assert m.steps[0] == 1
