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
