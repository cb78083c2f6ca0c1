"""The bench's Cramer-Rao bound takes its inputs from the bench's ground truth (``hil.crlb.TruthAmplitudes``):
the samples in each pulse's settled interval and the quiet baseline samples, from the true sample times and
pulse edges, and the currents the driver really achieved; never the firmware's PULSE_WINDOW counts."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from coiltrack.hil.crlb import amplitude_variance_factor
from coiltrack.tools.outputs import report as report_mod


def test_amplitude_variance_factor_against_monte_carlo():
    """The linear-baseline step model's variance factor against 20000 seeded least-squares fits of noisy
    data (numpy lstsq on independent draws): the sample variance of the fitted step inside the 99.9 %
    chi-square band; and the constant-baseline fallback 1/n_p + 1/n_b: catches the baseline's variance left
    out (the bound 1/n_p, too tight) or the slope's cost ignored."""
    rng = np.random.default_rng(5)
    tb = np.concatenate([np.arange(-35_000, 0, 8_333), np.arange(63_000, 98_000, 8_333)]).astype(float)
    tp = np.arange(3_000, 60_000, 8_333).astype(float)
    f = amplitude_variance_factor(tp, tb)
    t = np.concatenate([tp, tb])
    X = np.column_stack([np.ones(t.size), t * 1e-6, np.r_[np.ones(tp.size), np.zeros(tb.size)]])
    Y = rng.normal(size=(t.size, 20_000))
    A = np.linalg.lstsq(X, Y, rcond=None)[0][2]
    n = A.size
    s2 = A.var(ddof=1) / f * (n - 1)
    assert stats.chi2.ppf(0.0005, n - 1) < s2 < stats.chi2.ppf(0.9995, n - 1)
    assert f > 1 / tp.size + 1 / tb.size                 # the slope costs something
    # two samples cannot fit a slope: the constant baseline's 1/n_p + 1/n_b
    assert amplitude_variance_factor(tp[:1], tb[:1]) == pytest.approx(2.0, rel=1e-9)
    assert amplitude_variance_factor(tp, []) == np.inf


def test_crlb_ignores_the_firmwares_window_counts(bench_runner):
    """8 s of roetenberg-bench: a firmware reporting n_used = n_base = 1 in every PULSE_WINDOW leaves the
    bound unchanged (to 1e-12), where the old bound from the reported counts loosened 2.5 x; the bound's
    in-pulse samples are those after the true flat start (6-7 at 120 Hz in a 60 ms pulse), and its currents
    the achieved ones (the driver's regulation error, not the 1.5 A targets): catches the bound taking
    the firmware's counts or the commanded currents again."""
    run = bench_runner("roetenberg-bench", seed=1, duration_s=8.0)
    b, cfg, fw = run.bench, run.cfg, run.fw
    ref = report_mod.build(b, fw.status(), 8.0, transport="inproc", cfg=cfg)
    before = [rp["crlb_m"] for rp in b.recorder.poses if "crlb_m" in rp]
    assert len(before) >= 8
    one = lambda w: w._replace(n_used=1, n_base=1)       # noqa: E731
    b.recorder.windows = [(rx, one(w)) for rx, w in b.recorder.windows]
    for rp in b.recorder.poses:
        rp["windows"] = [one(w) for w in rp["windows"]]
    rep = report_mod.build(b, fw.status(), 8.0, transport="inproc", cfg=cfg)
    after = [rp["crlb_m"] for rp in b.recorder.poses if "crlb_m" in rp]
    np.testing.assert_allclose(after, before, rtol=1e-12)
    assert rep["crlb_position_rms_mm"] == ref["crlb_position_rms_mm"]
    from coiltrack.hil.crlb import TruthAmplitudes

    ta = TruthAmplitudes(b, run.scenario.sensor.noise_t, cfg.pulse.baseline_us)
    rp = next(r for r in b.recorder.poses if r["windows"])
    cur, sig = ta.for_pose(rp, 3)
    ex = {(e["coil"], e["pulse_id"]): e["current_a"] for e in b.driver.executed}
    for w in rp["windows"]:
        assert cur[w.coil] == ex[(w.coil, w.pulse_id)]
    assert np.all(np.abs(cur - 1.5) > 1e-5) and np.all(np.abs(cur - 1.5) < 1e-2)
    # the old figure from the reported counts (1 and 1) against the truth: sqrt(2) / sqrt(1/6.6 + ...) ~ 2.5
    f = (sig[0] / run.scenario.sensor.noise_t) ** 2
    assert np.all((f > 0.15) & (f < 0.5))
    assert np.sqrt(2.0 / f).min() > 2.0
