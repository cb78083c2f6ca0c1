"""Which rotation does the single-coil filter observe poorly, and is its covariance honest about it?

``python -m coiltrack.tools.analyses.adaptive_orientation_axes --seeds 5,6 [--duration 60]
[--fixed] [--set KEY=VALUE ...] [--window-s 1.0] [--skip-s 4] [--json OUT]``

Runs ``schepers-adaptive`` (the policy, or with ``--fixed`` its fixed X, Y, Z cycle) under the
probes of ``adaptive_consistency`` (the live filter's orientation, position and pose covariance
every 20 ms; every single-coil update with its coil, current and amplitude variance). At each
probed tick after ``--skip-s``:

* ``e``: the orientation error in the sensor frame (``R_true = R_est exp([e]x)``,
  ``estimate.single_coil``), ``P_o`` the filter's orientation block;
* ``u_c``: the unit field direction of coil ``c`` at the estimated pose, sensor frame. A pulse of
  coil ``c`` measures ``I R^T B_c``; a rotation ``dtheta`` changes it by ``[h_c]x dtheta``
  (Schepers & Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt`` eq 11), so it sees nothing of a
  rotation about ``u_c``;
* ``J``: the orientation information the updates of the last ``--window-s`` carried,
  ``sum I^2 (|h_c|^2 I3 - h_c h_c^T) / var`` (each update's coil field at the tick's pose), and
  ``v_min`` its least-informed direction (the rotation the recent pulses saw least).

Over the run it prints, per direction (each ``u_c``, ``v_min``, and the filter's own largest axis
``v_big`` of ``P_o``): the error's mean square ``E[(v.e)^2]`` (deg^2), the filter's variance
``E[v^T P_o v]`` (deg^2) and their ratio (the NEES along it: 1 for an honest filter), the share
of the whole error ``E[(v.e)^2] / E[|e|^2]`` (1/3 for an error spread evenly), and the updates per
coil. Not a bench command: a measurement for ``docs/adaptive.md``.

Exit status: 0 done; 2 a bad argument.
"""
from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from coiltrack.tools.analyses.adaptive_consistency import _tick_probe, _update_probe, run_probed, set_keys
from coiltrack.tools.bench.sweep import parse_seeds


def _skew_info(h) -> np.ndarray:
    """``[h]x^T [h]x = |h|^2 I3 - h h^T``: the orientation information of one unit-variance pulse."""
    return float(h @ h) * np.eye(3) - np.outer(h, h)


def directions(cfg, bench, rec, ups, window_s: float, skip_s: float) -> dict:
    """The per-direction table of the module docstring for one run."""
    from scipy.spatial.transform import Rotation

    from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
    from coiltrack.firmware.model.field import Coil

    truth = {int(rp["msg"].t_us): rp["true_R"] for rp in bench.recorder.poses}
    n = len(cfg.source.coils)
    model = SingleCoilModel([Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.source.coils])
    ups = [u for u in ups if not u[5] & 0b1111]
    ut = np.array([u[0] for u in ups], dtype=np.int64)
    names = [f"u{c}" for c in range(n)] + ["v_min", "v_big"]
    err = np.zeros(len(names))
    var = np.zeros(len(names))
    tot = 0.0
    cnt = 0
    cond = []
    win = int(window_s * 1e6)
    for t, Re, pe, Po, _ in rec:
        Rt = truth.get(t)
        if Rt is None or t * 1e-6 < skip_s:
            continue
        e = Rotation.from_matrix(Re.T @ Rt).as_rotvec()
        model.evaluate(pe, Re)
        h = np.asarray(model.h).copy()
        J = np.zeros((3, 3))
        lo, hi = np.searchsorted(ut, t - win), np.searchsorted(ut, t, side="right")
        for k in range(lo, hi):
            _, c, cur, _, vv, _ = ups[k]
            J += cur * cur * _skew_info(h[c]) / float(np.mean(vv))
        w, V = np.linalg.eigh(J)
        dirs = [h[c] / np.linalg.norm(h[c]) for c in range(n)]
        dirs.append(V[:, 0])
        wo, Vo = np.linalg.eigh(Po)
        dirs.append(Vo[:, 2])
        for i, v in enumerate(dirs):
            err[i] += float(v @ e) ** 2
            var[i] += float(v @ Po @ v)
        tot += float(e @ e)
        cnt += 1
        if w[2] > 0.0:
            cond.append(w[0] / w[2])
    if not cnt:
        return {"ticks": 0}
    d2 = math.degrees(1.0) ** 2
    out = {"ticks": cnt, "err_rms_deg": round(math.sqrt(tot / cnt * d2), 4),
           "updates": np.bincount([u[1] for u in ups if u[0] * 1e-6 >= skip_s], minlength=n).tolist(),
           "info_ratio_min_max_median": round(float(np.median(cond)), 4) if cond else None}
    for i, name in enumerate(names):
        out[name] = {"err_ms_deg2": round(err[i] / cnt * d2, 5), "var_deg2": round(var[i] / cnt * d2, 5),
                     "nees": round(err[i] / var[i], 3) if var[i] > 0 else None,
                     "share": round(err[i] / tot, 3) if tot > 0 else None}
    return out


def _one(seed: int, duration: float, fixed: bool, keys: dict, window_s: float, skip_s: float) -> dict:
    rec: list = []
    ups: list = []
    cfg, rep, bench = run_probed(seed, duration, fixed, keys, _tick_probe(rec), _update_probe(ups))
    out = directions(cfg, bench, rec, ups, window_s, skip_s)
    out.update(seed=seed, fixed=fixed, orientation_rms_deg=rep.get("orientation_rms_deg"),
               position_rms_mm=rep.get("position_rms_mm"), coil_energy_j=rep.get("coil_energy_j"))
    return out


def _line(r: dict) -> str:
    parts = [f"seed {r['seed']} {'fixed ' if r['fixed'] else 'policy'}: ori {r['orientation_rms_deg']} deg, "
             f"updates {r.get('updates')}, J min/max {r.get('info_ratio_min_max_median')}"]
    for k, v in r.items():
        if isinstance(v, dict):
            parts.append(f"  {k:6s} err^2 {v['err_ms_deg2']:.5f}  var {v['var_deg2']:.5f}  nees {v['nees']}  "
                         f"share {v['share']}")
    return "\n".join(parts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="5,6")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--fixed", action="store_true", help="the fixed X, Y, Z cycle instead of the policy")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE")
    ap.add_argument("--window-s", type=float, default=1.0)
    ap.add_argument("--skip-s", type=float, default=4.0)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    try:
        seeds = parse_seeds(a.seeds)
        keys = set_keys(a.set)
        if not (0.0 < a.duration <= 3600.0 and 0.0 < a.window_s <= 60.0 and 0.0 <= a.skip_s < a.duration):
            raise ValueError("--duration in (0, 3600], --window-s in (0, 60], --skip-s in [0, duration)")
    except ValueError as exc:
        print(f"adaptive_orientation_axes: {exc}", file=sys.stderr)
        return 2
    rows = []
    for s in seeds:
        r = _one(s, a.duration, a.fixed, keys, a.window_s, a.skip_s)
        rows.append(r)
        print(_line(r), flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"keys": keys, "duration_s": a.duration, "window_s": a.window_s, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
