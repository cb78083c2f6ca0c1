"""``coiltrack perf``'s work classes (``tools/bench/work_classes.py``): each tick named by the work
the firmware's own counters say it did."""
from coiltrack.tools.commands.perf import _record, format_table, measure
from coiltrack.tools.scenarios import get
from coiltrack.tools.bench.work_classes import COMPONENTS, label


def test_label_names_the_pieces_in_order():
    """The class is the moved counters in the order of COMPONENTS, 'idle' for none. Catches a
    class that depends on the order the counters were read in, or a counter that went back
    (a negative delta) named as work."""
    assert label([0] * len(COMPONENTS)) == "idle"
    d = [0] * len(COMPONENTS)
    d[COMPONENTS.index("pose")] = 2
    d[COMPONENTS.index("imu")] = 1
    assert label(d) == "imu+pose"
    d[COMPONENTS.index("solve")] = -3
    assert label(d) == "imu+pose"


def test_classes_partition_the_ticks_and_follow_the_filters_rates():
    """``roetenberg-fusion``, 8 s recorded, 3 s of warm-up: the classes count every measured
    tick once; the ticks with an orientation update are the IMU ticks' ``1/ori_update_every``
    (the inclination update runs on every fourth sample; 0.02 allows for the run's ends and
    for samples that arrive two in a tick); some ticks close windows and some solve; the
    ticks at or above the p99.9 are 0.1 % of the ticks (within one tick, the percentile being
    interpolated). Catches the orientation counter reading the prediction (ratio 1), a
    counter read before the tick only (no class but idle), and classes counted twice."""
    cfg = get("roetenberg-fusion").firmware_config()
    header, reads = _record("roetenberg-fusion", 1, 8.0)
    rep = measure(header, reads, 3.0)
    wc = rep["work_classes"]
    assert sum(w["ticks"] for w in wc.values()) == rep["ticks"]
    imu = sum(w["ticks"] for k, w in wc.items() if "imu" in k.split("+"))
    ori = sum(w["ticks"] for k, w in wc.items() if "orientation" in k.split("+"))
    assert imu == rep["fused_ticks"]
    assert abs(ori / imu - 1.0 / cfg.orientation.ori_update_every) <= 0.02
    assert any("window" in k.split("+") for k in wc)
    assert any("solve" in k.split("+") for k in wc)
    top = sum(rep["p999_work_classes"].values())
    assert rep["ticks"] * 0.001 - 1 <= top <= rep["ticks"] * 0.001 + 2    # interpolated percentile, ties
    for w in wc.values():
        assert w["cpu_us_median"] <= w["cpu_us_p99"] <= w["cpu_us_max"]
    assert "work classes" in format_table(rep)


def test_the_worst_ticks_in_field_evaluations_time():
    """The p99.9 and the maximum of the tick's CPU time divided by one field evaluation's
    time measured in the same run (the budget's unit in this machine's time): the ratios are
    those of the reported CPU figures, and the costliest tick is worth at least the
    evaluations it did. Catches the ratio taken of the wall-clock or the median figures."""
    header, reads = _record("roetenberg-bench", 1, 4.0)
    rep = measure(header, reads, 2.0)
    ev = rep["field_eval_us"]
    assert ev > 0
    # the report rounds field_eval_us to 1 ns and the ratios to 0.1 (from the unrounded time): the
    # ratio recomputed here carries up to 0.5 ns / ev of relative error (2 evaluations at 344 us
    # with a 0.285 us evaluation of the compiled core), besides the ratio's own rounding
    for key, cpu in (("tick_p999_in_field_evals", "tick_cpu_us_p999"), ("tick_max_in_field_evals", "tick_cpu_us_max")):
        ratio = rep[cpu] / ev
        assert abs(rep[key] - ratio) <= 0.2 + ratio * 0.0005 / ev * 1.01, key
    assert rep["tick_max_in_field_evals"] >= rep["max_field_evals_per_tick"]
    assert "in the budget's unit" in format_table(rep)
