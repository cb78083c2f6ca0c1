"""The acquisition solved ahead (``[budget] solve_ahead``, track.magnetic: ``_ahead_start`` and
``_use_ahead`` without a warm start).

``roetenberg-bench``, seed 1, on the virtual clock at the default budget (27 field evaluations a
tick): the first burst's solve is an acquisition (Kuipers, the invariant fit, the grid, the
orientation: about 45 evaluations, two ticks of the budget). Solved ahead from the sensor's
hemisphere on the inputs the burst's own solve will have, its pose leaves in the tick the burst
completes, bit for bit the one solved in turn; one whose inputs changed, or begun from the other
kind of start (the sensor got a pose in between, or lost it), is not used; and a re-acquisition
after a lost track is the same on both cores.
"""
import numpy as np
import pytest

from coiltrack.firmware.track.magnetic import MagneticTracker

from .test_solve_ahead import late_currents, run_recorded, same_solves


def _run(ahead: bool, seconds: float, impl: str = "compiled", hook=None, patch=None):
    """:func:`run_recorded` at the default budget on the core ``impl``."""
    return run_recorded(ahead, seconds, budget=None, impl=impl, hook=hook, patch=patch)


@pytest.fixture(scope="module")
def without():
    return _run(False, 3.0)[1]


@pytest.mark.parametrize("impl", ["compiled", "python"])
def test_the_first_burst_is_acquired_ahead_and_leaves_in_the_completing_tick(without, impl):
    """On either core (the reference's paths, or ``AheadStart`` and ``HandOver``). Catches an
    acquisition not solved ahead (the first pose one tick or more after its burst completed, as
    before), one begun from another hemisphere (the tracked position's zeros) or on other inputs
    (not used: missed), and one whose pose is not the burst's own (not the same bits as with
    ``solve_ahead`` off)."""
    fw, rows = _run(True, 3.0, impl=impl)
    assert not without[0][3] and without[0][1] >= 1          # without: acquired in turn, a tick or more late
    assert same_solves(rows, without)
    assert rows[0][1] == 0 and rows[0][0] < without[0][0]
    assert all(r[1] == 0 for r in rows)
    c = fw.tracker.counters()
    assert c["ahead_used"] == c["ahead_solves"] == len(rows) and c["ahead_missed"] == 0


@pytest.mark.parametrize("impl", ["compiled", "python"])
def test_an_acquisition_ahead_on_other_inputs_is_not_used(without, impl):
    """The currents of every solve ahead off by 1 ppm (a driver's report come in late): the
    acquisition ahead is begun but not used, and the first burst is acquired in turn as without.
    Catches a cold result taken without comparing the burst's inputs (the warm comparison only)."""

    fw, rows = _run(True, 3.0, impl=impl, patch=late_currents)
    c = fw.tracker.counters()
    assert c["ahead_solves"] == len(rows) and c["ahead_used"] == 0 and c["ahead_missed"] == c["ahead_solves"]
    assert same_solves(rows, without)
    assert rows[0][1] >= 1


def _flip_before_completion(burst_no: int, have: bool, pose=None, at=None):
    """A hook: once the ``burst_no``-th burst (0-based) has been solved ahead for the sensor,
    before it completes (or at the tick ``at``), the sensor's ``have_pose`` set to ``have`` (and
    its position and rotation to ``pose``'s), as a pose or a lost track between the solve ahead
    and the turn; the tick it did so in ``state["at"]``."""
    state = {"at": None}

    def hook(tr, t):
        ah = tr._ahead[0]
        if state["at"] is not None or (t != at if at is not None else tr.cycles != burst_no or tr.burst.complete
                                        or not ah.done or ah.burst is None or ah.burst != tr.schedule.burst_start):
            return
        tp = tr.poses[tr.channels[0].node]
        tp.have_pose = have
        if pose is not None:
            np.copyto(tp.position, pose[0])
            np.copyto(tp.rotation, pose[1])
        state["at"] = t
    return hook, state


def test_a_solve_ahead_of_the_other_kind_of_start_is_not_used():
    """An acquisition ahead, then the sensor given a pose before its turn (warm); a warm solve
    ahead, then the track lost before the turn (cold): neither is used, each burst is solved in
    turn from its own start as with ``solve_ahead`` off and the same flip. Catches a take-over
    that does not check the kind of start the solve ahead began from."""
    pose = (np.array([0.30, 0.05, -0.02]), np.eye(3))
    for burst_no, have, warm in ((0, True, True), (2, False, False)):
        hook, state = _flip_before_completion(burst_no, have, pose if have else None)
        fw, rows = _run(True, 3.0, hook=hook)
        assert state["at"] is not None
        hook, _ = _flip_before_completion(burst_no, have, pose if have else None, at=state["at"])
        plain = _run(False, 3.0, hook=hook)[1]
        assert rows[burst_no][3] is warm
        assert same_solves(rows, plain)
        c = fw.tracker.counters()
        assert c["ahead_missed"] == 1 and c["ahead_used"] == c["ahead_solves"] - 1


def test_the_kind_of_start_is_compared_not_only_the_inputs():
    """The reference's take-over (``_use_ahead``) of a finished solve ahead whose copies equal the
    burst's inputs but whose record says it began from the other kind of start: not used.
    Catches a comparison of the arrays alone (the kind recorded but never read)."""
    fw, _ = _run(True, 0.0, impl="python")
    tr = fw.tracker
    ch = tr.channels[0]
    tp = tr.poses[ch.node]
    ah = tr._ahead[0]
    tr.schedule.burst_start = 5_000
    for warm in (False, True):
        tp.have_pose = warm
        np.copyto(tp.position, tp.hemisphere)           # the warm hemisphere equals the cold one
        ch.fill_sigma()
        assert tr.warm_start(ch, tp) is warm
        for dst, src in zip((ah.S, ah.sigma, ah.currents, ah.hemisphere, ah.warm_p, ah.warm_R),
                            (ch.S, ch.sigma, tr.currents, tp.position, tp.warm_p, tp.warm_R)):
            np.copyto(dst, src)
        ah.take(5_000)
        ah.finish()
        ah.began(not warm)
        tr._next = 0
        missed = tr.ahead_missed
        assert tr._use_ahead(ch, warm) is False and tr.ahead_missed == missed + 1
        ah.take(5_000)
        ah.finish()
        ah.began(warm)
        tr._next = 0
        assert tr._same[0][warm]()


def test_a_reacquisition_ahead_is_the_same_on_both_cores():
    """The track lost before the 4th burst (``have_pose`` False, as after a solution out of the
    working volume): its acquisition is solved ahead and taken over on the compiled core
    (``AheadStart``, ``HandOver``) as on the reference, the same poses bit for bit. Catches a
    compiled begin that skips the acquisition ahead or takes it from the tracked position, and
    a hand-over that does not release it or solves a missed one from the wrong start."""
    burst_no = 3
    out = []
    for impl in ("compiled", "python"):
        state = {"done": False}

        def hook(tr, t, state=state):
            if not state["done"] and tr.cycles == burst_no and tr._next < 0 and not tr.burst.complete:
                tr.poses[tr.channels[0].node].have_pose = False
                state["done"] = True
        fw, rows = _run(True, 3.0, impl=impl, hook=hook)
        out.append((fw.tracker, rows))
    (tc, rc), (tp_, rp) = out
    if tc._ahead_start.__func__ is not MagneticTracker._ahead_start_compiled:
        pytest.skip("the compiled core is not built here")
    assert tc._begin.__func__ is MagneticTracker._begin_handover and tc._ho_begin.__name__ == "begin"
    assert same_solves(rc, rp)
    assert not rc[burst_no][3] and rc[burst_no][1] == 0
    assert tc.counters() == tp_.counters() and tc.counters()["ahead_missed"] == 0
