"""Bench report keys about faults: honest uncertainty, recovery, events.

* ``poses_overconfident``: valid poses whose position error lies outside the
  99.9 % chi-square bound of their own reported covariance. The POSE message
  carries the diagonal of the position covariance (``var_px``, ``var_py``,
  ``var_pz``, m^2), so the test statistic is
  ``d^2 = sum_i e_i^2 / var_i`` against ``chi2.ppf(0.999, 3)`` = 16.27 (three
  degrees of freedom: the three position axes); ``overconfident_fraction`` is
  their share of all valid poses (``overconfidence`` splits them into fused
  and magnetic-only).
* ``fault_recovery_s``: per timed fault window, the time from the fault's end
  (its start for a fault without an end) until the fused position error is
  back to what it would have been without the fault: the first instant ``t``
  whose following second of valid fused poses has an RMS error at most
  ``2 x max(no_fault_level_mm, RMS of the no-fault run's errors over the same
  second)``. The no-fault run (``recovery_reference`` ``"no-fault run"``) is
  the same scenario, seed, trajectory and configuration without the timed
  faults (``tools.bench.recovery``, run by ``coiltrack bench``): where the
  trajectory is at far range its error is itself above twice the run's
  level, and the faulted run is asked to do no better than it. Without that
  run (``recovery_reference`` ``"level"``: ``soak``, ``check``) the
  threshold is ``2 x no_fault_level_mm`` alone, which counts such a stretch
  as not recovered. The no-fault level is the fused RMS error of the same
  run outside every fault window and the ``RECOVERY_HORIZON_S`` after it (or
  ``reference_level_mm`` given by the caller). ``None``: not back within the
  horizon before the run ended. ``fused_rms_after_faults_mm``: the fused RMS
  error after the last fault window's end.
* ``faults_reported``: per fault switch, the firmware's ``FAULT_EVENT`` codes
  received while it was on or within ``REPORT_GRACE_S`` after;
  ``faults_unreported`` lists the switches that raised none of the events they
  should (``EXPECTED_EVENTS``).
* ``overconfident_by_fault``: the overconfident poses per fault window (and
  the ``REPORT_GRACE_S`` after it), and outside every window.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.supervise.health import IMU_SATURATION
from coiltrack.protocol import schema
from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID

#: chi-square 99.9 % quantile, 3 degrees of freedom (scipy.stats.chi2.ppf(0.999, 3))
CHI2_999_3 = 16.266236196238129
#: a fault's recovery is looked for this long after its end (s)
RECOVERY_HORIZON_S = 30.0
#: the window over which the recovered error is measured (s)
RECOVERY_WINDOW_S = 1.0
#: step of the recovery search (s)
RECOVERY_STEP_S = 0.1
#: events count for a fault received up to this long after it ended (s)
REPORT_GRACE_S = 3.0
#: the FAULT_EVENT codes that report each timed fault kind (any one of them)
EXPECTED_EVENTS = {
    "node_off": ("EVT_NODE_LOST",),
    "sat": ("EVT_SATURATION",),
    "open_circuit": ("EVT_COIL_FAULT",),
    "short": ("EVT_COIL_FAULT",),
    "overheat": ("EVT_COIL_FAULT",),
    "sag": ("EVT_COIL_FAULT",),
    "metal": ("EVT_DISTORTION",),
    "clock_step": ("EVT_CLOCK_STEP",),
}


def _evt_names() -> dict[int, str]:
    return {getattr(schema, n): n for n in dir(schema) if n.startswith("EVT_")}


def overconfident(msg, true_p) -> bool:
    """Is the position error of ``msg`` (a POSE) outside the 99.9 % chi-square bound
    (3 degrees of freedom) of its own reported variances?"""
    e = (msg.px - true_p[0], msg.py - true_p[1], msg.pz - true_p[2])
    d2 = 0.0
    for ei, v in zip(e, (msg.var_px, msg.var_py, msg.var_pz)):
        if not v > 0.0:
            return True          # a zero variance claims certainty no error can meet
        d2 += ei * ei / v
    return not d2 <= CHI2_999_3


def fused_trace(rec) -> tuple[np.ndarray, np.ndarray]:
    """True times (s) and position errors (m) of the valid fused poses a recorder holds."""
    ft, fe = [], []
    for rp in rec.poses:
        m = rp["msg"]
        if m.status & POSE_VALID and m.status & POSE_FUSED:
            ft.append(rec.master_to_true(m.t_us) * 1e-6)
            fe.append(math.dist((m.px, m.py, m.pz), rp["true_p"]))
    return np.array(ft), np.array(fe)


def fault_keys(bench, reference_level_mm: float | None = None, reference=None) -> dict:
    """The keys of the module docstring for a finished bench run; ``reference``: the
    no-fault run's :func:`fused_trace` (times s, errors m), or None."""
    rec = bench.recorder
    n_valid = n_over = n_over_f = n_over_m = 0
    ft, fe = [], []            # true time (s) and position error (m) of the valid fused poses
    ot = []                    # true time (s) of the overconfident ones
    for rp in rec.poses:
        m = rp["msg"]
        if not m.status & POSE_VALID:
            continue
        n_valid += 1
        if overconfident(m, rp["true_p"]):
            n_over += 1
            ot.append(rec.master_to_true(m.t_us) * 1e-6)
            if m.status & POSE_FUSED:
                n_over_f += 1
            else:
                n_over_m += 1
        if m.status & POSE_FUSED:
            ft.append(rec.master_to_true(m.t_us) * 1e-6)
            fe.append(math.dist((m.px, m.py, m.pz), rp["true_p"]))
    out = {
        "poses_overconfident": n_over,
        "overconfident_fraction": round(n_over / n_valid, 5) if n_valid else None,
        "overconfidence": {"fused": n_over_f, "magnetic": n_over_m, "chi2_bound": round(CHI2_999_3, 3)},
    }
    timed = list(bench.faults.timed)
    ft_a, fe_a = np.array(ft), np.array(fe)
    level = reference_level_mm
    if level is None and fe_a.size:
        keep = np.ones(fe_a.size, bool)
        for f in timed:
            t0 = f.t_on_us * 1e-6
            t1 = (f.t_off_us * 1e-6 if f.t_off_us is not None else math.inf) + RECOVERY_HORIZON_S
            keep &= ~((ft_a >= t0) & (ft_a < t1))
        if keep.any():
            level = float(np.sqrt(np.mean(fe_a[keep] ** 2))) * 1e3
    out["no_fault_level_mm"] = None if level is None else round(level, 3)
    ends = [f.t_off_us for f in timed if f.t_off_us is not None]
    if ends and fe_a.size:
        sel = ft_a >= max(ends) * 1e-6
        out["fused_rms_after_faults_mm"] = round(float(np.sqrt(np.mean(fe_a[sel] ** 2))) * 1e3, 3) if sel.any() else None
    out.update(recovery_keys(ft_a, fe_a, timed, level, reference))
    out["faults_reported"], out["faults_unreported"] = reported_faults(rec.events, timed)
    # where the overconfident poses were: in a fault window or the REPORT_GRACE_S after it, or elsewhere
    ot_a = np.array(ot)
    by, inside = {}, np.zeros(ot_a.size, bool)
    for f in timed:
        t1 = (f.t_off_us if f.t_off_us is not None else f.t_on_us) * 1e-6 + REPORT_GRACE_S
        sel = (ot_a >= f.t_on_us * 1e-6) & (ot_a < t1)
        by[f.describe()] = int(sel.sum())
        inside |= sel
    by["outside fault windows"] = int((~inside).sum())
    out["overconfident_by_fault"] = by
    return out


def event_name(ev, names: dict[int, str]) -> str:
    """The report's name of a FAULT_EVENT: its ``EVT_*`` name, and ``EVT_SATURATION_IMU`` for a
    saturation the firmware raised for an IMU (detail bit ``health.IMU_SATURATION``), which does
    not report a magnetometer's."""
    name = names.get(ev.code, f"code_{ev.code}")
    if name == "EVT_SATURATION" and ev.detail & IMU_SATURATION:
        return "EVT_SATURATION_IMU"
    return name


def reported_faults(events, timed) -> tuple[dict, list]:
    """Per timed fault, the event names received from its start to ``REPORT_GRACE_S`` after its
    end; and the faults none of whose :data:`EXPECTED_EVENTS` came. ``events``: (master time us,
    FAULT_EVENT) pairs."""
    names = _evt_names()
    rep, unrep = {}, []
    for f in timed:
        t0 = f.t_on_us
        t1 = (f.t_off_us if f.t_off_us is not None else math.inf) + REPORT_GRACE_S * 1e6
        got = sorted({event_name(ev, names) for t, ev in events if t0 <= t <= t1})
        rep[f.describe()] = got
        want = EXPECTED_EVENTS.get(f.kind)
        if want and not any(w in got for w in want):
            unrep.append(f.describe())
    return rep, unrep


def recovery_keys(ft, fe, timed, level_mm: float | None, reference=None) -> dict:
    """``fault_recovery_s`` (per fault of ``timed``, :func:`recovery_time`) and
    ``recovery_reference`` (what the error was held against; only with a timed fault) of the
    fused errors ``fe`` (m) at true times ``ft`` (s)."""
    out = {"fault_recovery_s": {f.describe(): recovery_time(ft, fe, f, level_mm, reference) for f in timed}}
    if timed:
        out["recovery_reference"] = "level" if reference is None else "no-fault run"
    return out


def recovery_time(ft, fe, fault, level_mm: float | None, reference=None) -> float | None:
    """Seconds from ``fault``'s end (its start if it has none) until the RMS of the
    valid fused errors ``fe`` (m) at true times ``ft`` (s) over the next
    ``RECOVERY_WINDOW_S`` is at most twice ``level_mm``, or, given the no-fault
    run's trace ``reference`` = (times s, errors m), at most twice the larger of
    ``level_mm`` and that run's RMS error over the same window (a window where it
    has fewer than two valid fused poses is held to the level); None when not
    within ``RECOVERY_HORIZON_S`` (or nothing to measure)."""
    if level_mm is None or not len(ft):
        return None
    t_end = (fault.t_off_us if fault.t_off_us is not None else fault.t_on_us) * 1e-6
    rt, re = reference if reference is not None else (np.zeros(0), np.zeros(0))
    k = 0
    while k * RECOVERY_STEP_S <= RECOVERY_HORIZON_S:
        t = t_end + k * RECOVERY_STEP_S
        sel = (ft >= t) & (ft < t + RECOVERY_WINDOW_S)
        ref = (rt >= t) & (rt < t + RECOVERY_WINDOW_S)
        lim = 2.0 * max(level_mm * 1e-3, math.sqrt(float(np.mean(re[ref] ** 2))) if ref.sum() >= 2 else 0.0)
        if sel.sum() >= 2 and math.sqrt(float(np.mean(fe[sel] ** 2))) <= lim:
            return round(k * RECOVERY_STEP_S, 2)
        if t > ft[-1]:
            return None
        k += 1
    return None
