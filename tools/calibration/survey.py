"""The distortion survey: fit the room's residual-field map and write it as ``[distortion]``.

``coiltrack calibrate --method survey`` (and the ``steel-table`` report) runs three steps:

1. **Jig poses** (:func:`jig_poses`): a grid over the working volume of roetenberg-bench (thesis
   ``seeds/002_cd7f1fdb7fc67471.txt`` sec 5.3: 15-80 cm, azimuth +-55 deg, elevation +-45 deg),
   ``radii x azimuths x elevations`` points with seeded orientations, as a positioning jig would
   hold the sensor (Anser's 7x7 / 9x9 grids are the same idea on one plane).
2. **Survey amplitudes** (:func:`survey_amplitudes`): at each jig pose, each coil's pulse
   amplitude in the sensor frame, ``S[:, j] = I_j R^T (B_j(p) + sum of the objects' responses)``
   (the settled field change a pulse window measures, the bench's physics: ``hil.world``), with
   the magnetometer's noise averaged over ``bursts`` bursts (sigma per amplitude
   ``noise_t sqrt(1/n_pulse + 1/n_base) / sqrt(bursts)``).
3. **The fit** (:func:`fit_survey`): the residual field of coil ``j`` per ampere in the source
   frame, ``r = R S[:, j] / I_j - B_j^nom(p)`` against the firmware's own nominal signal model
   (``coiltrack.firmware.model.signal``: what the map must correct), is fitted with ``K``
   equivalent dipoles per coil (``coiltrack.firmware.model.distortion``): for given positions the
   moments are linear (least squares), the positions found by multi-start Gauss-Newton on the
   projected residual (variable projection), one dipole at a time, then all jointly
   (``scipy.optimize.least_squares``). Uncertainties: ``sqrt(diag((J^T J)^-1)) * s`` with ``s``
   the residual's RMS (one sigma); the fit's residual RMS per unit current is reported.
"""
from __future__ import annotations

import dataclasses
import math
import os
import tempfile

import numpy as np
from coiltrack.tools.outputs import report as report_mod
from coiltrack.tools.outputs.report import RANGE_BANDS_CM

__all__ = ["jig_poses", "survey_amplitudes", "fit_survey", "survey_table", "correction_report"]

MU0_4PI = 1e-7


def jig_poses(radii=(0.15, 0.2, 0.27, 0.36, 0.48, 0.62, 0.78), n_az: int = 7, n_el: int = 5,
              az_max_deg: float = 55.0, el_max_deg: float = 45.0, seed: int = 1):
    """``p`` (m, 3) and ``R`` (m, 3, 3) of the jig grid (module docstring), ``m = radii x n_az x n_el``."""
    from scipy.spatial.transform import Rotation

    az = np.radians(np.linspace(-az_max_deg, az_max_deg, n_az))
    el = np.radians(np.linspace(-el_max_deg, el_max_deg, n_el))
    r, a, e = np.meshgrid(np.asarray(radii, float), az, el, indexing="ij")
    r, a, e = r.ravel(), a.ravel(), e.ravel()
    p = np.stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a), r * np.sin(e)], axis=1)
    R = Rotation.random(p.shape[0], random_state=np.random.default_rng([seed, 0x5EE7])).as_matrix()
    return p, R


def survey_amplitudes(world, p, R, currents, noise_t: float, n_pulse: float = 5.0, n_base: float = 5.0,
                      bursts: int = 10, seed: int = 1):
    """Per-coil pulse amplitudes ``S`` (m, 3, n) T in the sensor frame at the jig poses, and their
    sigma (T) (module docstring, step 2)."""
    rng = np.random.default_rng([seed, 0x5A4E])
    cur = np.asarray(currents, dtype=float)
    n = cur.size
    U = world.source.unit_fields(p)                      # (n, m, 3) T/A
    S = np.zeros((p.shape[0], 3, n))
    sigma = noise_t * math.sqrt(1.0 / n_pulse + 1.0 / n_base) / math.sqrt(bursts)
    for i in range(p.shape[0]):
        for k in range(n):
            u = U[k, i].copy()
            for obj in world.objects:
                if hasattr(obj, "coil_unit_field") and obj.active(0):
                    u += obj.coil_unit_field(world, k, p[i], R[i])
            S[i, :, k] = cur[k] * (R[i].T @ u) + rng.normal(0.0, sigma, 3)
    return S, sigma


def _nominal_fields(cfg, p):
    """The firmware's nominal per-ampere coil fields (n, m, 3) at ``p``: ``model.signal``."""
    from coiltrack.firmware.model.field import Coil
    from coiltrack.firmware.model.signal import SignalModel

    coils = [Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.source.coils]
    sm = SignalModel(coils, cfg.source.field_model)
    ones = [1.0] * len(coils)
    out = np.zeros((len(coils), p.shape[0], 3))
    for i in range(p.shape[0]):
        sm.fields(float(p[i, 0]), float(p[i, 1]), float(p[i, 2]), ones, False)
        out[:, i, :] = sm.B
    return out


def _dipole_basis(p, q):
    """(m, 3, 3): the field at ``p`` (m, 3) of a unit dipole at ``q`` along x, y, z (T per A m^2)."""
    d = p - q
    r2 = np.sum(d * d, axis=1)
    r = np.sqrt(r2)
    c = MU0_4PI / (r2 * r)
    G = 3.0 * d[:, :, None] * d[:, None, :] / r2[:, None, None] - np.eye(3)[None]
    return c[:, None, None] * G


def _design(p, qs):
    return np.concatenate([_dipole_basis(p, q).reshape(-1, 3) for q in qs], axis=1)   # (3m, 3K)


def _project(p, r, qs, w3):
    """Least-squares moments of dipoles at ``qs`` for the residual ``r`` (3m,), rows scaled by ``w3``
    (3m,): (moments (3K,), weighted remainder (3m,))."""
    A = _design(p, qs) * w3[:, None]
    mu, *_ = np.linalg.lstsq(A, r * w3, rcond=None)
    return mu, r * w3 - A @ mu


def _fit_coil(p, r, K: int, starts, w=None):
    """K dipoles for one coil's residual ``r`` (3m,): positions (K, 3), moments (K, 3); ``w``
    (m,) weights of the points (default 1)."""
    from scipy.optimize import least_squares

    w3 = np.ones(r.size) if w is None else np.repeat(np.asarray(w, float), 3)
    qs: list[np.ndarray] = []
    for _ in range(K):
        best = None
        for q0 in starts:
            try:
                sol = least_squares(lambda q: _project(p, r, qs + [q], w3)[1], q0, method="lm", max_nfev=200)
            except (ValueError, np.linalg.LinAlgError):
                continue
            c = float(np.sum(sol.fun ** 2))
            if np.all(np.isfinite(sol.x)) and (best is None or c < best[0]):
                best = (c, sol.x)
        if best is None:
            break
        qs.append(best[1])
    mu, _ = _project(p, r, qs, w3)
    x0 = np.concatenate([np.concatenate([q, mu[3 * k:3 * k + 3]]) for k, q in enumerate(qs)])

    def full(x):
        xs = x.reshape(-1, 6)
        return (r - _design(p, list(xs[:, :3])) @ xs[:, 3:].reshape(-1)) * w3

    sol = least_squares(full, x0, method="lm", max_nfev=400)
    x = sol.x.reshape(-1, 6)
    res = sol.fun / w3
    dof = max(res.size - x.size, 1)
    s = math.sqrt(float(sol.fun @ sol.fun) / dof)          # in weighted units
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s * s
        sig = np.sqrt(np.abs(np.diag(cov))).reshape(-1, 6)
    except np.linalg.LinAlgError:
        sig = np.full_like(x, np.inf)
    return x[:, :3], x[:, 3:], sig[:, :3], sig[:, 3:], res


def _starts(centre, distances=(0.5, 0.9, 1.5)):
    dirs = [np.array(v, float) for v in
            [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1),
             (1, 1, 1), (1, 1, -1), (1, -1, 1), (1, -1, -1), (-1, 1, 1), (-1, 1, -1), (-1, -1, 1), (-1, -1, -1)]]
    return [centre + d / np.linalg.norm(d) * s for d in dirs for s in distances]


def fit_survey(cfg, p, R, S, currents, dipoles_per_coil: int = 3, weight: str = "field",
               start_distances_m=(0.5, 0.9, 1.5)) -> tuple[dict, dict]:
    """The ``[distortion]`` table and a summary (residual RMS before and after, per coil) from the
    survey ``S`` (m, 3, n) at the jig poses ``(p, R)`` (module docstring, step 3). ``weight``:
    ``"position"`` weighs each point by ``|p| / |B_j^nom(p)|``, so the fit minimises the field error
    as the position error it causes (``dp ~ |p| dB / (3 |B|)`` for a dipole field: the far points,
    where the table's field is a larger part of the coil's, count most); ``"field"`` (default):
    unweighted, which on ``steel-table`` leaves a smaller relative field error at every range
    (0.66 % at 70 cm against 1.2 %: the far points' amplitudes are noisier).
    ``start_distances_m``: the multi-start positions lie at these distances from the coil centre
    in 14 directions (the 6 axes and the 8 diagonals)."""
    if weight not in ("position", "field"):
        raise ValueError(f"weight must be 'position' or 'field', got {weight!r}")
    cur = np.asarray(currents, dtype=float)
    nom = _nominal_fields(cfg, p)
    n = cur.size
    table = {"model": "dipoles", "coils": n}
    summary = {"points": int(p.shape[0]), "dipoles_per_coil": int(dipoles_per_coil), "coils": []}
    all_res = []
    for k in range(n):
        meas = np.einsum("mij,mj->mi", R, S[:, :, k]) / cur[k]      # source frame, per ampere
        r = (meas - nom[k]).reshape(-1)
        w = np.linalg.norm(p, axis=1) / np.linalg.norm(nom[k], axis=1) if weight == "position" else None
        if w is not None:
            w = w / np.mean(w)
        q, mu, sq, smu, res = _fit_coil(p, r, dipoles_per_coil, _starts(np.asarray(cfg.source.coils[k].center, float), start_distances_m), w)
        table[f"coil{k}_position_m"] = q.tolist()
        table[f"coil{k}_moment_am2_per_a"] = mu.tolist()
        table[f"coil{k}_position_m_sigma"] = sq.tolist()
        table[f"coil{k}_moment_am2_per_a_sigma"] = smu.tolist()
        all_res.append(res)
        summary["coils"].append({"residual_before_rms_t_per_a": float(np.sqrt(np.mean(r ** 2))),
                                 "residual_after_rms_t_per_a": float(np.sqrt(np.mean(res ** 2)))})
    rr = np.concatenate(all_res)
    table["residual_rms_t"] = float(np.sqrt(np.mean(rr ** 2)))
    table["n_points"] = int(p.shape[0])
    summary["residual_rms_t_per_a"] = table["residual_rms_t"]
    return table, summary


def survey_table(world, cfg, noise_t: float, seed: int = 1, dipoles_per_coil: int = 3, bursts: int = 50,
                 poses=None) -> tuple[dict, dict]:
    """Jig poses, amplitudes and fit in one call: ``(distortion table, summary)``."""
    p, R = poses if poses is not None else jig_poses(seed=seed)
    cur = [c.current for c in cfg.source.coils]
    S, sigma = survey_amplitudes(world, p, R, cur, noise_t, bursts=bursts, seed=seed)
    table, summary = fit_survey(cfg, p, R, S, cur, dipoles_per_coil)
    summary["amplitude_sigma_t"] = sigma
    return table, summary


def write_calibration(path, table: dict, summary: dict, extra: dict | None = None) -> None:
    """A calibration file holding the ``[distortion]`` table (and ``[meta]``)."""
    from coiltrack.firmware.calibration import dumps_toml

    meta = {"method": "survey", "residual_rms_t": table["residual_rms_t"], "poses": table["n_points"]}
    doc = dict(extra or {})
    doc.setdefault("meta", {}).update(meta)
    doc["distortion"] = table
    with open(path, "w") as fh:
        fh.write(dumps_toml(doc))


def record_survey(scenario, seed: int = 1, bursts: int = 50) -> dict:
    """A survey recording of the room of ``scenario`` (a Scenario such as ``steel-table``; its world
    for run seed ``seed``): the jig
    poses, the amplitudes and their sigma, in the layout of ``hil.calibrun`` recordings
    (``kind = "survey"``; ``hil.calibrun.save_recording`` writes it as ``.npz``)."""
    sc = scenario
    ss = np.random.SeedSequence(seed)
    s_world = int(ss.spawn(5)[0].generate_state(1)[0])          # as tools.bench.runner.BenchSetup
    world = sc.build_world(s_world, sc.duration_s)
    cfg = sc.firmware_config()
    p, R = jig_poses(seed=seed)
    cur = np.array([c.current for c in cfg.source.coils])
    S, sigma = survey_amplitudes(world, p, R, cur, sc.sensor.noise_t, bursts=bursts, seed=seed)
    return {"kind": "survey", "p": p, "R": R, "S": S, "currents": cur, "sigma_t": sigma,
            "meta": {"scenario": sc.name, "seed": int(seed), "bursts": int(bursts)}}


def fit_recording(rec: dict, cfg=None, dipoles_per_coil: int = 3) -> dict:
    """``coiltrack calibrate --method survey``: the calibration tables (``[distortion]`` and
    ``[meta]``) from a survey recording (:func:`record_survey`)."""
    from coiltrack.firmware.config import FirmwareConfig

    cfg = cfg or FirmwareConfig()
    S = np.asarray(rec["S"], float)
    if S.ndim != 3 or S.shape[2] != len(cfg.source.coils):
        raise ValueError(f"survey: amplitudes for {S.shape[-1]} coils, the configuration has {len(cfg.source.coils)}")
    table, summary = fit_survey(cfg, np.asarray(rec["p"], float), np.asarray(rec["R"], float), S,
                                np.asarray(rec["currents"], float), dipoles_per_coil)
    meta = {"method": "survey", "poses": int(table["n_points"]), "residual_rms": table["residual_rms_t"],
            "residual_unit": "T/A"}
    return {"meta": meta, "distortion": table}


def register(methods: dict, recorders: dict, room) -> None:
    """Add ``survey`` to ``coiltrack calibrate``'s methods (``tools.calibration.fits``): ``--record``
    surveys the room of the scenario ``room`` (``steel-table``) of run seed ``--seed`` (``--unit`` and ``--grid`` do not apply:
    the jig grid is :func:`jig_poses`')."""
    methods["survey"] = fit_recording
    recorders["survey"] = lambda unit, seed, grid: record_survey(room, seed=seed)


COPIED = ("position_rms_mm", "orientation_rms_deg", "position_p95_mm", "poses", "crlb_position_rms_mm", "by_range",
          "quality_error_rank_corr")


def _run(scenario, seed: int, duration_s: float, cfg):
    """One in-process run on the simulated clock (``tools.bench.runner.run_inproc``'s core): the report
    and ``{t_us: position}`` of the valid magnetic poses."""
    from coiltrack.firmware.loop import Firmware
    # imported where used here and below: the world's physics (magpylib) loads only when a run starts
    from coiltrack.tools.bench import runner

    fw_end, emu_end = runner.sim_link_pair("inproc")
    bench = runner.BenchSetup(scenario, seed, duration_s, emu_end, None, cfg=cfg)
    fw = Firmware(cfg, fw_end)
    prog = runner.Progress(False, duration_s, scenario.name)
    runner._tick_loop(bench, fw, None, int(duration_s * 1e6), cfg.timing.tick_us, prog)
    fw_end.close()
    emu_end.close()
    rep = report_mod.build(bench, fw.status(), duration_s, transport="inproc", cfg=cfg)
    return rep, poses_of(bench)


def poses_of(bench) -> dict:
    """``{(node, t_us): (estimated position, true position)}`` of a run's valid magnetic poses."""
    from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID

    out = {}
    for rp in bench.recorder.poses:
        m = rp["msg"]
        if m.status & POSE_VALID and not m.status & POSE_FUSED:
            out[(m.node, m.t_us)] = (np.array([m.px, m.py, m.pz]), np.asarray(rp["true_p"], float))
    return out


def table_error_by_range(run: dict, clean: dict) -> dict:
    """:func:`table_error_mm` per distance band of ``tools.outputs.report.RANGE_BANDS_CM`` (true distance)."""
    out = {}
    for lo, hi in RANGE_BANDS_CM:
        sel = [k for k in set(run) & set(clean) if lo / 100 <= np.linalg.norm(clean[k][1]) < hi / 100]
        if sel:
            e_run, n = table_error_mm({k: run[k] for k in sel}, {k: clean[k] for k in sel})
            out[f"{lo}-{hi}cm"] = {"poses": n, "uncorrected_or_run_mm": e_run}
    return out


def table_error_mm(run: dict, clean: dict) -> tuple[float | None, int]:
    """RMS (mm) over the poses both runs have of ``|p_run - p_clean|``: the position error the
    table makes (or leaves), the noise being the same on the same seed (the table changes the
    field the sensor samples, not the draws of its noise); and the number of poses compared."""
    keys = sorted(set(run) & set(clean))
    if not keys:
        return None, 0
    d = np.array([np.linalg.norm(run[k][0] - clean[k][0]) for k in keys])
    return round(float(np.sqrt(np.mean(d ** 2))) * 1e3, 3), len(keys)


def correction_report(bench, rep: dict, cfg, clean_scenario) -> dict:
    """``steel-table``: survey the room, run the corrected firmware and the clean bench
    (``clean_scenario``) on the same trajectory and seed (``tools.scenarios.distortion``). ``table_error_*_mm``: the table's own
    position error, this run's (and the corrected run's) poses against the clean run's at the same
    instants (:func:`table_error_mm`); ``distortion_correction_ratio`` is their ratio, uncorrected
    over corrected; ``*_position_rms_mm`` are the usual errors against the truth."""
    sc = bench.scenario
    seed, duration = bench.seed, rep["duration_s"]
    plain = dataclasses.replace(sc, report_extra=None)
    bare = cfg.with_(calibration={"calibration_file": ""})
    user_file = getattr(getattr(cfg, "calibration", None), "calibration_file", "")
    if user_file:
        # this run already applied a calibration file (bench --calibration): it is the corrected run
        cor, cor_poses = rep, poses_of(bench)
        unc, unc_poses = _run(plain, seed, duration, bare)
        out = {"survey": {"file": user_file}}
    else:
        table, summary = survey_table(bench.world, cfg, sc.sensor.noise_t, seed=seed)
        unc, unc_poses = rep, poses_of(bench)
        out = {"survey": {k: v for k, v in summary.items() if k != "coils"}}
        with tempfile.TemporaryDirectory() as d:
            path = os.path.join(d, "survey.toml")
            write_calibration(path, table, summary)
            cor, cor_poses = _run(plain, seed, duration, cfg.with_(calibration={"calibration_file": path}))
    clean, clean_poses = _run(clean_scenario, seed, duration, bare)
    out["uncorrected_position_rms_mm"] = unc.get("position_rms_mm")
    out["uncorrected_orientation_rms_deg"] = unc.get("orientation_rms_deg")
    out["uncorrected_quality_error_rank_corr"] = unc.get("quality_error_rank_corr")
    for k in COPIED:
        out["corrected_" + k] = cor.get(k)
        out["clean_" + k] = clean.get(k)
    out["table_error_uncorrected_mm"], n_u = table_error_mm(unc_poses, clean_poses)
    out["table_error_corrected_mm"], n_c = table_error_mm(cor_poses, clean_poses)
    out["table_error_poses"] = min(n_u, n_c)
    bu, bc = table_error_by_range(unc_poses, clean_poses), table_error_by_range(cor_poses, clean_poses)
    out["table_error_by_range"] = {
        band: {"poses": v["poses"], "uncorrected_mm": v["uncorrected_or_run_mm"],
               "corrected_mm": bc.get(band, {}).get("uncorrected_or_run_mm"),
               "ratio": (round(v["uncorrected_or_run_mm"] / bc[band]["uncorrected_or_run_mm"], 2)
                         if bc.get(band, {}).get("uncorrected_or_run_mm") else None)}
        for band, v in bu.items()}
    u, c = out["table_error_uncorrected_mm"], out["table_error_corrected_mm"]
    out["distortion_correction_ratio"] = round(u / c, 2) if u and c else None
    if hasattr(bench.world.objects[0], "describe"):
        out["table"] = bench.world.objects[0].describe()
    return out
