"""The heaviest pieces of work of a tick are never stacked in one tick.

* Fused tracker (``track.burst_fusion``): a tick that propagates IMU samples (the fused tick:
  orientation filter, strapdown, covariance prediction, a POSE) leaves the fusion step (the
  update, a replay step) to the next tick, at most one tick in a row.
* Adaptive single-coil mode (``track.single_coil_tracker``): a tick that has run an EKF update
  leaves the pulse decision (a covariance prediction per sensor and pulse in flight, the coil
  choice) to the next tick, which commands the pulse for the start the first tick found.

Both are checked tick by tick on short bench runs (seeded, virtual clock).
"""
from coiltrack.firmware.loop import Firmware
from coiltrack.tools import scenarios
from coiltrack.tools.links import inproc_pair
from coiltrack.tools.runner import BenchSetup

WARMUP_US = 2_000_000


def _run(name: str, seed: int, run_us: int, on_tick):
    sc = scenarios.get(name)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, seed, run_us * 1e-6 + 1.0, emu_end)
    cfg = sc.firmware_config()
    fw = Firmware(cfg, fw_end)
    t = 0
    while t < run_us:
        bench.emulator.step(t)
        on_tick(fw, t, True)
        fw.tick(t)
        on_tick(fw, t, False)
        t += cfg.tick_us
    return fw


def test_fused_ticks_leave_the_fusion_steps_to_the_next_tick():
    """``roetenberg-fusion``, 6 s: no tick that propagated IMU samples applies a fusion update
    or replays IMU steps on the shadow state unless the tick before it was put off too (the
    work must go on); fusion updates and fused poses are still made. Catches the check dropped
    (a fused tick carrying an 8-step replay), an inverted condition (the work only on fused
    ticks) and work put off forever (no fusion update at all)."""
    rows = []
    state = {}

    def on_tick(fw, t, before):
        tr = fw.tracker
        ins = next(iter(tr.inertial.values()))
        fus = ins.fusion
        key = (ins.samples, tr.solver.signal.evals + tr.comp_solver.signal.evals, fus.steps, fus.updates)
        if before:
            state["k"] = key
            state["deferred"] = tr.deferred
            return
        k0 = state["k"]
        imu = key[0] - k0[0]
        evals = key[1] - k0[1]
        replay_steps = (key[2] - k0[2]) - imu          # strapdown steps beyond the live state's own
        rows.append((t, imu, evals, replay_steps, tr.deferred - state["deferred"], key[3] - k0[3]))

    fw = _run("roetenberg-fusion", 3, 6_000_000, on_tick)
    rows = [r for r in rows if r[0] >= WARMUP_US]
    for prev, cur in zip(rows, rows[1:]):
        t, imu, evals, replay, deferred, updates = cur
        if imu and (replay > 1 or updates):
            assert prev[4], f"tick {t}: IMU samples and {replay} replay steps / an update"
    assert sum(r[4] for r in rows) >= 3                 # the rule did put work off (7 here)
    st = fw.status()
    assert st["fusion_updates"] >= 5 and st["fused_poses"] > 400


def test_adaptive_decision_after_an_update_waits_one_tick_for_the_same_start():
    """``schepers-adaptive``, 6 s: no tick runs both an EKF update and the coil choice, and a
    pulse decided in the tick after an update is commanded for the start found in the update
    tick (at least ``adaptive_lead_us`` less one tick ahead). Catches the deferral dropped
    (update and decision in one tick), a held start lost (the pulse moved a tick later, or
    commanded with no lead) and a decision put off forever (no pulses)."""
    from coiltrack.firmware.actuate.coil_choice import CoilChooser
    from coiltrack.firmware.estimate.single_coil import SchepersEKF

    calls = {"choose": 0, "update": 0}
    real_choose, real_update = CoilChooser.choose, SchepersEKF.update_single_coil

    def choose(self, *a, **k):
        calls["choose"] += 1
        return real_choose(self, *a, **k)

    def update(self, *a, **k):
        calls["update"] += 1
        return real_update(self, *a, **k)

    both = []
    state = {}
    commanded = []

    def on_tick(fw, t, before):
        tr = fw.tracker
        if before:
            state.update(calls)
            state["held"] = tr._held_start
            state["pulses"] = tr.pulses
            return
        c, u = calls["choose"] - state["choose"], calls["update"] - state["update"]
        if c and u:
            both.append(t)
        if state["held"] >= 0 and tr.pulses > state["pulses"]:
            commanded.append((t, state["held"], tr.next_free_us - tr.pulse_us - tr.gap_us,
                              tr.lead_us, fw.cfg.tick_us))

    CoilChooser.choose, SchepersEKF.update_single_coil = choose, update
    try:
        fw = _run("schepers-adaptive", 3, 6_000_000, on_tick)
    finally:
        CoilChooser.choose, SchepersEKF.update_single_coil = real_choose, real_update
    assert not both, f"update and coil choice in the same tick at {both[:5]}"
    assert calls["update"] > 30 and fw.tracker.pulses > 30
    assert len(commanded) >= 1                          # (2 here: most decisions find no pulse due)
    for t, held, start, lead, tick in commanded:
        assert start == held and start - t >= lead - tick


def test_sixteen_sensors_hand_over_within_the_track_budget():
    """``multi16`` (16 sensors, one solver), 4 s: the track stage's work in every tick, in
    field evaluations, is at most ``track_budget_evals``: the charges of the solver's units
    that ran (``pose.staged``: a unit's field evaluations, ``n`` for a closed form) plus ``n``
    for each sensor started (its burst status, warm start and ``begin``, after the last
    sensor's POSE: about one LM step's time). Before, a tick whose solve steps used the whole
    budget (two LM steps and the closing covariance) also handed over to the next sensor
    (9 + 3 = 12), and unusable bursts were all handed over in one tick. The sixteen solves of
    every burst still finish (each sensor gets its POSEs). Catches the hand-over not charged,
    its budget check inverted (a sensor never started: no POSEs of it) and a hand-over put off
    and then forgotten (the burst never released: no further cycles)."""
    state = {"worst": 0, "ticks_over": 0, "t_worst": None, "units": 0}
    per_node = {}

    def on_tick(fw, t, before):
        tr = fw.tracker
        sv = tr.solver
        if "n" not in state:
            state["n"] = sv.n
            orig_begin, orig_then = tr._begin, sv._then

            def begin(ch):
                state["units"] += sv.n
                per_node[ch.node] = per_node.get(ch.node, 0) + 1
                return orig_begin(ch)

            def then(unit, cost=0):
                if unit is None:
                    return orig_then(None, cost)

                def charged():
                    state["units"] += cost
                    return unit()
                return orig_then(charged, cost)
            tr._begin, sv._then = begin, then
        if before:
            state["units"] = 0
            return
        if t >= WARMUP_US and state["units"] > state["worst"]:
            state["worst"], state["t_worst"] = state["units"], t
        if t >= WARMUP_US and state["units"] > fw.cfg.track_budget_evals:
            state["ticks_over"] += 1

    fw = _run("multi16", 1, 4_000_000, on_tick)
    budget = fw.cfg.track_budget_evals
    assert state["ticks_over"] == 0, (state["ticks_over"], state["worst"], state["t_worst"], budget)
    assert state["worst"] == budget                 # the budget is used, not left idle
    assert sorted(per_node) == list(range(16, 32))
    assert min(per_node.values()) >= 5              # every sensor solved in every burst
    st = fw.status()
    assert st["cycles"] >= 5 and st["solve_ticks_max"] <= 70
