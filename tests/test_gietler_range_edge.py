"""The iterated EKF at the edge of the 2 m range (Gietler Table I's one divergence, seed 98).

What the divergence is: the true platform of seed 98 reaches 1.99 m; there the field of each
emitter (0.01-0.02 A/m) is at the noise, the filter's radial standard deviation is 0.05-0.17 m,
and a consistent estimate crosses the 2 m line (the paper's divergence rule) a step before the
truth does. The filter is not running off and its covariance has not collapsed: these tests pin
both facts (``_edge_sigma`` in ``tools/bench/gietler.py`` measures the first), with the emulated fields of ``hil.gietler`` (not the firmware's model) as the truth.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from coiltrack.firmware.estimate.brownian import BrownianEKF
from coiltrack.firmware.estimate.layout import BROWNIAN_LAYOUT as L
from coiltrack.hil import gietler as hg
from coiltrack.tools.bench import gietler as G
from coiltrack.tools.scenarios.gietler import EDGE_SIGMA, SPECS, _split


def test_seed_98_crosses_the_boundary_the_truth_has_nearly_reached():
    """Table I, seed 98, sigma^2 = 1e-4 (one run, 200 steps): the iterated EKF is counted diverged,
    and at that step the true platform was within ``EDGE_SIGMA`` (3) of the filter's radial standard
    deviations of 2 m (measured 0.31). Catches the diagnostic measuring the margin from the estimate
    instead of the truth, or in metres instead of standard deviations, and a change of the filter
    that makes this run run off (margin far beyond 3 sigma)."""
    spec, cfg = _split("gietler-air", (("noise.var", 1e-4),))
    r = G.run(spec, cfg, 98, variants=(("", "extended", True),))
    assert r["diverged"] == 1
    assert r["edge_sigma"] is not None and 0.0 <= r["edge_sigma"] <= EDGE_SIGMA


def test_the_filter_is_consistent_at_the_range_edge():
    """A platform in the Table I Brownian motion (eq 8, sigma_v 0.01, sigma_w 0.1) started at
    1.59 m flying out at 0.1 m/s, 40 steps of 0.1 s, sigma^2 = 1e-4, tracked by the iterated EKF
    from a start drawn from its own P0, over 30 seeds: the position NEES at the last step, summed
    over the seeds, lies in the two-sided 99.9 % chi-square band of 90 degrees of freedom
    (measured 84.5 in [53.6, 139]), and the squared radial errors in the filter's own radial
    standard deviations sum below the 99.9 % bound of 30 degrees of freedom (measured 38.1 against
    59.7); yet estimates end beyond 2 m (measured 6 of 30), so counting them as divergences counts
    the noise, not the filter. Catches a covariance that collapses where the signal is at the noise:
    each iterate updating P from the previous iterate's P instead of the prediction P^- (measured
    radial sum 79)."""
    n, seeds, noise = 40, 30, 1e-4
    u = np.array([0.8, 0.5, 0.33])
    u /= np.linalg.norm(u)
    theta = np.array([0.02, -0.05, 0.7])
    model = G.platform_model(SPECS["gietler-air"], True, None)
    P0 = np.diag([1e-4] * 3 + [1e-3] * 9)
    nees, beyond, radial = 0.0, 0, []
    for s in range(seeds):
        truth = hg.brownian_truth(s, n * 0.1, 0.1, 0.01, 0.1, 1.59 * u, 0.1 * u, theta)
        z, v = truth["z"], truth["v"][0]
        V = hg.measurements(hg.true_fields(truth), noise, False, np.random.default_rng(s))
        f = BrownianEKF(model, 0.1, 0.01, 0.1, noise, iterations=3, tol=1e-4)
        x0 = np.zeros(L.n)
        x0[L.VEL], x0[L.POS], x0[L.THETA] = v, z[0], theta
        f.reset(x0 + np.random.default_rng(1000 + s).multivariate_normal(np.zeros(L.n), P0), P0)
        for k in range(1, n + 1):
            f.step(V[k])
        e = f.x[L.POS] - z[n]
        ur = z[n] / np.linalg.norm(z[n])
        nees += float(e @ np.linalg.solve(f.P[L.POS, L.POS], e))
        beyond += float(np.linalg.norm(f.x[L.POS])) > 2.0
        radial.append(float(ur @ e) / float(np.sqrt(ur @ f.P[L.POS, L.POS] @ ur)))
    assert stats.chi2.ppf(0.0005, 3 * seeds) <= nees <= stats.chi2.ppf(0.9995, 3 * seeds), nees
    assert float(np.sum(np.square(radial))) <= stats.chi2.ppf(0.999, seeds), radial
    assert beyond >= 3, beyond


def _bench_h(x):
    """The emitters' field at the receiver for state ``x`` (12,), from the bench's eq 1
    (``hil.gietler.true_fields``, not the firmware's model), in the measurement order (9,)."""
    return hg.true_fields({"z": x[None, L.POS], "theta": x[None, L.THETA]})[0].real.reshape(9)


def test_the_crossing_estimate_is_the_map_of_its_step():
    """Table I, seed 98, sigma^2 = 1e-4: at the step where the iterated EKF crosses 2 m (193), its
    estimate is the minimiser of that step's MAP cost ``|L^-1 (x - x^-)|^2 + |V - h(x)|^2 / sigma^2``
    (``P^- = L L^T`` the filter's prediction), found independently by scipy's least_squares with the
    bench's field as ``h``, started at the prediction: position within 1 mm (measured 0.07 mm; the
    filter's radial standard deviation there is 47 mm), and that minimiser is itself beyond 2 m.
    So the crossing is the data's, not an iteration stopped short or running off. Catches the
    relinearised residual without the ``H (x^- - x_i)`` term or with its sign flipped, and the
    iteration budget ignored (one linearisation: the plain EKF's update, 3.9 mm off here)."""
    from scipy.optimize import least_squares

    spec, cfg = _split("gietler-air", (("noise.var", 1e-4),))
    truth, V = G.truth_and_measurements(spec, 98, None)
    model = G.platform_model(spec, True, None)
    f = BrownianEKF(model, cfg.gietler_dt_s, cfg.gietler_sigma_v, cfg.gietler_sigma_w, 1e-4,
                    iterations=cfg.gietler_iterations, tol=cfg.gietler_iter_tol)
    x0 = np.zeros(L.n)
    x0[L.POS], x0[L.THETA] = spec.x0_filter["z"], spec.x0_filter["theta"]
    f.reset(x0, cfg.gietler_p0 * np.eye(L.n))
    for t in range(1, 193):
        f.step(V[t])
    assert np.linalg.norm(f.x[L.POS]) < 2.0
    f.predict()
    xp, Pp = f.x.copy(), f.P.copy()
    f.update(V[193])
    assert np.linalg.norm(f.x[L.POS]) > 2.0
    Li = np.linalg.inv(np.linalg.cholesky(Pp))
    sol = least_squares(lambda x: np.concatenate([Li @ (x - xp), (V[193] - _bench_h(x)) / 1e-2]), xp,
                        xtol=1e-12, ftol=1e-12, gtol=1e-12)
    assert sol.success
    assert np.linalg.norm(sol.x[L.POS] - f.x[L.POS]) < 1e-3, (sol.x[L.POS], f.x[L.POS])
    assert np.linalg.norm(sol.x[L.POS]) > 2.0
