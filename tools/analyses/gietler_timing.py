"""Time per filter iteration of Gietler's trackers against the paper's 2.5 / 20 / 200 ms (sec IV-D).

``python -m coiltrack.tools.analyses.gietler_timing [--steps N] [--lattice N]``: one seed's emulated
measurements (sigma^2 = 1e-3), then ``N`` filter steps (prediction and update) of the plain
and the iterated EKF with the base model (3 emitter dipoles; the paper's air case) and with
the extended model (3 + 3 x 79 dipoles; the conductive case, and the conductive and
ferromagnetic one). Prints per step the median and p90 wall time, the model evaluations
(iterates) and field evaluations (sources evaluated), which do not depend on the machine.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from ..bench import gietler as G

CASES = (("air (base model H0)", "gietler-air", "extended", 2.5),
         ("copper cube (extended H, 79 sub-volumes)", "gietler-copper", "extended", 20.0),
         ("ferromagnetic cube (extended H, 79 sub-volumes)", "gietler-ferro", "extended", 200.0))


def main(argv=None) -> int:
    # imported where used here and below: the scenarios (scipy underneath) load only when needed, not for --help
    from ..scenarios.gietler import _split

    p = argparse.ArgumentParser(prog="python -m coiltrack.tools.analyses.gietler_timing", description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--lattice", type=int, default=10, help="bench cells per cube edge (default 10)")
    a = p.parse_args(argv)
    if not 1 <= a.steps <= 800 or not 2 <= a.lattice <= 14:
        print("gietler_timing: --steps in 1..800, --lattice in 2..14")
        return 2
    from coiltrack.firmware.estimate.brownian import BrownianEKF
    from coiltrack.firmware.estimate.layout import BROWNIAN_LAYOUT as L

    print(f"{'case':<48} {'filter':<13} {'us/step median':>14} {'p90':>8} {'iterates/step':>13} "
          f"{'field evals/step':>16} {'paper ms':>8}")
    for label, scen, model_name, paper_ms in CASES:
        spec, cfg = _split(scen, (("noise.var", 1e-3),))
        spec = replace(spec, lattice_n=a.lattice)
        obj = G.bench_object(spec)
        truth, V = G.truth_and_measurements(spec, 1, obj)
        for fname, iterated in (("EKF", False), ("iterated EKF", True)):
            model = G.platform_model(spec, True, obj)
            f = BrownianEKF(model, cfg.gietler_dt_s, cfg.gietler_sigma_v, cfg.gietler_sigma_w, cfg.gietler_noise_var,
                            iterations=cfg.gietler_iterations if iterated else 1, tol=cfg.gietler_iter_tol)
            x0 = np.zeros(L.n)
            x0[L.POS], x0[L.THETA] = spec.x0_filter["z"], spec.x0_filter["theta"]
            f.reset(x0, cfg.gietler_p0 * np.eye(L.n))
            n = min(a.steps, len(V) - 1)
            dt = np.zeros(n)
            for t in range(1, n + 1):
                t0 = time.perf_counter()
                f.step(V[t])
                dt[t - 1] = time.perf_counter() - t0
            print(f"{label:<48} {fname:<13} {np.median(dt) * 1e6:14.0f} {np.percentile(dt, 90) * 1e6:8.0f} "
                  f"{f.iterations_total / n:13.2f} {model.evals / n:16.0f} {paper_ms:8.1f}")
            label = ""
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
