"""Bench report: accuracy against ground truth, the Cramer-Rao bound for the
same geometry and noise, rates, link counters and pulse-window checks."""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.rotation import matrix_from_quat
from coiltrack.hil.crlb import crlb_position_rms
from coiltrack.protocol.schema import POSE_DISTORTED, POSE_FUSED, POSE_INCONSISTENT, POSE_VALID
from .faultreport import fault_keys
from .jsonout import write

#: distance bands of the per-range breakdown, cm
RANGE_BANDS_CM = ((10, 30), (30, 45), (45, 60), (60, 90))


def is_wall_clock(key: str) -> bool:
    """A report key measured on the wall clock (tick execution, jitter, speed), which differs
    from run to run of the same seed; every other figure is a function of scenario, seed,
    duration and configuration."""
    return key.startswith("tick_") or key in ("wall_s", "speedup", "deadline_misses", "cpu_deadline_misses")


def _rot_angle(Ra, Rb) -> float:
    c = (float(np.trace(Ra.T @ Rb)) - 1.0) * 0.5
    return math.acos(max(-1.0, min(1.0, c)))


def window_violations(bench) -> int:
    """Count windows that used a sample outside the flat part of the true pulse.

    Compared on TRUE time (``hil.bench.window_truth``): the true instants of
    the first and last used samples (the bench knows which sample carried
    which time stamp, whatever the node's clock drift and sync error) against
    the true edges the driver produced; the flat part starts when the L/R
    current and the eddy fields of every conductor in the world have settled
    to 1e-3 of the pulse's field (``World.flat_start_us``) and ends at the
    true end edge.
    """
    from coiltrack.hil.bench import window_truth

    return sum(1 for r in window_truth(bench) if r.get("violation"))


#: battery of the thesis source: four AA cells (thesis sec 5.2.2), 6 V x 2.4 Ah
BATTERY_WH = 6.0 * 2.4


def energy(executed, world, duration_s: float, battery_wh: float = BATTERY_WH) -> dict:
    """Coil charge and energy of the pulses the driver executed.

    ``coil_energy_j`` is the energy dissipated in the windings, I^2 R t per
    pulse (flat-top approximation; the L/R edges are a few tenths of a
    millisecond of a 60 ms pulse). The driver draws ``I`` from the supply for
    the length of the pulse, so the battery delivers ``V * I * t``;
    ``projected_runtime_h`` is the battery energy over that mean power.
    """
    charge = coil_e = supply_e = 0.0
    for e in executed:
        t = (e["end_us"] - e["start_us"]) * 1e-6
        i = abs(e["current_a"])
        r = world.coils[e["coil"]].resistance
        charge += i * t
        coil_e += i * i * r * t
        supply_e += world.supply_v * i * t
    p_mean = supply_e / duration_s if duration_s > 0 else 0.0
    lengths = sorted(e["end_us"] - e["start_us"] for e in executed)
    return {
        "pulse_ms": round(lengths[len(lengths) // 2] * 1e-3, 3) if lengths else None,   # median executed pulse
        "pulses_per_s": round(len(executed) / duration_s, 3) if duration_s > 0 else 0.0,
        "coil_charge_c": round(charge, 4),
        "coil_energy_j": round(coil_e, 4),
        "supply_energy_j": round(supply_e, 4),
        "projected_runtime_h": round(battery_wh / p_mean, 2) if p_mean > 0 else None,
    }


def _core_of(cfg) -> str:
    """The numeric core a firmware of ``cfg`` runs in this install (``coiltrack.firmware.core``)."""
    from coiltrack.firmware.core import resolve

    return resolve(getattr(getattr(cfg, "core", None), "impl", "compiled"))


def _rms(a) -> float:
    return float(np.sqrt(np.mean(a ** 2))) if a.size else float("nan")


def build(bench, fw_status: dict, duration_s: float, transport: str, cfg) -> dict:
    """The bench report of a finished run: the poses against the ground truth, the bound, the
    coil energy, the link, the faults and each scenario's own keys."""
    rec = bench.recorder
    world = bench.world
    errs = _PoseErrors(bench, cfg)
    pe, ae, cb = np.array(errs.pos), np.array(errs.ang), np.array(errs.crlb)
    rms = _rms
    dist = [float(np.linalg.norm(rp["true_p"])) for rp in rec.poses]
    from coiltrack.hil.bench import bench_metrics, fault_summary

    truth = bench_metrics(bench, cfg.pulse.fall_us, cfg.pulse.baseline_us)
    rep = {
        "scenario": bench.scenario.name,
        "seed": bench.seed,
        "transport": transport,
        "core": fw_status.get("core") or _core_of(cfg),     # the numeric core that ran ([core] impl)
        "duration_s": duration_s,
        "poses": int(pe.size),
        "poses_invalid": errs.invalid,
        "position_rms_mm": round(rms(pe) * 1e3, 3),
        "position_p95_mm": round(float(np.percentile(pe, 95)) * 1e3, 3) if pe.size else None,
        "orientation_rms_deg": round(math.degrees(rms(ae)), 3),
        "crlb_position_rms_mm": round(rms(cb) * 1e3, 3),
        "pose_rate_hz": round(pe.size / duration_s, 3) if duration_s > 0 else 0.0,
        "by_range": _by_range(rec, pe, ae, cb),
        "distance_range_cm": [round(min(dist) * 100, 1), round(max(dist) * 100, 1)] if dist else None,
        "frames_rx": fw_status.get("rx_frames_ok", 0),
        "frames_bad": fw_status.get("rx_frames_bad", 0) + bench.emulator.decoder.frames_bad,
        "pulse_window_violations": truth.pop("pulse_window_violations"),
        "windows_flagged": fw_status.get("windows_flagged", 0),
        "coil_pulses": len(bench.driver.executed),
        "mag_samples": bench.sensor.samples,
        "source_moving": bool(getattr(world, "source_moving", False)),
    }
    if len(cfg.link.sensor_ids) > 1:
        rep["sensors"] = _sensor_keys(cfg, errs.per_node)
    rep.update(energy(bench.driver.executed, world, duration_s))
    if hasattr(bench.driver, "accuracy_report"):
        rep["coil_driver"] = bench.driver.accuracy_report()
    rep.update(truth)
    rep["faults"] = fault_summary(bench, fw_status)
    _tail_keys(rep, bench, fw_status, np.array(errs.fused), duration_s, cfg)
    return rep


class _PoseErrors:
    """The errors of a run's valid poses against the ground truth: magnetic (position, angle,
    the position bound at each), fused (distance, position error, angle error), per sensor node,
    and the count of invalid poses."""

    def __init__(self, bench, cfg):
        rec = bench.recorder
        world = bench.world
        sigma_amp, truth_amp = _amplitude_sigma(bench, cfg)
        currents = np.array([c.current for c in cfg.source.coils])
        self.pos, self.ang, self.crlb, self.fused = [], [], [], []
        self.invalid = 0
        self.per_node: dict[int, list] = {}
        for rp in rec.poses:
            m = rp["msg"]
            if not m.status & POSE_VALID:
                self.invalid += 1
                continue
            p = np.array([m.px, m.py, m.pz])
            R = matrix_from_quat(np.array([m.qw, m.qx, m.qy, m.qz]))
            if m.status & POSE_FUSED:
                self.fused.append((float(np.linalg.norm(rp["true_p"])), float(np.linalg.norm(p - rp["true_p"])),
                                   _rot_angle(R, rp["true_R"])))
                continue
            self.pos.append(float(np.linalg.norm(p - rp["true_p"])))
            self.ang.append(_rot_angle(R, rp["true_R"]))
            inp = truth_amp.for_pose(rp, len(world.coils)) if truth_amp is not None else None
            self.crlb.append(crlb_position_rms(world, rp["true_p"], rp["true_R"], *(inp or (currents, sigma_amp))))
            rp["crlb_m"] = self.crlb[-1]            # per pose, for the pose table (tools.outputs.posecsv)
            self.per_node.setdefault(m.node, []).append((self.pos[-1], self.ang[-1]))


def _amplitude_sigma(bench, cfg):
    """The amplitude sigma of the bound (the windows' median sample counts, or the AC
    demodulator's), and for DC pulses the bound's ground-truth currents and counts."""
    rec = bench.recorder
    n_used = [w.n_used for _, w in rec.windows if w.n_used]
    n_base = [w.n_base for _, w in rec.windows if w.n_base]
    nu = float(np.median(n_used)) if n_used else 1.0
    nb = float(np.median(n_base)) if n_base else 1.0
    sigma_amp = bench.scenario.sensor.noise_t * math.sqrt(1.0 / nu + 1.0 / nb)
    amp_sigma = getattr(bench.scenario.sensor, "amplitude_sigma", None)
    if amp_sigma is not None and amp_sigma(cfg) is not None:      # AC blocks: the demodulator's sigma
        return np.broadcast_to(amp_sigma(cfg), (3, len(cfg.source.coils))), None
    from coiltrack.hil.crlb import TruthAmplitudes

    return sigma_amp, TruthAmplitudes(bench, bench.scenario.sensor.noise_t, cfg.pulse.baseline_us)


def _by_range(rec, pe, ae, cb) -> dict:
    """The magnetic poses' figures in each band of :data:`RANGE_BANDS_CM`."""
    vdist = np.array([float(np.linalg.norm(rp["true_p"])) for rp in rec.poses
                      if rp["msg"].status & POSE_VALID and not rp["msg"].status & POSE_FUSED])
    by_range = {}
    for lo, hi in RANGE_BANDS_CM:
        sel = (vdist >= lo / 100) & (vdist < hi / 100)
        if np.any(sel):
            by_range[f"{lo}-{hi}cm"] = {"poses": int(sel.sum()), "position_rms_mm": round(_rms(pe[sel]) * 1e3, 2),
                                        "crlb_position_rms_mm": round(_rms(cb[sel]) * 1e3, 2),
                                        "orientation_rms_deg": round(math.degrees(_rms(ae[sel])), 2)}
    return by_range


def _sensor_keys(cfg, per_node: dict) -> list:
    """Every sensor's own figures (magnetic poses), in node order."""
    out = []
    for node in cfg.link.sensor_ids:
        e = np.array(per_node.get(node, []), dtype=float).reshape(-1, 2)
        out.append({"node": int(node), "poses": int(e.shape[0]), "position_rms_mm": round(_rms(e[:, 0]) * 1e3, 3),
                    "orientation_rms_deg": round(math.degrees(_rms(e[:, 1])), 3)})
    return out


def _tail_keys(rep: dict, bench, fw_status: dict, fused, duration_s: float, cfg) -> None:
    """The link, signing, fused, AC, consistency, quality, adaptive and fault keys, the paper's
    figure and the scenario's own keys, in that order."""
    rec = bench.recorder
    if hasattr(bench.link, "counts"):
        rep["link_faults"] = dict(bench.link.counts)
    if getattr(bench, "verifier", None) is not None:
        # what the nodes did with the firmware's signatures (commands accepted, refused by kind)
        rep["signing"] = {**bench.verifier.counters(), "firmware_signed": fw_status.get("tx_signed", 0)}
    if len(fused):
        _fused_keys(rep, fused, duration_s, fw_status, _rms)
    # consistency flags of the valid poses (NIS monitor, health), and the adaptive mode's counters
    if "ac_blocks" in fw_status:
        _ac_keys(rep, fw_status)
        rep.update(_ac_energy(bench, duration_s))
    rep["poses_distorted"] = sum(1 for rp in rec.poses if rp["msg"].status & POSE_VALID
                                 and rp["msg"].status & POSE_DISTORTED)
    rep["poses_inconsistent"] = sum(1 for rp in rec.poses if rp["msg"].status & POSE_VALID
                                    and rp["msg"].status & POSE_INCONSISTENT)
    rep.update(quality_keys(rec.poses))
    if "adaptive_pulses" in fw_status:
        rep["adaptive"] = {k[len("adaptive_"):]: v for k, v in fw_status.items() if k.startswith("adaptive_")}
    rep.update(fault_keys(bench))
    ref = bench.scenario.reference
    if ref:
        rep["paper"] = ref
    if getattr(bench.scenario, "report_extra", None) is not None:
        rep.update(bench.scenario.report_extra(bench, rep, cfg))


def quality_keys(poses) -> dict:
    """``quality_error_rank_corr``: minus Spearman's rank correlation (``scipy.stats.spearmanr``)
    of POSE.quality with the true position error over the valid magnetic poses, so that a quality
    falling as the error grows (the intent) is POSITIVE (1: the error's order exactly reversed;
    None: fewer than 3 poses, a constant quality or error, or scipy missing); ``quality_mean``."""
    q, e = [], []
    for rp in poses:
        m = rp["msg"]
        if m.status & POSE_VALID and not m.status & POSE_FUSED and hasattr(m, "quality"):
            q.append(float(m.quality))
            e.append(float(np.linalg.norm(np.array([m.px, m.py, m.pz]) - rp["true_p"])))
    out = {"quality_error_rank_corr": None, "quality_mean": round(float(np.mean(q)), 1) if q else None}
    if len(q) < 3 or np.ptp(q) == 0 or np.ptp(e) == 0:
        return out
    try:
        from scipy.stats import spearmanr
    except ImportError:
        return out
    rho = float(spearmanr(q, e).statistic)
    out["quality_error_rank_corr"] = round(-rho, 3) if math.isfinite(rho) else None
    return out


def _fused_keys(rep: dict, fz: np.ndarray, duration_s: float, fw_status: dict, rms) -> None:
    """With fused poses (``POSE_FUSED``, the thesis ch. 6 filter at the IMU
    rate) the headline keys describe them and the magnetic-only solutions of the
    same run move to ``magnetic_*``."""
    for k in ("poses", "position_rms_mm", "position_p95_mm", "orientation_rms_deg", "pose_rate_hz"):
        rep["magnetic_" + k] = rep[k]
    rep["magnetic_by_range"] = rep.pop("by_range")
    fd, fe, fa = fz[:, 0], fz[:, 1], fz[:, 2]
    rep["poses"] = int(fe.size)
    rep["position_rms_mm"] = round(rms(fe) * 1e3, 3)
    rep["position_p95_mm"] = round(float(np.percentile(fe, 95)) * 1e3, 3)
    rep["orientation_rms_deg"] = round(math.degrees(rms(fa)), 3)
    rep["pose_rate_hz"] = round(fe.size / duration_s, 3)
    mag = rep["magnetic_position_rms_mm"]
    rep["fused_to_magnetic_position"] = round(rep["position_rms_mm"] / mag, 3) if mag else None
    by_range = {}
    for lo, hi in RANGE_BANDS_CM:
        sel = (fd >= lo / 100) & (fd < hi / 100)
        if np.any(sel):
            mb = rep["magnetic_by_range"].get(f"{lo}-{hi}cm", {})
            by_range[f"{lo}-{hi}cm"] = {"poses": int(sel.sum()), "position_rms_mm": round(rms(fe[sel]) * 1e3, 2),
                                        "orientation_rms_deg": round(math.degrees(rms(fa[sel])), 2),
                                        "magnetic_position_rms_mm": mb.get("position_rms_mm"),
                                        "magnetic_orientation_rms_deg": mb.get("orientation_rms_deg"),
                                        "crlb_position_rms_mm": mb.get("crlb_position_rms_mm")}
    rep["by_range"] = by_range
    rep["fusion"] = {k: v for k, v in fw_status.items()
                     if k.startswith(("fusion_", "fused_", "imu_", "compass_", "source_imu"))}


def _ac_keys(rep: dict, fw_status: dict) -> None:
    """AC excitation: ``excitation``, the magnetic pose rate and the demodulator's figures."""
    rep["excitation"] = "ac"
    rep.setdefault("magnetic_pose_rate_hz", rep["pose_rate_hz"])
    rep["ac_quadrature_ratio_mean"] = round(fw_status["ac_quadrature_ratio_mean"], 5)
    rep["ac_quadrature_ratio_max"] = round(fw_status["ac_quadrature_ratio_max"], 5)
    rep["ac"] = {k[len("ac_"):]: (round(v, 5) if isinstance(v, float) else v)
                 for k, v in fw_status.items() if k.startswith("ac_")}


def _ac_energy(bench, duration_s: float, battery_wh: float = BATTERY_WH) -> dict:
    """Coil charge and energy of AC drive: ``|I|^2 R / 2`` per coil while on; a linear driver from
    the supply draws the rectified mean ``(2/pi) |I|``, so the battery delivers ``V (2/pi) |I| t``."""
    drv = getattr(bench.driver, "ac_driver", None)
    plans = getattr(bench.driver, "plans", {})
    if drv is None or not plans:
        return {}
    on_s = max(0.0, duration_s - min(p["on_true_us"] for p in plans.values()) * 1e-6)
    world = bench.world
    charge = coil_e = 0.0
    for k, d in enumerate(drv.drives):
        if d is None:
            continue
        i = abs(d.current)
        charge += 2.0 / math.pi * i * on_s
        coil_e += 0.5 * i * i * world.coils[k].resistance * on_s
    supply_e = world.supply_v * charge
    p_mean = supply_e / duration_s if duration_s > 0 else 0.0
    return {"pulses_per_s": 0.0, "coil_charge_c": round(charge, 4), "coil_energy_j": round(coil_e, 4),
            "supply_energy_j": round(supply_e, 4),
            "projected_runtime_h": round(battery_wh / p_mean, 2) if p_mean > 0 else None}


def format_table(rep: dict) -> str:
    """The report as the two-column table ``coiltrack bench`` prints."""
    rows = (_accuracy_rows(rep) + _energy_rows(rep) + _comparison_rows(rep) + _flag_rows(rep)
            + _detail_rows(rep))
    if rep.get("distance_range_cm"):
        rows.insert(4, ("distance range", f'{rep["distance_range_cm"][0]}-{rep["distance_range_cm"][1]} cm'))
    if not rep["poses"] and "magnetic_position_rms_mm" not in rep:    # no pose: no error to show
        rows = [r for r in rows if r[0] not in ("position RMS", "orientation RMS")]
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{w}}  {v}" for k, v in rows)


def _accuracy_rows(rep: dict) -> list:
    """The run, its poses and their accuracy (fused and magnetic)."""
    rows = [
        ("scenario", rep["scenario"]), ("seed", rep["seed"]), ("transport", rep["transport"]),
        ("duration", f'{rep["duration_s"]:.1f} s'),
        ("poses", f'{rep["poses"]} valid, {rep["poses_invalid"]} invalid ({rep["pose_rate_hz"]:.2f} Hz)'),
        ("position RMS", f'{rep["position_rms_mm"]:.2f} mm  (CRLB {rep["crlb_position_rms_mm"]:.2f} mm)'),
        ("orientation RMS", f'{rep["orientation_rms_deg"]:.2f} deg'),
    ]
    if "magnetic_position_rms_mm" in rep:
        rows[5] = ("position RMS (fused)", f'{rep["position_rms_mm"]:.2f} mm  ({rep["fused_to_magnetic_position"]} '
                                           f'of magnetic only)')
        rows[6] = ("orientation RMS (fused)", f'{rep["orientation_rms_deg"]:.2f} deg')
        rows += [("magnetic only", f'{rep["magnetic_position_rms_mm"]:.2f} mm (CRLB {rep["crlb_position_rms_mm"]:.2f}'
                                   f' mm), {rep["magnetic_orientation_rms_deg"]:.2f} deg, '
                                   f'{rep["magnetic_poses"]} poses')]
    if rep.get("source_moving"):
        rows.append(("source moving", "true (body-worn: its own IMU and magnetometer module)"))
    return rows


def _energy_rows(rep: dict) -> list:
    """The link, the pulse windows, the coil energy and the driver."""
    rows = [
        ("frames rx / bad", f'{rep["frames_rx"]} / {rep["frames_bad"]}'),
        ("pulse window violations", rep["pulse_window_violations"]),
        ("coil energy", f'{rep["coil_energy_j"]:.2f} J in {rep["pulses_per_s"]:.2f} pulses/s'
                        + (f'; battery {rep["projected_runtime_h"]} h (4 AA)' if rep["projected_runtime_h"] else '')),
    ]
    cd = rep.get("coil_driver")
    if cd and cd.get("current_error_rms") is not None:
        rows.append(("coil driver", f'current error {cd["current_error_rms"] * 100:.2f} % rms (static gain '
                                    f'+-{cd["static_gain_error_max"] * 100:.1f} %), winding up to '
                                    f'{cd["winding_temp_max_c"]:.1f} C (R +{cd["resistance_rise_max"] * 100:.2f} %), '
                                    f'{cd["pulses_voltage_limited"]} pulses voltage-limited'))
    return rows


def _comparison_rows(rep: dict) -> list:
    """The fixed cycle of the same trajectory, the uncalibrated and the perfect bench."""
    rows = []
    if "fixed_position_rms_mm" in rep:
        rows += [("fixed X/Y/Z cycle", f'{rep["fixed_position_rms_mm"]:.2f} mm, '
                                       f'{rep["fixed_orientation_rms_deg"]:.2f} deg, '
                                       f'{rep["fixed_coil_energy_j"]:.2f} J in {rep["fixed_pulses_per_s"]:.2f} '
                                       f'pulses/s; battery '
                                       f'{rep["fixed_projected_runtime_h"]} h (same trajectory and seed)'),
                 ("this run / fixed", f'position RMS x{rep["position_rms_ratio"]}, orientation RMS '
                                      f'x{rep["orientation_rms_ratio"]}, coil energy x{rep["energy_ratio"]}')]
    if "perfect_position_rms_mm" in rep:
        # an imperfect-bench scenario: the same trajectory and seed uncalibrated and on the perfect bench
        rows += [("calibration", rep.get("calibration") or "none"),
                 ("uncalibrated", f'{rep["uncalibrated_position_rms_mm"]:.2f} mm, '
                                  f'{rep["uncalibrated_orientation_rms_deg"]:.2f} deg (x{rep["uncalibrated_over_calibrated_position"]}'
                                  f', x{rep["uncalibrated_over_calibrated_orientation"]} of this run)'),
                 ("perfect bench", f'{rep["perfect_position_rms_mm"]:.2f} mm, {rep["perfect_orientation_rms_deg"]:.2f} deg '
                                   f'(this run x{rep["calibrated_over_perfect_position"]}, '
                                   f'x{rep["calibrated_over_perfect_orientation"]} of it)')]
    return rows


def _flag_rows(rep: dict) -> list:
    """AC excitation, flagged poses, timing, faults and overconfidence."""
    rows = []
    if rep.get("excitation") == "ac":
        rows.append(("AC excitation", f'{rep["magnetic_pose_rate_hz"]:.1f} magnetic poses/s; quadrature / in-phase '
                                      f'{rep["ac_quadrature_ratio_mean"]:.4f} mean, {rep["ac_quadrature_ratio_max"]:.4f} max'))
    if rep.get("poses_distorted") or rep.get("poses_inconsistent"):
        rows.append(("poses flagged", f'{rep["poses_distorted"]} distorted, {rep["poses_inconsistent"]} inconsistent'))
    for k in ("tick_jitter_us_median", "tick_jitter_us_p99", "tick_jitter_us_max", "deadline_misses",
              "cpu_deadline_misses", "latency_ms_p50", "latency_ms_p99", "pulse_window_min_margin_us"):
        if rep.get(k) is not None:
            rows.append((k, rep[k]))
    fl = rep.get("faults")
    if fl and (fl["injected"].get("switches") or fl["reported"].get("events")):
        rows.append(("faults injected", ", ".join(fl["injected"]["switches"]) or "-"))
        ev = fl["reported"]["events"]
        rows.append(("faults reported", ", ".join(f"{k} x{v}" for k, v in sorted(ev.items())) or "-"))
        if rep.get("fault_recovery_s"):
            rows.append(("fault recovery", ", ".join(f"{k} {'-' if v is None else f'{v:g} s'}" for k, v in rep[
                "fault_recovery_s"].items()) + f' (against the {rep.get("recovery_reference", "level")})'))
        if rep.get("faults_unreported"):
            rows.append(("faults unreported", ", ".join(rep["faults_unreported"])))
    if rep.get("overconfident_fraction") is not None:
        rows.append(("overconfident poses", f'{rep["poses_overconfident"]} ({rep["overconfident_fraction"]:.4f} of '
                                            f'the valid; 99.9 % chi-square, 3 dof)'))
    return rows


def _detail_rows(rep: dict) -> list:
    """Each sensor, signing, interruption, the paper's figure and the range bands."""
    rows = []
    for sn in rep.get("sensors", []):
        rows.append((f"  sensor {sn['node']}", f"{sn['position_rms_mm']:.1f} mm, {sn['orientation_rms_deg']:.2f} deg, "
                                              f"{sn['poses']} poses"))
    sg = rep.get("signing")
    if sg:
        rows.append(("signed commands", f'{sg["firmware_signed"]} sent, {sg["accepted"]} accepted; refused '
                                        f'{sg["unsigned"]} unsigned, {sg["forged"]} forged, {sg["replayed"]} replayed'))
    if rep.get("interrupted"):
        rows.append(("interrupted", f'stopped by {rep.get("stopped_by")}: the figures are of the part that ran'))
    if "paper" in rep:
        p = rep["paper"]
        rows.append(("paper", f'{p.get("position_rms_mm")} mm, {p.get("orientation_rms_deg")} deg ({p.get("source")})'))
    for band, b in rep.get("by_range", {}).items():
        if "magnetic_position_rms_mm" in b:
            rows.append((f"  at {band}", f'{b["position_rms_mm"]:.1f} mm, {b["orientation_rms_deg"]:.1f} deg fused; '
                                         f'{b["magnetic_position_rms_mm"]} mm (CRLB {b["crlb_position_rms_mm"]}), '
                                         f'{b["magnetic_orientation_rms_deg"]} deg magnetic'))
            continue
        rows.append((f"  at {band}", f'{b["position_rms_mm"]:.1f} mm (CRLB {b["crlb_position_rms_mm"]:.1f}), '
                                     f'{b["orientation_rms_deg"]:.1f} deg, {b["poses"]} poses'))
    return rows


def write_json(rep: dict, path: str) -> None:
    """The report as strict JSON (``null`` for a figure that is not a finite number)."""
    write(path, rep)
