"""The burst's MAG_FLIP_CMDs sent a few a tick (``FlipScheduler.plan`` with ``per_tick``, then
``step``): the very commands the all-at-once plan sends (the same sensors in the same order, the
same time, the states of the plan's moment even when samples change them meanwhile), none lost
or sent twice, and a new plan sends what still waits first. Catches a state read at send time,
an off-by-one at the tick's end, a command dropped when a plan comes early."""
from coiltrack.firmware.supervise.flips import FlipScheduler

SENSORS = tuple(range(16, 32))


def _run(per_tick, plans, observe_between=True):
    f = FlipScheduler(SENSORS, min_gap_us=10_000)
    sent, ticks = [], []
    for k, (now, q0, q1) in enumerate(plans):
        f.plan(now, q0, q1, sent.append, lambda n, a, s: sent.append((n, a, s)), per_tick)
        ticks.append(len(sent))
        for _ in range(k + 1):                              # the next ticks (a plan may come early)
            if observe_between:
                for n in SENSORS[::3]:
                    f.observe(n, 0)                         # samples report a state meanwhile
            if f.pending:
                f.step(sent.append, lambda n, a, s: sent.append((n, a, s)), per_tick)
            ticks.append(len(sent))
    while f.pending:                                        # the ticks after the last plan
        f.step(sent.append, lambda n, a, s: sent.append((n, a, s)), per_tick)
        ticks.append(len(sent))
    return sent, ticks, f


def test_spread_commands_are_the_all_at_once_commands():
    plans = [(1000, 50_000, 90_000), (100_000, 150_000, 155_000), (200_000, 250_000, 400_000),
             (201_000, 260_000, 300_000)]
    once, once_ticks, f0 = _run(0, plans)
    for per_tick in (1, 3, 4, 5, 16, 40):
        spread, ticks, f = _run(per_tick, plans)
        assert spread == once
        assert f.sent == f0.sent == len(once) and f.pending == 0 and f.flips_planned == f0.flips_planned
        steps = [b - a for a, b in zip([0] + ticks, ticks)]
        assert max(steps) <= max(per_tick, 16)
    # a flip when the gap allows it: the middle of the gap; a short gap repeats the state at once
    assert once[0] == (16, 70_000, 0) and once[16] == (16, 100_000, 0)


def test_states_are_the_plans():
    f = FlipScheduler(SENSORS)
    out = []
    f.plan(0, 20_000, 60_000, None, lambda n, a, s: out.append(s), per_tick=2)
    for n in SENSORS:
        f.observe(n, 0)
    while f.pending:
        f.step(None, lambda n, a, s: out.append(s), 2)
    assert out == [0] * 16                          # every sensor was in state 1: all flip to 0
