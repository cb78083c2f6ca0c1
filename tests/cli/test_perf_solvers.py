"""``coiltrack perf --solver both`` (``tools/analyses/perf_solvers.py``): the cost ratios of
Raab's tracker to the least squares on the same recorded inputs."""
from coiltrack.tools.commands.perf import _record
from coiltrack.tools.analyses.perf_solvers import format_solver_costs, solver_costs


def test_ratios_are_reported_and_raab_does_a_third_of_the_evaluations():
    """8 s of ``raab-acquire`` (a sensor at rest, one Raab update per burst),
    replayed with each solver after a 3 s warm-up: the report carries
    ``raab_lm_eval_ratio`` (means of field evaluations per burst solve) and
    ``raab_lm_time_ratio`` and ``raab_lm_cpu_ratio`` (medians of wall and CPU
time, not asserted: clocks), equal
    to the ratios of the per-solver figures, and the evaluation ratio is at
    most 1/3 (issue 12; field evaluations are machine-independent). Catches a
    ratio of the wrong figures and a tracker that evaluates the field on
    every update again."""
    header, reads = _record("raab-acquire", 1, 8.0)
    d = solver_costs(header, reads, ("lm", "raab"), 3.0)
    lm, ra = d["lm"], d["raab"]
    assert lm["updates"] == ra["updates"] > 5
    assert d["raab_lm_eval_ratio"] == round(ra["evals_mean"] / lm["evals_mean"], 3)
    assert d["raab_lm_time_ratio"] == round(ra["us_median"] / lm["us_median"], 3)
    assert d["raab_lm_cpu_ratio"] == round(ra["cpu_us_median"] / lm["cpu_us_median"], 3)
    assert d["raab_lm_eval_ratio"] <= 1.0 / 3.0
    assert "raab / lm per update" in format_solver_costs(d)
