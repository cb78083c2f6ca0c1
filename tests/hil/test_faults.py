"""Every fault switch of the bench, with the firmware in the loop (simulated
clock). For each: the firmware keeps running to the end and keeps making
poses after the fault; it reports the fault (FAULT_EVENT codes, POSE status
bits, counters); and it never vouches for a pose it should not: every pose
marked VALID without a warning bit is accurate (static sensor at 26 cm,
CRLB 1.7 mm: error < 8 mm and < 3 deg), and no VALID pose used a window
that left the flat part of its pulse."""
from __future__ import annotations

import math

import numpy as np
import pytest

from coiltrack.firmware.rotation import matrix_from_quat
from coiltrack.protocol.schema import (EVT_CLOCK_STEP, EVT_COIL_FAULT, EVT_DISTORTION, EVT_NODE_BACK, EVT_NODE_LOST,
                             EVT_SATURATION, NODE_COIL_DRIVER, NODE_SENSOR_BASE, POSE_COIL_FAULT, POSE_DEGRADED,
                             POSE_DISTORTED, POSE_INCONSISTENT, POSE_SATURATED, POSE_STALE, POSE_VALID)

WARN = POSE_DEGRADED | POSE_INCONSISTENT | POSE_STALE | POSE_SATURATED | POSE_DISTORTED | POSE_COIL_FAULT
DURATION = 14.0
SENSOR, DRIVER = NODE_SENSOR_BASE, NODE_COIL_DRIVER


def _pose_error(rp):
    m = rp["msg"]
    p = np.array([m.px, m.py, m.pz])
    R = matrix_from_quat(np.array([m.qw, m.qx, m.qy, m.qz]))
    c = (np.trace(R.T @ rp["true_R"]) - 1) / 2
    return float(np.linalg.norm(p - rp["true_p"])), math.degrees(math.acos(max(-1.0, min(1.0, c))))


def check_survived_and_vouched(run, recovered_after_us=None, min_valid_after=3, allow=0):
    fw, b = run.fw, run.bench
    assert fw.ticks == int(DURATION * 1e6) // run.cfg.timing.tick_us + 1
    poses = b.recorder.poses
    assert len(poses) >= int(DURATION / 0.6) - 2              # a pose (valid or not) every cycle
    for rp in poses:
        st = rp["msg"].status
        if st & POSE_VALID and not st & WARN:
            pe, ae = _pose_error(rp)
            assert pe < 8e-3 and ae < 3.0, (rp["msg"].t_us, st, pe, ae)
    assert run.rep["pulse_window_violations_in_valid_poses"] == 0
    if recovered_after_us is not None:
        after = [rp for rp in poses if rp["msg"].t_us > recovered_after_us]
        ok = [rp for rp in after if rp["msg"].status & POSE_VALID and not rp["msg"].status & WARN & ~allow]
        assert len(ok) >= min_valid_after, [hex(rp["msg"].status) for rp in after]


def events(run, code=None):
    ev = [m for _, m in run.bench.recorder.events]
    return ev if code is None else [m for m in ev if m.code == code]


def statuses(run, t0=0, t1=1 << 62):
    return [rp["msg"].status for rp in run.bench.recorder.poses if t0 <= rp["msg"].t_us < t1]


@pytest.fixture(scope="module")
def baseline(bench_runner):
    return bench_runner("static", seed=3, duration_s=DURATION)


def test_no_fault_no_report(baseline):
    check_survived_and_vouched(baseline)
    assert events(baseline) == []
    assert all(s == POSE_VALID for s in statuses(baseline))
    f = baseline.rep["faults"]
    assert f["injected"]["switches"] == [] and f["reported"]["events"] == {}


def test_link_faults_dropped_corrupted_delayed_duplicated(bench_runner):
    run = bench_runner("static", seed=3, duration_s=DURATION,
                       faults="drop=0.03,corrupt=0.02,truncate=0.01,duplicate=0.03,delay=0.03,garbage=0.01,"
                              "both_ways=1")
    lf = run.rep["link_faults"]
    for k in ("dropped", "corrupted", "truncated", "duplicated", "delayed", "garbage"):
        assert lf[k] > 0, lf
    assert run.rep["frames_bad"] >= lf["corrupted"] // 2
    st = run.fw.status()
    assert st["rx_frames_bad"] > 0 and st["rx_seq_gaps"] > 0
    # delayed and duplicated samples are not mistaken for clock steps
    assert events(run, EVT_CLOCK_STEP) == []
    # missing samples (gaps) mark windows incomplete: those poses say DEGRADED, and are still fine.
    # At these rates a burst loses one of its six command/status frames (or its POSE) with
    # probability ~0.4, so 23 bursts give ~14 +- 2.3 good poses: at least 10 (2 sigma below)
    check_survived_and_vouched(run, recovered_after_us=0, min_valid_after=10, allow=POSE_DEGRADED)
    for rp in run.bench.recorder.poses:
        if rp["msg"].status & POSE_VALID:
            assert _pose_error(rp)[0] < 8e-3
    # a lost COIL_STATUS or pulse command makes the firmware refuse to vouch for that burst
    # (COIL_FAULT); windows that lost too many samples give no pose either (DEGRADED)
    vetoed = [s for s in statuses(run) if not s & POSE_VALID]
    assert vetoed and all(s & (POSE_COIL_FAULT | POSE_DEGRADED) for s in vetoed)
    assert any(s & POSE_COIL_FAULT for s in vetoed)


def test_link_latency_jitter_is_no_clock_step(bench_runner):
    """Every frame late by an exponential 2 ms (what the two-process CAN bench over slcan sees on a
    loaded host): no clock step is reported and every pose is vouched for. Catches nodes that step
    their time base on each sync correction (stamps jumping by ms, flagged as steps: 12 clock steps
    and 13 invalid poses in a 20 s slcan run) or that take three late broadcasts as a clock step."""
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="jitter_ms=2")
    assert run.rep["link_faults"] is not None
    assert events(run, EVT_CLOCK_STEP) == []
    assert run.fw.status()["sup_clock_steps"] == 0
    check_survived_and_vouched(run, recovered_after_us=0, min_valid_after=int(DURATION / 0.6) - 3)


@pytest.mark.parametrize("spec,node,how", [("clock_step=5ms@6s", SENSOR, 1 << 8),
                                           ("clock_step=-12ms@6.05s", SENSOR, 1 << 8),
                                           ("clock_step=driver:-4ms@6.1s", DRIVER, 1 << 9),
                                           ("clock_step=driver:3ms@6.5s", DRIVER, 1 << 9)])
def test_clock_steps(bench_runner, spec, node, how):
    """Sensor steps show in the sample stamps at once; driver steps show in the sync replies
    (two broadcasts right after each burst confirm them before the burst's pose)."""
    run = bench_runner("static", seed=3, duration_s=DURATION, faults=spec)
    ev = events(run, EVT_CLOCK_STEP)
    assert len(ev) == 1 and ev[0].detail == node | how
    assert run.fw.status()["sup_clock_steps"] == 1
    check_survived_and_vouched(run, recovered_after_us=7_500_000)
    # the burst during which the clock stepped was not vouched for (or was unaffected)
    for rp in run.bench.recorder.poses:
        if rp["msg"].status & POSE_VALID:
            assert _pose_error(rp)[0] < 8e-3


def test_drift_100ppm_needs_no_report(bench_runner):
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="drift=100")
    assert events(run) == []
    check_survived_and_vouched(run, recovered_after_us=0, min_valid_after=20)


def test_magnetometer_saturation(bench_runner):
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="sat=6s-8s")
    ev = events(run, EVT_SATURATION)
    assert len(ev) == 1 and ev[0].detail == SENSOR
    during = statuses(run, 6_000_000, 8_000_000)
    assert during and all(s & POSE_SATURATED and not s & POSE_VALID for s in during)
    assert run.fw.status()["sup_saturated_samples"] > 200
    check_survived_and_vouched(run, recovered_after_us=8_500_000)


def test_coil_open_circuit(bench_runner):
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="open_circuit=1@6s-8s")
    ev = events(run, EVT_COIL_FAULT)
    assert len(ev) >= 3 and all(e.detail == (1 << 8) | 2 for e in ev)       # coil 1, OPEN_CIRCUIT
    during = statuses(run, 6_000_000, 8_000_000)
    assert during and all(s & POSE_COIL_FAULT and not s & POSE_VALID for s in during)
    check_survived_and_vouched(run, recovered_after_us=8_500_000)


def test_coil_short_trips_on_over_current(bench_runner):
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="short=2@6s-7.5s")
    ev = events(run, EVT_COIL_FAULT)
    assert ev and all(e.detail == (2 << 8) | 1 for e in ev)               # coil 2, OVER_CURRENT
    during = statuses(run, 6_000_000, 7_500_000)
    assert during and all(s & POSE_COIL_FAULT and not s & POSE_VALID for s in during)
    check_survived_and_vouched(run, recovered_after_us=8_000_000)


def test_supply_sag(bench_runner):
    """The battery sags to 40 %: 1.2 A instead of 1.5 A. The driver reports the sag and the
    current it measured; the firmware flags the poses and solves with the measured current, so
    they stay accurate."""
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="sag=0.4@6s-9s")
    ev = events(run, EVT_COIL_FAULT)
    assert len(ev) >= 12 and all(e.detail & 0xFF == 64 | 128 for e in ev)  # CURRENT_SAG | SUPPLY_LOW
    during = [rp for rp in run.bench.recorder.poses if 6_000_000 <= rp["msg"].t_us < 9_000_000]
    assert during
    for rp in during:
        assert rp["msg"].status & POSE_COIL_FAULT and rp["msg"].status & POSE_VALID
        assert _pose_error(rp)[0] < 8e-3
    check_survived_and_vouched(run, recovered_after_us=9_500_000)


def test_coil_over_temperature(bench_runner):
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="overheat=0@6s-8s")
    ev = events(run, EVT_COIL_FAULT)
    assert len(ev) >= 3 and all(e.detail == 4 | 16 for e in ev)       # coil 0, OVER_TEMPERATURE | REFUSED
    during = statuses(run, 6_000_000, 8_000_000)
    assert during and all(s & POSE_COIL_FAULT and not s & POSE_VALID for s in during)
    check_survived_and_vouched(run, recovered_after_us=8_500_000)


def test_metal_brought_near_the_sensor(bench_runner):
    """A steel part (2 cm radius, mu_r 200, conducting) carried 6 cm from the sensor from 6 s on:
    it shifts the quiet field by ~2 uT and distorts the pulses; every pose from the burst it
    appeared in is flagged DISTORTED."""
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="metal=6.01s")
    ev = events(run, EVT_DISTORTION)
    assert len(ev) == 1 and ev[0].detail & 0xFF == SENSOR and not ev[0].detail >> 31
    after = statuses(run, 6_000_000)
    assert after and all(s & POSE_DISTORTED for s in after)
    assert all(not s & POSE_DISTORTED for s in statuses(run, 0, 6_000_000))
    # the distortion is real: flagged poses are off by more than the unflagged ones
    errs = [_pose_error(rp)[0] for rp in run.bench.recorder.poses if rp["msg"].t_us > 6_000_000]
    assert max(errs) > 8e-3
    check_survived_and_vouched(run)


def test_metal_taken_away_clears_the_flag(bench_runner):
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="metal=5s-8s")
    ev = events(run, EVT_DISTORTION)
    assert [e.detail >> 31 for e in ev] == [0, 1]
    assert all(not s & POSE_DISTORTED for s in statuses(run, 9_000_000))
    check_survived_and_vouched(run, recovered_after_us=9_000_000)


def test_sensor_node_disappears_and_comes_back(bench_runner):
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="node_off=sensor@6s-8s")
    lost, back = events(run, EVT_NODE_LOST), events(run, EVT_NODE_BACK)
    assert [e.detail for e in lost] == [SENSOR] and [e.detail for e in back] == [SENSOR]
    assert events(run, EVT_CLOCK_STEP) == []       # its rebooted clock is re-acquired, not a step
    assert 6_000_000 < lost[0].t_us < 6_400_000 and 8_000_000 <= back[0].t_us < 8_050_000
    during = statuses(run, 6_000_000, 8_000_000)
    assert during and all(not s & POSE_VALID for s in during)
    check_survived_and_vouched(run, recovered_after_us=8_500_000)


def test_coil_driver_disappears_and_comes_back(bench_runner):
    run = bench_runner("static", seed=3, duration_s=DURATION, faults="node_off=driver@6s-8s")
    lost, back = events(run, EVT_NODE_LOST), events(run, EVT_NODE_BACK)
    assert [e.detail for e in lost] == [DRIVER] and [e.detail for e in back] == [DRIVER]
    assert events(run, EVT_CLOCK_STEP) == []
    during = statuses(run, 6_000_000, 8_000_000)
    assert during and all(s & POSE_COIL_FAULT and not s & POSE_VALID for s in during)
    assert run.fw.status()["sup_coil_status_missing"] >= 2
    check_survived_and_vouched(run, recovered_after_us=8_500_000)


def test_everything_at_once(bench_runner):
    """All switches in one run of the moving thesis bench: nothing crashes, everything is reported."""
    spec = ("drop=0.01,corrupt=0.01,duplicate=0.01,delay=0.01,drift=100,clock_step=4ms@3s,sat=5s-6s,"
            "open_circuit=0@7s-8s,sag=0.4@9s-10s,metal=11s-13s,node_off=sensor@14s-15s,short=1@16s-17s")
    run = bench_runner("roetenberg-bench", seed=5, duration_s=19.0, faults=spec)
    got = set(run.rep["faults"]["reported"]["events"])
    # (the carried metal is not required here: for some orientations of the moving sensor its
    # induced field is nearly orthogonal to the earth field, where the magnitude test is blind)
    assert {"clock_step", "saturation", "coil_fault", "node_lost", "node_back"} <= got
    assert run.fw.ticks == 19_001
    assert run.rep["pulse_window_violations_in_valid_poses"] == 0
    # the run goes on: after the last switch, poses are valid again (or say why not: the 1 %
    # link faults can lose a COIL_STATUS, and then the firmware does not vouch for the burst)
    last = [rp["msg"].status for rp in run.bench.recorder.poses if rp["msg"].t_us > 17_500_000]
    assert last and all(s & (POSE_VALID | POSE_COIL_FAULT) for s in last)
    assert any(s & POSE_VALID for s in last)
