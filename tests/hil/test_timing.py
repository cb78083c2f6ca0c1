"""HIL timing tests on the simulated clock, asserting in microseconds.

* Every sample the firmware used for a pulse amplitude lies in the flat
  part of the TRUE pulse (after the L/R rise and the eddy transients have
  settled to 1e-3, before the true end edge), compared on true time; and the
  checker does catch samples on an edge.
* With node clocks drifting by +-100 ppm and offset by seconds, the time sync
  keeps the windows aligned (and without it they drift off).
* Pulse commands reach the driver ahead of their start.
* Set/reset flips stay out of the pulse windows.
* Latency from the sample that completes a cycle to the pose frame, and the
  tick timing measures.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from coiltrack.hil.bench import flips_inside_windows, window_truth
from coiltrack.hil.clock import SimClock
from coiltrack.firmware.measure.pulse import PULSE_FLIP
from coiltrack.protocol.schema import STAMP_LSB_US
from coiltrack.tools.bench.realtime import emulator_loop, firmware_loop, inproc_timing


@pytest.fixture(scope="module")
def fast_run(bench_runner):
    """1 kHz magnetometer and IMU, eddy plate and steel part, clocks drifting up to 100 ppm."""
    return bench_runner("hil-fast", seed=2, duration_s=12.0)


@pytest.fixture(scope="module")
def thesis_run(bench_runner):
    return bench_runner("roetenberg-bench", seed=4, duration_s=30.0, faults="drift=100")


def _check_windows(run, expect_min):
    wt = window_truth(run.bench)
    checked = [r for r in wt if "violation" in r]
    assert len(checked) >= expect_min
    assert all(r["matched"] for r in wt)
    for r in checked:
        # true instants of the first and last used samples, in microseconds
        assert r["first_true_us"] >= r["flat_start_us"], r
        assert r["last_true_us"] <= r["true_end_us"], r
        assert not r["violation"]
    return checked


def test_used_samples_lie_in_the_flat_part_fast_profile(fast_run):
    checked = _check_windows(fast_run, 3 * 18)
    margin = min(min(r["margin_start_us"], r["margin_end_us"]) for r in checked)
    assert margin >= 1000                               # settle 6 ms vs flat part from ~4.5 ms
    # the eddy plate really delays the flat part beyond the L/R rise (2.3 ms)
    assert max(r["flat_start_us"] - r["true_start_us"] for r in checked) > 4000
    assert fast_run.rep["pulse_window_violations"] == 0


def test_used_samples_lie_in_the_flat_part_thesis_profile(thesis_run):
    checked = _check_windows(thesis_run, 3 * 45)
    assert min(r["margin_start_us"] for r in checked) > 0
    assert thesis_run.rep["pulse_window_violations"] == 0


def test_the_checker_catches_samples_on_the_edge(bench_runner):
    """Same fast bench, firmware settle 1 ms instead of 6 ms: at 1 kHz the second in-pulse
    sample (the first is always dropped) comes 1-2 ms after the edge, before even the L/R rise
    has settled (2.3 ms), so every window uses samples on the edge, and the checker says so."""
    run = bench_runner("hil-fast", seed=2, duration_s=4.0, cfg={"settle_us": 1000})
    wt = [r for r in window_truth(run.bench) if "violation" in r]
    assert len(wt) >= 15 and all(r["violation"] for r in wt)
    assert all(r["first_true_us"] < r["flat_start_us"] for r in wt)
    assert run.rep["pulse_window_violations"] == len(wt)


def test_sync_keeps_100ppm_clocks_aligned(thesis_run):
    """Sensor +100 ppm, driver -100 ppm, offsets of seconds (unsynchronised they would part by
    6 ms in 30 s). What the windows need is that the sensor stamps a pulse's true edge with the
    commanded master time: within 5 us, all run long. In absolute terms both nodes see the
    master late by the broadcast's link latency, the same for both (one tick in this runner:
    the emulator reads the broadcast at its next step), so it cancels between them."""
    b = thesis_run.bench
    tick = thesis_run.cfg.timing.tick_us
    assert b.sensor.clock.drift_ppm == 100.0 and b.driver.clock.drift_ppm == -100.0
    assert abs(b.sensor.clock.offset_us) > 100_000 and abs(b.driver.clock.offset_us) > 100_000
    ex = b.driver.executed
    assert len(ex) >= 3 * 45
    for e in ex:
        # the drift is fitted once the sync points span 1 s; before that only the offset is
        # (200 ppm relative drift x up to 0.5 s between syncs)
        tol = 5 if e["start_us"] > 2_000_000 else 100
        assert abs(b.sensor.master(e["start_us"]) - e["master_start_us"]) <= tol
        assert abs(b.sensor.master(e["end_us"]) - e["master_end_us"]) <= tol
        assert abs(e["start_us"] - e["master_start_us"] - tick) <= tol
    st, tt = np.array(b.sensor.stamps), np.array(b.sensor.true_times)
    late = tt > 2_000_000
    # the stamps on the wire (MAG_PACKED) are rounded to STAMP_LSB_US = 8 us: +-4 us on top
    assert np.max(np.abs(st[late] - tt[late] + tick)) <= 5 + STAMP_LSB_US // 2


def test_without_sync_the_windows_drift_off(bench_runner):
    """Control: the same drifting clocks with the firmware's time sync reduced to the first
    broadcast: the driver and the sensor drift apart at 200 us/s and the windows leave the
    flat part within seconds."""
    def no_sync(fw, bench):
        sup = fw.supervisor
        sup.scfg = dataclasses.replace(sup.scfg, sync_around_burst=False)
        sup.timesync.period_us = 10**12

    run = bench_runner("hil-fast", seed=2, duration_s=16.0, faults="drift=100", setup=no_sync)
    b = run.bench
    assert run.fw.supervisor.timesync.sent == 1
    ex = b.driver.executed
    assert max(abs(e["start_us"] - e["master_start_us"]) for e in ex) > 1000
    assert run.rep["pulse_window_violations"] > 0


def test_pulse_commands_reach_the_driver_ahead(thesis_run, fast_run):
    for run in (thesis_run, fast_run):
        b = run.bench
        assert b.driver.refused == 0
        lead = run.cfg.timing.lead_us
        for e in b.driver.executed:
            # in master time (driver's view) and in true time
            # commands leave lead_us before the cycle; coil j starts j * spacing later
            j_max = len(run.cfg.source.coils) - 1
            assert lead - run.cfg.timing.tick_us <= e["lead_us"] <= lead + j_max * run.cfg.timing.spacing_us + 100
            assert e["start_us"] - e["rx_true_us"] >= lead - 2 * run.cfg.timing.tick_us
        assert run.rep["command_lead_min_ms"] >= (lead - run.cfg.timing.tick_us) / 1000


def test_flips_stay_out_of_the_pulse_windows(thesis_run, bench_runner):
    b = thesis_run.bench
    cmd = [f for f in b.sensor.flip_log if f["commanded"]]
    assert len(cmd) >= 40                           # one per cycle
    assert flips_inside_windows(b) == 0
    flagged = [w for _, w in b.recorder.windows if w.flags & PULSE_FLIP]
    assert not flagged
    # control: the firmware does not schedule flips; the sensor flips by itself every 8 samples,
    # inside the windows, and the firmware sees it in the flip bit
    def no_flips(fw, bench):
        fw.supervisor.scfg = dataclasses.replace(fw.supervisor.scfg, flips=False)

    run = bench_runner("roetenberg-bench", seed=4, duration_s=6.0, setup=no_flips)
    wins = [w for _, w in run.bench.recorder.windows]
    assert flips_inside_windows(run.bench) > 10
    assert sum(1 for w in wins if w.flags & PULSE_FLIP) > 0.8 * len(wins)


def test_time_sync_broadcasts_and_replies(thesis_run):
    rec = thesis_run.bench.recorder
    t = np.array([r for r, _ in rec.time_syncs])
    assert np.max(np.diff(t)) <= 250_000 + thesis_run.cfg.timing.tick_us
    st = thesis_run.fw.status()
    assert st["sync_replies"] >= 2 * (st["sync_sent"] - 1)
    assert st["sync_rtt_us_min"] == thesis_run.cfg.timing.tick_us       # one tick each way in this runner


def test_latency_from_last_sample_to_pose_is_bounded(thesis_run, fast_run):
    """On the simulated clock the latency is the pipeline's quantisation (the emulator step
    after the sample, the firmware tick after that, the emulator step that receives the pose:
    3 ticks) plus the ticks the bounded solve takes after the last window closed, which the
    firmware reports (``solve_ticks_max``; 0 where every burst was solved ahead, the acquisition
    included): a pose leaves in the tick its solve completes."""
    for run in (thesis_run, fast_run):
        rep = run.rep
        st = run.fw.status()
        assert rep["latency_ms_max"] is not None
        assert 0 <= st["solve_ticks_max"] <= -(-st["solve_evals_max"] // run.cfg.budget.track_budget_evals) + 2
        assert rep["latency_ms_max"] * 1000 <= (3 + st["solve_ticks_max"]) * run.cfg.timing.tick_us
        assert rep["latency_ms_p50"] * 1000 >= run.cfg.timing.tick_us - 1


# ---------------------------------------------------------------------------
# the loops' timing measures, on an injected clock
# ---------------------------------------------------------------------------


class _ScriptedFirmware:
    """Each tick takes the next scripted execution time on the simulated clock."""

    def __init__(self, clock, exec_us):
        self.clock, self.exec_us, self.ticks = clock, list(exec_us), []

    def tick(self, now):
        self.ticks.append(now)
        self.clock.now_us += self.exec_us[len(self.ticks) - 1] if len(self.ticks) <= len(self.exec_us) else 10


def test_firmware_loop_measures_jitter_and_deadline_misses():
    clock = SimClock(0)
    # 1 kHz; tick 5 takes 2.5 ms (misses its deadline and two slots), tick 9 takes 900 us
    ex = [10] * 20
    ex[5] = 2_500
    ex[9] = 900
    fw = _ScriptedFirmware(clock, ex)
    out = firmware_loop(fw, clock, 20_000, 1000, spin_us=0)      # a simulated clock only moves when slept
    assert fw.ticks[:6] == [0, 1000, 2000, 3000, 4000, 5000]
    assert fw.ticks[6:8] == [7500, 8000]       # slot 6 skipped, slot 7 starts 500 us late
    assert out["deadline_misses"] == 2         # the overrun tick and the skipped slot
    assert out["tick_jitter_us_max"] == 1500.0
    assert out["tick_exec_us_max"] == 2500.0
    assert out["tick_late_us_max"] == 500.0
    assert out["tick_jitter_us_median"] == 0.0


def test_inproc_timing_replays_execution_on_a_real_time_schedule():
    ex_ns = np.full(100, 50_000, dtype=np.int64)       # 50 us per tick
    ex_ns[10] = 2_300_000                              # one 2.3 ms solve
    out = inproc_timing(ex_ns, 1000)
    assert out["deadline_misses"] == 2                 # the overrun and the slot it swallowed
    assert out["tick_late_us_max"] == 300              # the next tick starts at 12.3 ms (slot 12 ms)
    assert out["tick_jitter_us_max"] == 1300           # period 10 -> 12.3 ms
    assert out["tick_exec_us_max"] == 2300
    assert out["ticks"] == 100
    assert "inproc" in out["timing_source"]


def test_emulator_loop_steps_on_an_injected_clock():
    clock = SimClock(-500)

    class Emu:
        def __init__(self):
            self.t = []
            self.recorder = type("R", (), {"poses": []})()

        def step(self, now):
            self.t.append(now)

    emu = Emu()
    emulator_loop(emu, object(), clock, 2_000, step_us=250, wait=clock.sleep)
    assert emu.t == list(range(0, 2_001, 250))


def test_firmware_loop_trace_records_each_ticks_gap_sleeps_and_stages(tmp_path):
    """With a LoopTrace the loop records, per tick, the previous tick's end, its start and end, the
    sleeps between (count, time asked, the longest measured: a sleep the platform overran shows
    there, not in the tick) and the stage times ``tick_timed`` wrote; the file keeps them by name.
    Without one, ``fw.tick`` runs (not ``tick_timed``) and nothing is recorded."""
    from coiltrack.tools.bench.timing import LoopTrace

    class Timed(_ScriptedFirmware):
        def tick_timed(self, now, out):
            out[:] = np.arange(1, 7) * 100
            self.tick(now)

    clock = SimClock(0)
    naps = []

    def sleep(s):                      # the fourth gap's sleep overruns by 7 ms
        naps.append(s)
        clock.now_us += int(round(s * 1e6)) + (7_000 if len(naps) == 3 else 0)
    fw = Timed(clock, [10] * 8)
    trace = LoopTrace(cap=16, path=str(tmp_path / "t.npz"))
    firmware_loop(fw, clock, 12_000, 1000, sleep=sleep, spin_us=0, trace=trace)
    r = trace.rows[:trace.n]
    col = {c: i for i, c in enumerate(LoopTrace.COLS)}
    assert trace.n == len(fw.ticks) and list(r[:, col["start"]]) == fw.ticks
    assert fw.ticks[:4] == [0, 1000, 2000, 10_000]
    assert list(r[1:, col["prev_end"]]) == list(r[:-1, col["end"]])
    assert r[3, col["sleeps"]] == 1 and r[3, col["sleep_asked"]] == 990 and r[3, col["sleep_max"]] == 7_990
    assert r[3, col["start"]] - r[3, col["prev_end"]] == 7_990
    assert list(r[2, col["st_receive"]:col["st_transmit"] + 1]) == [100, 200, 300, 400, 500, 600]
    trace.save()
    z = np.load(tmp_path / "t.npz")
    assert list(z["cols"]) == list(LoopTrace.COLS) and z["rows"].shape == (trace.n, len(LoopTrace.COLS))
    plain = _ScriptedFirmware(SimClock(0), [10] * 4)
    firmware_loop(plain, plain.clock, 4_000, 1000, spin_us=0)
    assert len(plain.ticks) == 4


def test_firmware_loop_polls_only_the_last_spin_us_before_a_slot():
    """The loop sleeps until ``SPIN_US`` (50 us) before each slot and polls the clock for the rest: a
    SCHED_FIFO loop polling its CPU keeps the tty's flush work off it (with 200 us, 84-87 % of the
    writes made in the last 200 us before a tick were read a tick late; docs/bench-realtime.md).
    On a clock that moves 5 us a reading, each gap after a 10 us tick is one sleep of
    1000 - 10 - 10 - 50 us asked, then 50 us of polls, and every tick starts on its slot;
    catches a spin back at 200 us (780 us asked), or none."""
    from coiltrack.tools.bench.realtime import SPIN_US

    class Ticking(SimClock):
        def now(self):
            self.now_us += 5
            return self.now_us

    clock = Ticking(0)
    naps = []

    def sleep(s):
        naps.append(int(round(s * 1e6)))
        clock.now_us += naps[-1]
    fw = _ScriptedFirmware(clock, [10] * 8)
    out = firmware_loop(fw, clock, 6_000, 1000, sleep=sleep)
    assert SPIN_US == 50
    assert fw.ticks == [1000, 2000, 3000, 4000, 5000] and out["deadline_misses"] == 0
    # after each 10 us tick and two readings (10 us), one sleep to 50 us before the next slot
    assert naps[1:] == [1000 - 10 - 10 - SPIN_US] * (len(naps) - 1)
