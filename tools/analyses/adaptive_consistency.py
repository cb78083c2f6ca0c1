"""Is the single-coil filter's orientation covariance the size of its errors, and where not, why?

``python -m coiltrack.tools.analyses.adaptive_consistency --seed 5 [--duration 60] [--fixed]
[--set KEY=VALUE ...] [--bin 2]``

Runs ``schepers-adaptive`` (the policy, or with ``--fixed`` its fixed X, Y, Z cycle) on the
simulated clock and, at every 20 ms tick, takes the live filter's state (time, orientation,
position and the pose blocks of ``P``; ``estimate.single_coil``: the orientation error is in the
sensor frame, ``R_true = R exp([e]x)``). The truth is the recorder's, at the same instant (the
POSE the filter sent at its own time). Per ``--bin`` seconds it prints:

* the coil pulses executed per coil;
* ``|cos|`` of the angle between the orientation covariance's largest axis and each coil's
  field direction at the sensor (a pulse of coil ``c`` sees no rotation about its own field
  ``h_c``: Schepers & Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt`` eqs 9-11, the
  orientation columns ``[h]x``);
* the orientation NEES ``e^T P^-1 e`` (3 for a consistent filter), and its parts along the
  covariance's largest and smallest axes (1 each); the error (deg) and ``sqrt(tr P)`` (deg);
* the position NEES (3).

Then, over the run after its first 4 s, the amplitude errors ``(y - I h(p_true, R_true)) /
sqrt(var)`` of the pulses the filter took (``var`` as the filter took it; the truth at the
pulse's measurement time): their mean square per component (1 for honest variances) and the
correlation of consecutive pulses' errors, for pulses that share baseline samples (the next one
starting less than two baselines after this one's end: ``estimate.shared_baseline``) and for
those that do not. Independent errors give 0; a shared baseline about 0.2.

The NIS cannot show an error along a direction no recent pulse observed; this NEES can.
Not a bench command: a measurement for the note.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys

import numpy as np

TICK_EVERY_US = 20_000


@contextlib.contextmanager
def _update_probe(ups: list):
    """Record every single-coil update: measurement time, coil, current, amplitude, its variance."""
    from coiltrack.firmware.estimate.single_coil import SchepersEKF

    orig = SchepersEKF.update_pulse

    def update_pulse(self, k, m, model):
        t = int(self.clone_t[k]) if k >= 0 else int(self.t_us or 0)
        flags = orig(self, k, m, model)
        ups.append((t, int(m.coil), float(m.current), np.array(m.y, dtype=float), np.array(m.var, dtype=float), flags))
        return flags
    SchepersEKF.update_pulse = update_pulse
    try:
        yield
    finally:
        SchepersEKF.update_pulse = orig


@contextlib.contextmanager
def _tick_probe(rec: list):
    """Record the single-coil filters' state after every ``TICK_EVERY_US`` firmware tick."""
    from coiltrack.firmware import loop
    from coiltrack.firmware.estimate.layout import ORI, POS

    orig = loop.Firmware.tick

    def tick(self, now_us):
        orig(self, now_us)
        if now_us % TICK_EVERY_US:
            return
        for s in getattr(self.tracker, "sensors", {}).values():
            e = s.ekf
            if e.initialized:
                rec.append((int(e.t_us), e.R.copy(), e.p.copy(), e.P[ORI, ORI].copy(), e.P[POS, POS].copy()))
    loop.Firmware.tick = tick
    try:
        yield
    finally:
        loop.Firmware.tick = orig


def run_probed(seed: int, duration: float, fixed: bool, keys: dict, *probes):
    """schepers-adaptive (its fixed cycle when ``fixed``) with ``keys``, run in process under the
    context managers ``probes``: the configuration, the report and the bench that made it."""
    from coiltrack.tools.bench import runner
    from coiltrack.tools.outputs import report
    from coiltrack.tools.scenarios import get

    sc = get("schepers-adaptive")
    cfg = sc.fixed_config() if fixed else sc.firmware_config()
    if keys:
        cfg = cfg.with_keys(**keys)
    got = {}
    orig = report.build

    def build(bench, *a, **k):
        got["bench"] = bench
        return orig(bench, *a, **k)
    report.build = build
    try:
        with contextlib.ExitStack() as stack:
            for p in probes:
                stack.enter_context(p)
            rep = runner.run_inproc(sc, seed, duration, cfg=cfg)
    finally:
        report.build = orig
    return cfg, rep, got["bench"]


def _run(seed: int, duration: float, fixed: bool, keys: dict):
    rec: list = []
    ups: list = []
    cfg, rep, bench = run_probed(seed, duration, fixed, keys, _tick_probe(rec), _update_probe(ups))
    return cfg, rep, bench, rec, ups


def amplitude_errors(cfg, bench, ups, skip_s: float = 4.0) -> dict:
    """Normalised amplitude errors of the updates after ``skip_s`` (module docstring): mean square
    per component, and the correlation of consecutive pulses' errors, sharing a baseline or not."""
    from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
    from coiltrack.firmware.model.field import Coil

    ups = [u for u in ups if u[0] * 1e-6 > skip_s and not u[5] & 0b1111]
    if len(ups) < 3:
        return {"updates": len(ups)}
    model = SingleCoilModel([Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.source.coils])
    K = bench.world.sensor_kinematics(np.array([u[0] for u in ups], dtype=np.int64))
    z = np.zeros((len(ups), 3))
    for i, (t, c, cur, y, var, _) in enumerate(ups):
        model.evaluate(K.position[i], K.R[i])
        z[i] = (y - cur * np.asarray(model.h[c])) / np.sqrt(var)
    pulse_us = cfg.adaptive.adaptive_pulse_us or cfg.timing.pulse_us
    p = cfg.pulse
    # consecutive measurement times closer than pulse + fall + 2 baselines + guard: shared samples
    near = np.diff([u[0] for u in ups]) < pulse_us + p.fall_us + 2 * p.baseline_us + p.guard_us
    out = {"updates": len(ups), "mean_square": round(float(np.mean(z * z)), 3)}
    for name, m in (("shared", near), ("apart", ~near)):
        out[f"pairs_{name}"] = int(m.sum())
        if m.sum() >= 3:
            out[f"corr_{name}"] = round(float(np.corrcoef(z[:-1][m].ravel(), z[1:][m].ravel())[0, 1]), 3)
    return out


def tabulate(cfg, bench, rec, duration: float, bin_s: float) -> list[dict]:
    """Per bin: pulses per coil, |cos| (largest axis, field of each coil), NEES parts, errors."""
    from scipy.spatial.transform import Rotation

    from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
    from coiltrack.firmware.model.field import Coil

    truth = {int(rp["msg"].t_us): (rp["true_R"], rp["true_p"]) for rp in bench.recorder.poses}
    n_coils = len(cfg.source.coils)
    model = SingleCoilModel([Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.source.coils])
    nb = int(math.ceil(duration / bin_s))
    acc = np.zeros((nb, 6))
    cos = np.zeros((nb, n_coils))
    cnt = np.zeros(nb)
    use = np.zeros((nb, n_coils), dtype=int)
    for ex in bench.driver.executed:
        use[min(int(ex["start_us"] * 1e-6 / bin_s), nb - 1), ex["coil"]] += 1
    for t, Re, pe, Po, Pp in rec:
        tr = truth.get(t)
        if tr is None:
            continue
        k = min(int(t * 1e-6 / bin_s), nb - 1)
        e = Rotation.from_matrix(Re.T @ tr[0]).as_rotvec()
        w, V = np.linalg.eigh(Po)
        ev = V.T @ e
        dp = tr[1] - pe
        acc[k] += (e @ np.linalg.solve(Po, e), ev[2] ** 2 / w[2], ev[0] ** 2 / w[0], e @ e, np.trace(Po),
                   dp @ np.linalg.solve(Pp, dp))
        model.evaluate(pe, Re)
        for c in range(n_coils):
            h = np.asarray(model.h[c])
            cos[k, c] += abs(V[:, 2] @ h) / np.linalg.norm(h)
        cnt[k] += 1
    rows = []
    for k in range(nb):
        n = max(cnt[k], 1.0)
        a = acc[k] / n
        rows.append({"t_s": k * bin_s, "pulses": use[k].tolist(), "cos_big_field": np.round(cos[k] / n, 2).tolist(),
                     "nees_ori": a[0], "nees_ori_big": a[1], "nees_ori_small": a[2],
                     "err_deg": math.degrees(math.sqrt(a[3])), "sigma_deg": math.degrees(math.sqrt(a[4])),
                     "nees_pos": a[5], "samples": int(cnt[k])})
    return rows


def set_keys(items) -> dict:
    """``--set KEY=VALUE`` items as configuration keys (a value read as JSON where it parses)."""
    out = {}
    for it in items or ():
        if "=" not in it:
            raise ValueError(f"--set {it!r}: expected KEY=VALUE")
        k, v = it.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--bin", type=float, default=2.0, help="seconds per row")
    ap.add_argument("--fixed", action="store_true", help="the fixed X, Y, Z cycle instead of the policy")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="firmware configuration key (repeatable)")
    a = ap.parse_args(argv)
    try:
        keys = set_keys(a.set)
        if not (0.0 < a.duration <= 3600.0) or not (0.0 < a.bin <= a.duration):
            raise ValueError("--duration must be in (0, 3600] s and --bin in (0, duration]")
        cfg, rep, bench, rec, ups = _run(a.seed, a.duration, a.fixed, keys)
    except (ValueError, TypeError) as exc:
        print(f"adaptive_consistency: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({k: rep.get(k) for k in ("position_rms_mm", "orientation_rms_deg", "coil_energy_j")}))
    print("   t  pulses/coil     |cos(big axis, h_c)|  NEESori  big  small  err_deg  sigma_deg  NEESpos")
    for r in tabulate(cfg, bench, rec, a.duration, a.bin):
        print(f"{r['t_s']:4.0f}  {str(r['pulses']):14s} {str(r['cos_big_field']):22s} {r['nees_ori']:7.2f} "
              f"{r['nees_ori_big']:5.2f} {r['nees_ori_small']:6.2f} {r['err_deg']:8.3f} {r['sigma_deg']:9.3f} "
              f"{r['nees_pos']:8.2f}")
    print("amplitude errors:", json.dumps(amplitude_errors(cfg, bench, ups)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
