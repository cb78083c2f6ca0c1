"""A divergence at the edge of the 2 m range: the filter running off, or the truth reaching the line?

``python -m coiltrack.tools.analyses.gietler_edge [--scenario gietler-air] [--seed 98] [--noise-var 1e-4]
[--streams 100] [--check-iterations 30]``

Gietler et al. 2019 (``seeds/003_93f59c2e1c5b6c59.txt``, sec III-C) count a run as diverged
when the estimated position is farther than 2 m from the receiver. The eq-8 motion is unbounded,
so a true platform may itself come to the line; a run here ends, undiverged, when the truth
leaves the 2 m sphere (``tools/bench/gietler.py``). For one seed this command prints:

1. The seed's own run (the sweep's measurements, the configured iterated EKF): the last scored
   step and the truth's range there; at the step where the estimate crosses 2 m, the truth's and
   the estimate's range, the position error projected on the truth's direction in the filter's
   own radial standard deviations ``sqrt(u^T P u)``, the position NEES ``e^T P^-1 e`` (3 degrees
   of freedom), the iterates used; and whether a budget of ``--check-iterations`` iterates gives
   the same crossing (the iteration converged; it stops earlier when no state moves by more than
   ``gietler_iter_tol``).
2. The same true trajectory under ``--streams`` independent measurement-noise streams, each
   filtered through every scored step (not stopped at a crossing, so that the error figures are
   not selected): the fraction of streams whose estimate crosses 2 m at a scored step (the
   paper's rule); at the last scored step the mean radial error in radial standard deviations
   (0 for an unbiased filter) and the mean position NEES (3 for a consistent one, with the
   two-sided 99.9 % chi-square band of ``3 x streams`` degrees of freedom scaled to a mean) and
   its median (2.37 for a consistent one: the mean is sensitive to a few streams far off); and
   the probability that an unbiased, consistent estimate with the filter's own covariance lies
   beyond 2 m at the last scored step, ``P(|z + e| > 2 m)``, ``e ~ N(0, P_pos)`` (sampled, 4000
   draws per stream): a lower bound on how often such an estimate crosses the line at some step.

Work, not time, is what it reports; it allocates freely (it is a command, not firmware).
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from coiltrack.tools import args as A
from ..bench import gietler as G


def _filter(spec, cfg, model, iterations):
    from coiltrack.firmware.estimate.brownian import BrownianEKF
    from coiltrack.firmware.estimate.layout import BROWNIAN_LAYOUT as L

    f = BrownianEKF(model, cfg.gietler_dt_s, cfg.gietler_sigma_v, cfg.gietler_sigma_w, cfg.gietler_noise_var,
                    iterations=iterations, tol=cfg.gietler_iter_tol)
    x0 = np.zeros(L.n)
    x0[L.VEL], x0[L.POS] = spec.x0_filter["v"], spec.x0_filter["z"]
    x0[L.RATE], x0[L.THETA] = spec.x0_filter["omega"], spec.x0_filter["theta"]
    f.reset(x0, cfg.gietler_p0 * np.eye(L.n))
    return f


def scored_steps(spec, truth) -> int:
    """The last scored step of a run, as ``tools.bench.gietler.run_filter`` ends it: the step before
    the true platform first leaves the 2 m sphere or comes within ``min_range_m`` of the
    receiver with emitter 1 or the cube's centre."""
    r = np.linalg.norm(truth["z"][1:], axis=1)
    near = r < spec.min_range_m
    if spec.cube_center is not None:
        from coiltrack.hil.motion import euler_zyx_to_matrix

        c = truth["z"][1:] + np.einsum("nij,j->ni", euler_zyx_to_matrix(truth["theta"][1:]),
                                       np.asarray(spec.cube_center))
        near |= np.linalg.norm(c, axis=1) < spec.min_range_m
    out = np.flatnonzero((r > 2.0) | near)
    return int(out[0]) if out.size else len(r)


def own_run(spec, cfg, model, truth, V, iterations, diverge_m):
    """The seed's run until the estimate crosses ``diverge_m``: a dict of the crossing's figures
    (``step`` None when it does not cross at a scored step)."""
    from coiltrack.firmware.estimate.layout import BROWNIAN_LAYOUT as L

    n_end = scored_steps(spec, truth)
    f = _filter(spec, cfg, model, iterations)
    for t in range(1, n_end + 1):
        f.step(V[t])
        zh = f.x[L.POS]
        if float(np.linalg.norm(zh)) > diverge_m:
            z = truth["z"][t]
            P = f.P[L.POS, L.POS]
            e = zh - z
            u = z / float(np.linalg.norm(z))
            sr = math.sqrt(float(u @ P @ u))
            return {"step": t, "n_end": n_end, "r_true": float(np.linalg.norm(z)), "r_hat": float(np.linalg.norm(zh)),
                    "radial_sigmas": float(u @ e) / sr, "sigma_r": sr, "nees": float(e @ np.linalg.solve(P, e)),
                    "error_m": float(np.linalg.norm(e)), "margin_sigmas": (diverge_m - float(np.linalg.norm(z))) / sr,
                    "iterates": f.iterations_last}
    return {"step": None, "n_end": n_end}


def streams(spec, cfg, model, truth, fields, n_streams, seed, diverge_m, draws=4000):
    """The true trajectory under ``n_streams`` noise streams (see the module): a dict of the
    crossing fraction and the last scored step's error figures."""
    from coiltrack.firmware.estimate.layout import BROWNIAN_LAYOUT as L
    from coiltrack.hil import gietler as hg

    n_end = scored_steps(spec, truth)
    z = truth["z"][n_end]
    u = z / float(np.linalg.norm(z))
    crossed, radial, nees, beyond = 0, [], [], []
    gauss = np.random.default_rng(np.random.SeedSequence([seed, 0xED6E]))
    for k in range(n_streams):
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0xED6E, k]))
        V = hg.measurements(fields, spec.noise_var, spec.freq_hz > 0.0, rng)
        f = _filter(spec, cfg, model, cfg.gietler_iterations)
        c = False
        for t in range(1, n_end + 1):
            f.step(V[t])
            c |= float(np.linalg.norm(f.x[L.POS])) > diverge_m
        crossed += c
        P = f.P[L.POS, L.POS]
        e = f.x[L.POS] - z
        radial.append(float(u @ e) / math.sqrt(float(u @ P @ u)))
        nees.append(float(e @ np.linalg.solve(P, e)))
        s = z + gauss.multivariate_normal(np.zeros(3), P, size=draws)
        beyond.append(float(np.mean(np.linalg.norm(s, axis=1) > diverge_m)))
    return {"n_end": n_end, "r_true": float(np.linalg.norm(z)), "streams": n_streams, "crossed": crossed,
            "radial_sigmas_mean": float(np.mean(radial)), "radial_sigmas_sd": float(np.std(radial)),
            "nees_mean": float(np.mean(nees)), "nees_median": float(np.median(nees)), "p_beyond_consistent": float(np.mean(beyond))}


def main(argv=None) -> int:
    # imported where used here and below: the scenarios (scipy underneath) load only when needed, not for --help
    from ..scenarios.gietler import SPECS, _split

    p = argparse.ArgumentParser(prog="python -m coiltrack.tools.analyses.gietler_edge", description=__doc__.split("\n")[0])
    p.add_argument("--scenario", default="gietler-air", choices=sorted(k for k, s in SPECS.items()
                                                                       if s.trajectory == "brownian"))
    p.add_argument("--seed", type=A.integer(0, 2 ** 31 - 1), default=98)
    p.add_argument("--noise-var", type=A.real(0.0, lo_open=True), default=1e-4,
                   help="sigma^2, (A/m)^2 (default 1e-4)")
    p.add_argument("--streams", type=A.integer(0, 10000), default=100,
                   help="independent noise streams on the seed's trajectory (default 100; 0: the seed's run only)")
    p.add_argument("--check-iterations", type=A.integer(1, 100), default=30,
                   help="iterate budget of the convergence check (default 30)")
    a = p.parse_args(argv)

    spec, cfg = _split(a.scenario, (("noise.var", a.noise_var),))
    obj = G.bench_object(spec)
    truth, V = G.truth_and_measurements(spec, a.seed, obj)
    model = G.platform_model(spec, True, obj)
    dm = cfg.gietler_diverge_m
    print(f"{a.scenario}, seed {a.seed}, sigma^2 = {a.noise_var:g} (A/m)^2, iterated EKF "
          f"(budget {cfg.gietler_iterations}, tol {cfg.gietler_iter_tol:g}), extended model")
    r = own_run(spec, cfg, model, truth, V, cfg.gietler_iterations, dm)
    n_end = r["n_end"]
    print(f"  scored steps 1..{n_end}; truth at the last scored step {np.linalg.norm(truth['z'][n_end]):.4f} m, "
          f"farthest over the whole trajectory {np.max(np.linalg.norm(truth['z'], axis=1)):.4f} m")
    if r["step"] is None:
        print(f"  the estimate stays within {dm:g} m over the scored steps")
    else:
        print(f"  estimate crosses {dm:g} m at step {r['step']}: |z| {r['r_true']:.4f} m, |z^| {r['r_hat']:.4f} m, "
              f"error {r['error_m']:.3f} m, radial error {r['radial_sigmas']:+.2f} sigma_r (sigma_r "
              f"{r['sigma_r'] * 1e3:.1f} mm), NEES {r['nees']:.2f} (3 dof), truth {r['margin_sigmas']:.2f} sigma_r "
              f"inside {dm:g} m, {r['iterates']} iterates")
        c = own_run(spec, cfg, model, truth, V, a.check_iterations, dm)
        same = c["step"] == r["step"]
        print(f"  with a budget of {a.check_iterations} iterates: "
              + ("no crossing" if c["step"] is None else
                 f"crossing at step {c['step']} ({c['iterates']} iterates), |z^| {c['r_hat']:.4f} m")
              + (" (the same crossing)" if same else " (a different outcome)"))
    if a.streams:
        from coiltrack.hil.gietler import true_fields

        fields = true_fields(truth, obj)
        s = streams(spec, cfg, model, truth, fields, a.streams, a.seed, dm)
        try:
            from scipy import stats  # the dev extra: only for the band
            band = "(99.9 %% band %.2f..%.2f)" % tuple(stats.chi2.ppf(q, 3 * a.streams) / a.streams
                                                     for q in (0.0005, 0.9995))
        except ImportError:
            band = "(3 expected)"
        print(f"  {a.streams} independent noise streams on this trajectory, {s['n_end']} scored steps each:")
        print(f"    estimate beyond {dm:g} m at a scored step (counted diverged): {s['crossed']} of {a.streams}")
        print(f"    at the last scored step (truth {s['r_true']:.4f} m): radial error {s['radial_sigmas_mean']:+.2f} "
              f"+- {s['radial_sigmas_sd']:.2f} sigma_r, mean NEES {s['nees_mean']:.2f} {band}, median "
              f"{s['nees_median']:.2f} (2.37 for 3 dof)")
        print(f"    an unbiased, consistent estimate with the filter's covariance lies beyond {dm:g} m there with "
              f"probability {s['p_beyond_consistent']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
