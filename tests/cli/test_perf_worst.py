"""``coiltrack perf --worst N`` (``tools/commands/perf.py``): the ticks of the most CPU time, each
with what it did, and the garbage collections told apart from the firmware's work."""
from coiltrack.firmware.loop import PHASES
from coiltrack.tools.commands.perf import _record, format_table, measure


def test_worst_ticks_are_the_costliest_with_their_work():
    """``multi16``, 6 s recorded, replayed after a 4 s warm-up with ``worst`` above the tick
    count: every measured tick, in falling CPU time, the first five none below the run's CPU
    p99 (no clock is asserted against a number: only the order, which holds whatever the
    machine's timing); each names every stage and at most the budget's field evaluations;
    some tick (which ones are costliest depends on the machine) names the sensor being
    solved (16 sensors); the per-run keys of the collections are there and in the table.
    Catches the list sorted the wrong way (cheapest ticks), ticks of the warm-up listed (t
    before 4 s) and the evaluations of another tick attributed."""
    header, reads = _record("multi16", 1, 6.0)
    rep = measure(header, reads, 4.0, worst=10_000)
    w = rep["worst_ticks"]
    assert len(w) == 2001                               # 4.000 .. 6.000 s at 1 ms
    cpus = [x["cpu_us"] for x in w]
    assert cpus == sorted(cpus, reverse=True)
    assert cpus[4] >= rep["tick_cpu_us_p99"]            # 5 of 2001 ticks: above the p99
    assert cpus[0] == rep["tick_cpu_us_max"]
    for x in w:
        assert x["t_us"] >= 4_000_000
        assert list(x["phases_us"]) == list(PHASES)
        assert 0 <= x["field_evals"] <= rep["track_budget_evals"]
        assert x["gc_collections"] >= 0
    assert any("/16 (node " in x["tracker_at"] for x in w)
    assert rep["gc_collections_in_ticks"] >= 0 and rep["gc_us_max"] >= 0.0
    rep["worst_ticks"] = w[:5]
    table = format_table(rep)
    assert "ticks of the most CPU time" in table and "garbage collections" in table
