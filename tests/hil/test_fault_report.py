"""The fault keys of the bench report (``tools.outputs.faultreport``) against
independent references (scipy's chi-square quantile, hand-made error
series), and a short soak: a bench run under a dense seeded schedule of
faults, survived, reported, recovered from, with honest covariances and
constant firmware memory."""
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import chi2

from coiltrack.hil.faults import TimedFault
from coiltrack.tools.outputs import faultreport as fr


def _pose(err, var):
    return SimpleNamespace(px=err[0], py=err[1], pz=err[2], var_px=var[0], var_py=var[1], var_pz=var[2])


def test_overconfidence_bound_is_the_999_quantile_with_three_degrees_of_freedom():
    """The bound equals scipy's chi2.ppf(0.999, 3) to 1e-9, and a pose is
    overconfident exactly when sum e_i^2 / var_i passes it: d^2 = 16.0 is
    inside, 16.5 outside (with 1 dof, 10.83, or 2 dof, 13.82, or the 99 %
    quantile, 11.34, both would be outside; with 4 dof, 18.47, both inside).
    Each axis is divided by its own variance. A zero variance is overconfident."""
    assert fr.CHI2_999_3 == pytest.approx(chi2.ppf(0.999, 3), abs=1e-9)
    var = (4e-6, 1e-6, 9e-6)                      # sigma 2, 1, 3 mm
    unit = np.array([2e-3, 1e-3, 3e-3]) / np.sqrt(3.0)
    assert not fr.overconfident(_pose(unit * np.sqrt(16.0), var), (0.0, 0.0, 0.0))
    assert fr.overconfident(_pose(unit * np.sqrt(16.5), var), (0.0, 0.0, 0.0))
    # all the error on the least certain axis: 11 mm on z (sigma 3 mm, d^2 = 13.4) is inside
    assert not fr.overconfident(_pose((0.0, 0.0, 11e-3), var), (0.0, 0.0, 0.0))
    assert fr.overconfident(_pose((0.0, 11e-3, 0.0), var), (0.0, 0.0, 0.0))
    assert fr.overconfident(_pose((1e-6, 0.0, 0.0), (0.0, 1.0, 1.0)), (0.0, 0.0, 0.0))


def test_recovery_time_counts_from_the_fault_end_to_twice_the_level():
    """Errors of 100 mm until 1.5 s after the fault's end, then 8 mm (level
    5 mm, limit 10 mm): the first one-second window within the limit starts
    1.5 s after the end (on the 0.1 s grid). An open-ended fault counts from
    its start; errors that never come back give None. Catches a recovery
    measured from the fault's start or against the level itself."""
    t = np.arange(0.0, 30.0, 1 / 120)
    e = np.where(t < 11.5, 0.100, 0.008)
    f = TimedFault("sat", 5_000_000, 10_000_000)
    assert fr.recovery_time(t, e, f, 5.0) == pytest.approx(1.5, abs=1e-9)
    assert fr.recovery_time(t, e, TimedFault("sag", 10_000_000, None), 5.0) == pytest.approx(1.5, abs=1e-9)
    assert fr.recovery_time(t, np.full(t.size, 0.1), f, 5.0) is None
    assert fr.recovery_time(t, e, f, 3.0) is None           # 8 mm is not within 6 mm


def test_recovery_is_held_to_the_no_fault_run_where_it_is_itself_above_twice_the_level():
    """The old mistake: the no-fault run of the same seed is at 8 mm except 45-60 s, where the
    trajectory is at far range and its error is 40 mm (twice the 10 mm level is 20 mm: the
    tracker with no fault is itself "not recovered" there). The faulted run is 300 mm off until
    46.2 s, then exactly the no-fault run. Against the level alone the recovery waits for the
    first second ahead whose RMS is within 20 mm: 0.3 s of 40 mm and 0.7 s of 8 mm at 59.7 s
    (sqrt(0.3 * 1600 + 0.7 * 64) = 22.9 mm, too much), 0.2 s of 40 mm at 59.8 s (19.1 mm):
    14.8 s. Against the no-fault run (twice max(level, its RMS over the same second)) it is the
    time the faulted trace takes to rejoin it: the first window wholly past 46.2 s, 1.2 s. A
    faulted run that stays at 100 mm is never back. The factor 2 is kept: 79 mm beside the
    no-fault run's 40 mm is back, 81 mm is not. The keys say which reference was used."""
    t = np.arange(0.0, 80.0, 1 / 120)
    und = np.where((t >= 45.0) & (t < 60.0), 0.040, 0.008)
    flt = np.where(t < 46.2, 0.300, und)
    f = TimedFault("sat", 40_000_000, 45_000_000)
    assert fr.recovery_time(t, flt, f, 10.0) == pytest.approx(14.8, abs=1e-9)
    assert fr.recovery_time(t, flt, f, 10.0, (t, und)) == pytest.approx(1.2, abs=1e-9)
    assert fr.recovery_time(t, np.where(t < 46.2, 0.300, 0.100), f, 10.0, (t, und)) is None
    # within twice the no-fault run's own error at the time: 79 mm against 40 mm is back at once; 81 mm
    # is not, until the second ahead holds half of it and half 8 mm (57.6 mm rms against twice 28.8 mm)
    assert fr.recovery_time(t, np.where(t < 46.2, 0.300, np.where(t < 60.0, 0.079, und)), f, 10.0,
                            (t, und)) == pytest.approx(1.2, abs=1e-9)
    assert fr.recovery_time(t, np.where(t < 46.2, 0.300, np.where(t < 60.0, 0.081, und)), f, 10.0,
                            (t, und)) == pytest.approx(14.5, abs=1e-9)
    # the level still bounds a no-fault run that is quieter than it (2 mm: 15 mm is within 20 mm)
    assert fr.recovery_time(t, np.full(t.size, 0.015), f, 10.0, (t, np.full(t.size, 0.002))) == 0.0
    # a window where the no-fault run has no valid fused pose is held to the level
    gap = (t >= 45.0) & (t < 60.0)
    assert fr.recovery_time(t, flt, f, 10.0, (t[~gap], und[~gap])) == pytest.approx(14.8, abs=1e-9)
    keys = fr.recovery_keys(t, flt, [f], 10.0, (t, und))
    assert keys == {"fault_recovery_s": {f.describe(): pytest.approx(1.2)}, "recovery_reference": "no-fault run"}
    assert fr.recovery_keys(t, flt, [f], 10.0)["recovery_reference"] == "level"
    assert fr.recovery_keys(t, flt, [], 10.0) == {"fault_recovery_s": {}}


def test_an_imu_saturation_does_not_report_a_magnetometer_saturation():
    """``EVT_SATURATION`` with the IMU detail bit is the IMU's (``health.IMU_SATURATION``): a timed
    magnetometer saturation answered only by it stays unreported; the magnetometer's own event
    (detail: the node) reports it. Catches the detail bit left unread."""
    from coiltrack.firmware.supervise.health import IMU_SATURATION
    from coiltrack.protocol.schema import EVT_SATURATION

    sat = TimedFault("sat", 10_000_000, 12_000_000)
    imu = SimpleNamespace(code=EVT_SATURATION, detail=16 | IMU_SATURATION)
    mag = SimpleNamespace(code=EVT_SATURATION, detail=16)
    rep, unrep = fr.reported_faults([(11_000_000, imu)], [sat])
    assert rep == {sat.describe(): ["EVT_SATURATION_IMU"]} and unrep == [sat.describe()]
    rep, unrep = fr.reported_faults([(11_000_000, imu), (14_500_000, mag)], [sat])
    assert rep[sat.describe()] == ["EVT_SATURATION", "EVT_SATURATION_IMU"] and unrep == []
    _, unrep = fr.reported_faults([(15_500_000, mag)], [sat])          # after the grace: not its report
    assert unrep == [sat.describe()]


def test_bench_rescores_recovery_against_the_no_fault_trace():
    """``tools.bench.recovery.add_recovery_reference`` replaces the report's level-only recovery by
    the one against the no-fault trace, with the report's own level; ``TraceKeeper`` keeps the
    valid fused poses of a recorder (true time, error) and forwards the rest to its inner outputs."""
    from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID
    from coiltrack.tools.bench.recovery import TraceKeeper, add_recovery_reference, needs_reference

    t = np.arange(0.0, 80.0, 1 / 120)
    und = np.where((t >= 45.0) & (t < 60.0), 0.040, 0.008)
    flt = np.where(t < 46.2, 0.300, und)
    faults = SimpleNamespace(timed=[TimedFault("sat", 40_000_000, 45_000_000)])
    rep = {"no_fault_level_mm": 10.0, "fault_recovery_s": {"sat=@40s-45s": 14.8}, "recovery_reference": "level"}
    add_recovery_reference(rep, (t, flt), faults, (t, und))
    assert rep["fault_recovery_s"] == {"sat=@40s-45s": pytest.approx(1.2)}
    assert rep["recovery_reference"] == "no-fault run"
    assert needs_reference(faults) and not needs_reference(SimpleNamespace(timed=[])) and not needs_reference(None)

    def pose(status, x, t_us):
        return {"msg": SimpleNamespace(status=status, px=x, py=0.0, pz=0.0, t_us=t_us), "true_p": (0.0, 0.0, 0.0)}

    rec = SimpleNamespace(poses=[pose(POSE_VALID | POSE_FUSED, 0.003, 1000), pose(POSE_VALID, 0.5, 2000),
                                 pose(POSE_FUSED, 0.5, 3000), pose(POSE_VALID | POSE_FUSED, -0.004, 4000)],
                          master_to_true=lambda t_us: t_us + 500)
    seen = []
    inner = SimpleNamespace(finish=lambda b, r: seen.append(r), wrap=lambda port, **kw: ("wrapped", port),
                            tick=lambda t: seen.append(t), paced=True)
    keep = TraceKeeper(inner)
    keep.tick(7)
    assert keep.wrap("port", side="emulator") == ("wrapped", "port") and keep.paced
    keep.finish(SimpleNamespace(recorder=rec), {"r": 1})
    assert seen == [7, {"r": 1}]
    assert keep.trace[0] == pytest.approx([1.5e-3, 4.5e-3]) and keep.trace[1] == pytest.approx([0.003, 0.004])
    alone = TraceKeeper()
    assert alone.wrap("port") == "port"
    with pytest.raises(AttributeError):
        alone.paced


def test_short_soak_survives_reports_and_recovers():
    """28 s of roetenberg-fusion (seed 3) with every link fault on and a
    sensor outage, a magnet on the sensor board and an open coil: no crash;
    every fault raised its event; each window recovered from within 3 s;
    at most 1 % overconfident valid poses; the poses of the saturation gap
    carry POSE_DEAD_RECKONING and those past ``dead_reckon_limit_us`` are
    sent not valid; the firmware's state bytes and container sizes do not
    change after the first sample. Catches the fused track lost after an
    outage, gap poses sent as plain valid poses, an event missing, or a
    buffer that grows."""
    from coiltrack.tools.scenarios import get
    from coiltrack.tools.bench.soak import LINK_RATES, passed, soak_run

    link = ",".join(f"{k}={v:g}" for k, v in LINK_RATES.items())
    sched = f"{link},node_off=sensor@6s-8s,sat=12s-16s,open_circuit=1@20s-23s"
    rep = soak_run(get("roetenberg-fusion"), 3, 28.0, sched)
    v = rep["verdict"]
    assert passed(v), (v, rep["fault_recovery_s"], rep["faults_unreported"], rep["overconfident_fraction"])
    assert rep["fusion"]["imu_orientation_reacquired"] == 1 and rep["fusion"]["fusion_recoveries"] >= 2
    assert rep["fusion"]["fused_poses_lost"] > 0 and rep["poses_invalid"] >= rep["fusion"]["fused_poses_lost"]
    assert rep["state_bytes_constant"] and rep["items_growth"] == 0
    assert sum(rep["overconfident_by_fault"].values()) == rep["poses_overconfident"]   # windows apart: each once
    ev = rep["faults"]["reported"]["events"]
    assert ev.get("dead_reckoning") and ev.get("track_reinit")
    assert rep["faults"]["reported"]["pose_status"].get("dead_reckoning", 0) > 0
