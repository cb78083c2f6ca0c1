"""Does each coil carry a constant model error that repeated pulses of that coil cannot average away?

``python -m coiltrack.tools.analyses.adaptive_coil_bias --seeds 1-10 [--duration 60] [--fixed]
[--set KEY=VALUE ...] [--json out.json]``

Runs ``schepers-adaptive`` (the policy, or with ``--fixed`` its fixed X, Y, Z cycle) per seed and
records every single-coil update the filter takes (``SchepersEKF.update_pulse``: the clone pose it
is linearised at, the coil, the reported current, the amplitude and its variance). For each taken
update, with ``h`` the firmware's per-ampere field (Schepers & Veltink 2010,
``seeds/000_e46ec0e8bf7ea271.txt`` eqs 5-8: ``y = I R^T B_c(p)``) and ``u = h / |h|``, the
relative errors along the field, ``e = (a - I h) . u / (I |h|)``:

* ``truth``: ``a`` the amplitude, ``h`` at the true pose (the bench's recorder, at the pulse's
  measurement time): the whole error of the amplitude as the filter's model sees it;
* ``innov``: ``a`` the amplitude, ``h`` at the filter's own clone pose: the innovation, which the
  filter sees (its mean tells whether the filter can see a constant part);
* ``coil model``: ``a = R^T U_c(p)`` the bench's own field per ampere at the true pose (its
  winding of 3 x 3 mm, ``hil.physics.SourceCoil``) against the firmware's single loop;
* ``driver``: ``-g_c / (1 + g_c)``, with ``g_c`` the coil driver's static sense-gain error
  (``hil.nodes.DriverAccuracy.gain_error_max``, invisible in ``COIL_STATUS``: the reported current
  is ``(1 + g_c)`` times the true one).

Per coil it prints the number of updates and the means of the four (``1e-3``), each weighted by
the inverse of the amplitude noise's variance along ``u`` (``(I |h|)^2 / u^T diag(var) u``: a pulse
near the source carries a tighter relative error), and the standard error of the truth mean from
that noise alone. If the truth
mean is the sum of the coil model's and the driver's, per coil and seed, the constant error
follows the bench's physics, not the noise. Not a bench command: a measurement for the note.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys

import numpy as np

from coiltrack.tools.analyses.adaptive_consistency import run_probed, set_keys
from coiltrack.tools.bench.sweep import parse_seeds


@contextlib.contextmanager
def _probe(ups: list):
    """Record each update's time, coil, current, amplitude and clone pose, and its flags."""
    from coiltrack.firmware.estimate.single_coil import SchepersEKF

    orig = SchepersEKF.update_pulse

    def update_pulse(self, k, m, model):
        if k >= 0:
            if not self.clone_taken[k]:
                self._take_clone(k)
            t, p, R = int(self.clone_t[k]), self.clone_p[k].copy(), self.clone_R[k].copy()
        else:
            t, p, R = int(self.t_us or 0), self.p.copy(), self.R.copy()
        flags = orig(self, k, m, model)
        ups.append((t, int(m.coil), float(m.current), np.array(m.y, dtype=float), p, R, int(flags),
                    np.array(m.var, dtype=float)))
        return flags
    SchepersEKF.update_pulse = update_pulse
    try:
        yield
    finally:
        SchepersEKF.update_pulse = orig


def run_seed(seed: int, duration: float, fixed: bool, keys: dict, skip_s: float = 4.0) -> dict:
    """One seed: per coil the relative errors along the field (module docstring)."""
    from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
    from coiltrack.firmware.model.field import Coil
    ups: list = []
    cfg, rep, bench = run_probed(seed, duration, fixed, keys, _probe(ups))
    ups = [u for u in ups if u[0] * 1e-6 > skip_s and not u[6] & 0b1111]
    n_coils = len(cfg.source.coils)
    model = SingleCoilModel([Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.source.coils])
    K = bench.world.sensor_kinematics(np.array([u[0] for u in ups], dtype=np.int64))
    e = np.zeros((len(ups), 3))
    w = np.zeros(len(ups))
    coil = np.array([u[1] for u in ups], dtype=int)
    for i, (t, c, cur, y, p, R, _, var) in enumerate(ups):
        Rt, pt = K.R[i], K.position[i]
        model.evaluate(pt, Rt)
        h = np.array(model.h[c], dtype=float)
        hn = float(np.linalg.norm(h))
        u = h / hn
        w[i] = (cur * hn) ** 2 / float(u @ (var * u))        # 1 / the white variance of e along u
        e[i, 0] = float((y - cur * h) @ u) / (cur * hn)
        b = Rt.T @ bench.world.unit_fields(pt)[c]
        e[i, 2] = float((b - h) @ u) / hn
        model.evaluate(p, R)
        he = np.array(model.h[c], dtype=float)
        e[i, 1] = float((y - cur * he) @ (he / np.linalg.norm(he))) / (cur * float(np.linalg.norm(he)))
    g = [float(x) for x in bench.driver.gain_error]
    out = {"seed": seed, "fixed": fixed, "position_rms_mm": rep.get("position_rms_mm"),
           "orientation_rms_deg": rep.get("orientation_rms_deg"), "coils": []}
    for c in range(n_coils):
        m = coil == c
        n = int(m.sum())
        row = {"coil": c, "updates": n, "driver": -g[c] / (1.0 + g[c])}
        if n:
            wm = w[m] / w[m].sum()
            row.update(truth=float(wm @ e[m, 0]), truth_se=float(1.0 / math.sqrt(w[m].sum())),
                       truth_plain=float(e[m, 0].mean()), innov=float(wm @ e[m, 1]), coil_model=float(wm @ e[m, 2]))
        out["coils"].append(row)
    out["rel_model"] = float(getattr(cfg, "field_model_rel_sigma", float("nan"))) if hasattr(cfg, "field_model_rel_sigma") \
        else None
    return out


def summarise(rows: list[dict]) -> dict:
    """Over every seed and coil: the truth means against the bench's constant part (coil model plus
    driver), their correlation, the least-squares slope through 0, and the mean of
    ``((truth - constant) / se)^2`` (1 if the rest is the amplitude noise alone); the same for the
    driver's part alone and for the coil model's alone, and the spread of the truth means."""
    t, se, m, d = (np.array([c[k] for r in rows for c in r["coils"] if c["updates"]])
                   for k in ("truth", "truth_se", "coil_model", "driver"))
    out = {"coil_runs": int(t.size), "truth_rms": float(np.sqrt(np.mean(t * t)))}
    for name, x in (("model+driver", m + d), ("driver", d), ("coil_model", m)):
        out[name] = {"corr": float(np.corrcoef(t, x)[0, 1]) if np.std(x) > 0 else None,
                     "slope": float((t @ x) / (x @ x)), "chi2_per_coil": float(np.mean(((t - x) / se) ** 2)),
                     "residual_rms": float(np.sqrt(np.mean((t - x) ** 2)))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="1-10")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--fixed", action="store_true", help="the fixed X, Y, Z cycle instead of the policy")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="firmware configuration key (repeatable)")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--summary", metavar="JSON", help="print the summary of rows written before, run nothing")
    a = ap.parse_args(argv)
    if a.summary:
        try:
            with open(a.summary) as f:
                print(json.dumps(summarise(json.load(f)), indent=1))
        except (OSError, ValueError, KeyError) as exc:
            print(f"adaptive_coil_bias: --summary {a.summary}: {exc}", file=sys.stderr)
            return 2
        return 0
    try:
        seeds = parse_seeds(a.seeds)
        keys = set_keys(a.set)
        if not (0.0 < a.duration <= 3600.0):
            raise ValueError("--duration must be in (0, 3600] s")
    except ValueError as exc:
        print(f"adaptive_coil_bias: {exc}", file=sys.stderr)
        return 2
    rows = []
    print("seed coil updates  truth(1e-3) +-se  innov  coil_model  driver  model+driver  pos_mm  ori_deg")
    for s in seeds:
        r = run_seed(s, a.duration, a.fixed, keys)
        rows.append(r)
        for c in r["coils"]:
            if not c["updates"]:
                continue
            print(f"{s:4d} {c['coil']:4d} {c['updates']:7d} {1e3 * c['truth']:9.2f} {1e3 * c['truth_se']:5.2f} "
                  f"{1e3 * c['innov']:6.2f} {1e3 * c['coil_model']:9.2f} {1e3 * c['driver']:7.2f} "
                  f"{1e3 * (c['coil_model'] + c['driver']):11.2f}  {r['position_rms_mm']:.3f} "
                  f"{r['orientation_rms_deg']:.3f}", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)
    print(json.dumps(summarise(rows), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
