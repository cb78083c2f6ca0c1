"""Where the adaptive policy spends coil energy its floor does not: the policy's pulses against the
bound's optimal schedule on the same trajectory.

``python -m coiltrack.tools.analyses.adaptive_gap --seeds 2,7 [--duration 60] [--ratio 1.0]
[--sample-phase aligned] [--set KEY=VALUE ...] [--json out.json]``

Per seed it runs ``schepers-adaptive``'s policy (the firmware configuration with ``--set``) and
records every pulse it commands (``single_coil_pulses.PulseBook.command``: start, coil, current,
length) and who commanded it: the fixed cycle of the warm-up and settling
(``single_coil_policy._decide_fixed``), the policy's own decision (``_decide_command``, with the
chooser's ``reached``: whether an allowed current brought the target to ``sigma_min``) or the
acquisition burst. It then solves the bound on the same trajectory
(``energy_bound.least_energy`` with the ``chosen`` kinds at ``--sample-phase``, the seed's exponents
fitted to the fixed cycle's current sweeps) and sets the two schedules side by side in the bound's
windows (one fixed-cycle period each), in the bound's units: ``I^2 T`` over the fixed cycle's
``I_0^2 T_0`` per coil and window (the energy ratio less the coil's rise and fall).

Printed per seed: the policy's and the floor's energy fraction, and the gap between them split by

* **phase**: the windows of the warm-up (the fixed cycle at full current until the reference has
  settled: ``reference_warmup_us``, ``reference_settle_drop``) against the rest;
* **coil**, **range** (windows nearer and farther than the median range), and the policy's pulses
  that reached their goal against those that did not (``unreached_share``);
* **what a pulse is**: pulses per second, the energy-weighted rms current and mean length, after
  the warm-up, for the policy and the floor.

The warm-up has no counterpart in the bound (it holds the mean variance over the whole run from
the start), so its energy is the gap a policy that runs the fixed cycle first cannot close.
Not a bench command: a measurement for the note.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys

import numpy as np

#: who commanded a pulse
WARM, OWN, ACQ = "warmup", "policy", "acquisition"


@contextlib.contextmanager
def _pulse_probe(rec: list):
    """Record every commanded pulse ``(start_us, coil, current, length_us, who, reached, target)``
    (``target``: the chooser's target variable, 0 position, 3 orientation; -1 for no decision)."""
    from coiltrack.firmware.actuate import single_coil_policy as scp
    from coiltrack.firmware.actuate.single_coil_pulses import PulseBook

    who = [ACQ, False, -1]
    orig_cmd, orig_fixed, orig_own = PulseBook.command, scp._SingleCoilActuation._decide_fixed, \
        scp.AdaptiveActuation._decide_command

    def command(self, coil, current, start, length, acq, mid_us=-1):
        out = orig_cmd(self, coil, current, start, length, acq, mid_us)
        rec.append((int(start), int(coil), float(current), int(length), ACQ if acq else who[0], bool(who[1]),
                    int(who[2])))
        return out

    def decide_fixed(self, now_us):
        who[0], who[1], who[2] = WARM, True, -1
        try:
            return orig_fixed(self, now_us)
        finally:
            who[0] = ACQ

    def decide_command(self):
        who[0], who[1], who[2] = OWN, bool(self.chooser.reached), int(self.chooser.target)
        try:
            return orig_own(self)
        finally:
            who[0] = ACQ
    PulseBook.command = command
    scp._SingleCoilActuation._decide_fixed = decide_fixed
    scp.AdaptiveActuation._decide_command = decide_command
    try:
        yield
    finally:
        PulseBook.command = orig_cmd
        scp._SingleCoilActuation._decide_fixed = orig_fixed
        scp.AdaptiveActuation._decide_command = orig_own


@contextlib.contextmanager
def _reference_probe(refs: list):
    """Keep every actual-error reference made (``reference_error = "actual"``)."""
    from coiltrack.firmware.actuate import accuracy_actual as aa

    orig = aa._ActualError.__init__

    def init(self, *a, **k):
        orig(self, *a, **k)
        refs.append(self)
    aa._ActualError.__init__ = init
    try:
        yield
    finally:
        aa._ActualError.__init__ = orig


def reference_state(refs: list) -> dict | None:
    """The last actual-error reference's model-error estimate ``q`` (pulses, weight) and its means
    against the belief's at the end of the run (position and orientation traces)."""
    if not refs:
        return None
    r = refs[-1]
    from coiltrack.firmware.estimate.layout import ORI, POS

    def tr(M, b):
        return float(M[b, b].trace())
    return {"q": r.est.q(), "pulses": r.est.n, "weight": r.est.sxx,
            "actual_over_belief_end": [tr(r.Pa, POS) / tr(r.P, POS), tr(r.Pa, ORI) / tr(r.P, ORI)]}


def policy_pulses(seed: int, duration: float, keys: dict, refs: list | None = None):
    """Run the policy; its report and its pulses (a structured array)."""
    from coiltrack.tools.analyses.adaptive_consistency import run_probed

    rec: list = []
    refs = [] if refs is None else refs
    _, rep, _ = run_probed(seed, duration, False, keys, _pulse_probe(rec), _reference_probe(refs))
    dt = [("t", "i8"), ("coil", "i4"), ("current", "f8"), ("length", "i8"), ("who", "U12"), ("reached", "?"), ("target", "i4")]
    return rep, np.array(rec, dtype=dt)


def floor_schedule(seed: int, duration: float, ratio: float, phase: str, sweeps: str):
    """The bound's optimum on the seed's trajectory: ``(model, kinds, out)`` with ``out['detail']``
    per window and coil (energy, time, kind, current)."""
    from coiltrack.tools.analyses import energy_bound as eb

    model = eb.SeedModel(seed, 1, duration, phase=phase)
    hi, lo = eb._sweep_figures(f"{sweeps}/fixed-910.json"), eb._sweep_figures(f"{sweeps}/fixed-450.json")
    a_pos, a_rot = model.exponents(hi[seed], lo[seed], eb._sweep_model_error())
    kinds = eb.mode_kinds("chosen", model.tm, fixed_pulse_s=model.T0, baseline_s=model.B0, long_baseline_s=0.1,
                          max_pulse_s=0.4, step_s=0.0005, phase=phase)
    out = eb.least_energy(model.Jt, model.x0, model.cost(kinds), model.ref_energy, a_pos, a_rot, ratio)
    return model, kinds, out


def compare(model, kinds, out: dict, pulses, duration: float) -> dict:
    """The two schedules in the bound's windows and units (module docstring)."""
    W, K = model.x0.shape
    D = model.D
    unit = model.ref_energy                                   # I0^2 T0 per coil and window
    norm = W * K * unit
    d = out["detail"]
    eb_wk = d["energy"]                                       # (W, K) A^2 s
    w = np.minimum((pulses["t"] * 1e-6 // D).astype(int), W - 1)
    e = pulses["current"] ** 2 * pulses["length"] * 1e-6
    ep_wk = np.zeros((W, K))
    np.add.at(ep_wk, (w, pulses["coil"]), e)
    warm_w = np.zeros(W, bool)
    own = pulses["who"] == OWN
    last_warm = int(w[pulses["who"] != OWN].max()) if np.any(pulses["who"] != OWN) else -1
    warm_w[:last_warm + 1] = True
    r = np.linalg.norm(model.p, axis=1)
    near = r < np.median(r)
    gap = ep_wk - eb_wk

    def share(mask_w=None, coil=None):
        g = gap if mask_w is None else gap[mask_w]
        if coil is not None:
            g = g[:, coil]
        return float(np.sum(g) / norm)

    kind = d["kind"]
    slot = kinds.slot[kind]
    n_b = np.where(slot > 0, d["time"] / slot, 0.0)           # the floor's pulses (W, K)
    after = ~warm_w
    eb_after = eb_wk[after]
    Tb = kinds.T[kind][after]
    sel = own & ~np.isin(w, np.where(warm_w)[0])
    res = {
        "policy_fraction": float(ep_wk.sum() / norm), "floor_fraction": float(eb_wk.sum() / norm),
        "floor_converged": bool(out["converged"]), "warmup_windows": int(warm_w.sum()),
        "gap": {"total": share(), "warmup": share(warm_w), "after": share(after),
                "coils_after": [share(after, k) for k in range(K)],
                "near_after": share(after & near), "far_after": share(after & ~near),
                "unreached": float(np.sum(e[own & ~pulses["reached"]]) / norm),
                "reached": float(np.sum(e[own & pulses["reached"]]) / norm)},
        "policy_after": {"pulses_per_s": float(np.sum(sel) / (after.sum() * D)),
                         "current_rms_a": float(np.sqrt(np.sum(e[sel] * pulses["current"][sel] ** 2) / max(e[sel].sum(), 1e-300))),
                         "length_ms": float(np.sum(e[sel] * pulses["length"][sel]) / max(e[sel].sum(), 1e-300) * 1e-3),
                         "coil_share": [float(np.sum(e[sel & (pulses["coil"] == k)]) / max(e[sel].sum(), 1e-300))
                                        for k in range(K)],
                         "pulses_per_coil": [int(np.sum(sel & (pulses["coil"] == k))) for k in range(K)],
                         "unreached_pulses": int(np.sum(sel & ~pulses["reached"]))},
        "floor_after": {"pulses_per_s": float(n_b[after].sum() / (after.sum() * D)),
                        "current_rms_a": float(np.sqrt(np.sum(eb_after * d["current"][after] ** 2) / max(eb_after.sum(), 1e-300))),
                        "length_ms": float(np.sum(eb_after * Tb) / max(eb_after.sum(), 1e-300) * 1e3),
                        "coil_share": [float(eb_after[:, k].sum() / max(eb_after.sum(), 1e-300)) for k in range(K)],
                        "pulses_per_coil": [float(n_b[after][:, k].sum()) for k in range(K)]},
        "energy_after": {"policy": float(ep_wk[after].sum() / (after.sum() * K * unit)),
                         "floor": float(eb_after.sum() / (after.sum() * K * unit))},
        "per_window": {"policy": ep_wk.tolist(), "floor": eb_wk.tolist(), "range_m": r.tolist()},
    }
    # the policy's own pulses after the warm-up by target group, goal reached or not, near or far
    near_p = near[w]
    split = {}
    for tname, tmask in (("position", pulses["target"] < 3), ("orientation", pulses["target"] >= 3)):
        for rname, rmask in (("reached", pulses["reached"]), ("unreached", ~pulses["reached"])):
            for dname, dmask in (("near", near_p), ("far", ~near_p)):
                m = sel & tmask & rmask & dmask
                split[f"{tname}/{rname}/{dname}"] = [int(m.sum()), float(e[m].sum() / norm),
                                                     float(np.sqrt(np.mean(pulses["current"][m] ** 2))) if m.any() else 0.0]
    res["policy_split"] = split
    # where the policy over-spends most: the windows after the warm-up, ranked by their gap
    gw = gap[after].sum(axis=1)
    res["gap_top_decile_share"] = float(np.sort(gw)[::-1][:max(1, len(gw) // 10)].sum() / max(gw.sum(), 1e-300))
    res["gap_vs_range_corr"] = float(np.corrcoef(gw, r[after])[0, 1]) if len(gw) > 2 else float("nan")
    return res


def _print(seed: int, rep: dict, res: dict) -> None:
    g, pa, fa = res["gap"], res["policy_after"], res["floor_after"]
    print(f"seed {seed}: policy {res['policy_fraction']:.3f} (report energy_ratio {rep.get('energy_ratio', float('nan')):.3f}), "
          f"floor {res['floor_fraction']:.3f}, x{res['policy_fraction'] / res['floor_fraction']:.2f}; "
          f"position {rep.get('position_rms_ratio', float('nan')):.3f}, orientation {rep.get('orientation_rms_ratio', float('nan')):.3f}")
    print(f"  gap {g['total']:.3f} = warm-up {g['warmup']:.3f} ({res['warmup_windows']} windows) + after {g['after']:.3f} "
          f"[coils {', '.join(f'{x:.3f}' for x in g['coils_after'])}; near {g['near_after']:.3f}, far {g['far_after']:.3f}]")
    print(f"  after the warm-up, energy per window/coil-window: policy {res['energy_after']['policy']:.3f}, "
          f"floor {res['energy_after']['floor']:.3f}; policy pulses reached/unreached energy {g['reached']:.3f}/{g['unreached']:.3f}")
    print("  policy's own pulses after the warm-up (target/goal/range: pulses, energy fraction, rms current A):")
    print("    " + "; ".join(f"{k} {v[0]} {v[1]:.3f} {v[2]:.2f}" for k, v in res["policy_split"].items() if v[0]))
    for name, x in (("policy", pa), ("floor", fa)):
        print(f"  {name:6s}: {x['pulses_per_s']:.2f} pulses/s, rms current {x['current_rms_a']:.3f} A, length "
              f"{x['length_ms']:.1f} ms, energy by coil {', '.join(f'{c:.2f}' for c in x['coil_share'])}, pulses by coil "
              f"{', '.join(f'{c:.0f}' for c in x['pulses_per_coil'])}")


def main(argv=None) -> int:
    from coiltrack.tools.analyses.adaptive_consistency import set_keys
    from coiltrack.tools.bench.sweep import parse_seeds

    ap = argparse.ArgumentParser(prog="python -m coiltrack.tools.analyses.adaptive_gap", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="1-10")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--ratio", type=float, default=1.0, help="the floor's RMS ratio (default 1.0: the policy's ratio)")
    ap.add_argument("--sample-phase", choices=("mean", "aligned"), default="aligned",
                    help="the floor's sample phase (aligned: pulse_length = chosen's floor; mean: 60 ms pulses')")
    ap.add_argument("--sweeps", default="docs/adaptive-sweeps", help="folder with fixed-910.json and fixed-450.json")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="firmware configuration key (repeatable)")
    ap.add_argument("--fixed-from", help="a sweep JSON of the same scenario whose runs give each seed's fixed-cycle "
                                         "figures (fixed_coil_energy_j, fixed_*_rms_*): the report's ratios")
    ap.add_argument("--json", help="write the rows here")
    a = ap.parse_args(argv)
    try:
        seeds = parse_seeds(a.seeds)
        keys = set_keys(a.set)
        if not (0.0 < a.duration <= 3600.0):
            raise ValueError("--duration must be in (0, 3600] s")
        if not a.ratio >= 1.0:
            raise ValueError("--ratio must be >= 1")
    except ValueError as exc:
        print(f"adaptive_gap: {exc}", file=sys.stderr)
        return 2
    fixed = {}
    if a.fixed_from:
        try:
            with open(a.fixed_from) as f:
                fixed = {int(r["seed"]): r["figures"] for r in json.load(f)["runs"]}
        except (OSError, ValueError, KeyError) as exc:
            print(f"adaptive_gap: --fixed-from {a.fixed_from}: {exc}", file=sys.stderr)
            return 2
    rows = []
    for s in seeds:
        try:
            model, kinds, out = floor_schedule(s, a.duration, a.ratio, a.sample_phase, a.sweeps)
        except (OSError, ValueError, KeyError) as exc:
            print(f"adaptive_gap: --sweeps {a.sweeps}: {exc}", file=sys.stderr)
            return 2
        refs: list = []
        rep, pulses = policy_pulses(s, a.duration, keys, refs)
        fx = fixed.get(s)
        if fx is not None and "energy_ratio" not in rep:
            rep = dict(rep, energy_ratio=rep["coil_energy_j"] / fx["fixed_coil_energy_j"],
                       position_rms_ratio=rep["position_rms_mm"] / fx["fixed_position_rms_mm"],
                       orientation_rms_ratio=rep["orientation_rms_deg"] / fx["fixed_orientation_rms_deg"])
        res = compare(model, kinds, out, pulses, a.duration)
        res["reference"] = reference_state(refs)
        _print(s, rep, res)
        if res["reference"]:
            x = res["reference"]
            print(f"  actual-error reference: q {x['q']:.3f} ({x['pulses']} pulses, weight {x['weight']:.1f}); actual/belief "
                  f"at the end: position {x['actual_over_belief_end'][0]:.3f}, orientation {x['actual_over_belief_end'][1]:.3f}")
        res.update(seed=s, report={k: rep.get(k) for k in ("energy_ratio", "position_rms_ratio", "orientation_rms_ratio")})
        rows.append(res)
        sys.stdout.flush()
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"settings": a.set or [], "ratio": a.ratio, "sample_phase": a.sample_phase, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
