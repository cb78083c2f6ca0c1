"""``coiltrack perf``: the firmware's work told apart from the machine's (``tools/bench/tick_noise.py``):
page faults, context switches and core changes around each tick, replays compared tick by tick,
and a harness that does not make the firmware fault. Counts and times are injected: no clock is
asserted."""
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from coiltrack.tools.bench.tick_noise import FIELDS, MachineProbe, recurrence, summarise


def _usage(minflt=0, majflt=0, nivcsw=0, nvcsw=0):
    return SimpleNamespace(ru_minflt=minflt, ru_majflt=majflt, ru_nivcsw=nivcsw, ru_nvcsw=nvcsw)


def _probe(readings):
    """A probe fed ``readings``: (usage, core) per read, in order."""
    it = iter(readings)
    cur = {}

    def usage():
        cur["u"], cur["c"] = next(it)
        return cur["u"]

    return MachineProbe(usage=usage, cpu=lambda: cur["c"])


def test_probe_rows_split_inside_the_tick_from_before_it():
    """Three ticks, the counters given: the first tick's row holds only what happened between
    its two reads (no 'before' for a first tick); the second tick began after a voluntary and
    an involuntary switch that happened between the ticks (before = 2, none inside) and faulted
    three pages (one major) inside; the third was preempted inside and ended on another core.
    Catches the between-ticks switches counted as inside the tick (a preemption blamed on the
    firmware's tick), a fault counted twice, and a core change missed."""
    p = _probe([(_usage(10, 0, 5, 5), 0), (_usage(12, 0, 5, 5), 0),           # tick 1: 2 minor faults
                (_usage(12, 0, 6, 6), 0), (_usage(14, 1, 6, 6), 0),           # tick 2: switched before, 3 faults
                (_usage(14, 1, 6, 6), 0), (_usage(14, 1, 7, 6), 1)])          # tick 3: preempted, core 0 -> 1
    rows = []
    for _ in range(3):
        p.before()
        rows.append(dict(zip(FIELDS, p.after())))
    assert rows[0] == {"minflt": 2, "majflt": 0, "nivcsw": 0, "nvcsw": 0, "switches_before": 0, "migrated": 0}
    assert rows[1] == {"minflt": 2, "majflt": 1, "nivcsw": 0, "nvcsw": 0, "switches_before": 2, "migrated": 0}
    assert rows[2] == {"minflt": 0, "majflt": 0, "nivcsw": 1, "nvcsw": 0, "switches_before": 0, "migrated": 1}


def test_probe_reads_this_thread_by_default():
    """The default probe reads the real counters: every field an integer >= 0, the core a number."""
    p = MachineProbe()
    p.before()
    x = sum(range(1000))                                   # some work between the reads
    row = p.after()
    assert x and len(row) == len(FIELDS) and all(isinstance(v, int) and v >= 0 for v in row)


def test_summary_keeps_the_disturbed_ticks_out_of_the_undisturbed_figures():
    """1000 ticks of 10 us; four disturbed ones are the costliest: a preempted one (900 us), one
    after a switch (600 us), one with page faults (400 us), one on a new core (300 us), and one
    undisturbed tick of 200 us. The undisturbed maximum is that 200 us tick, each disturbance
    counts its own tick with its CPU time, and the tick at or above the p99.9 (interpolated:
    600.3 us, so the costliest alone) is the preempted one; against a 500 us tick the two
    misses are counted as disturbed ones. Catches a disturbed tick left in the undisturbed
    figures, and one counted under two causes."""
    n = 1000
    cpu = np.full(n, 10_000, dtype=np.int64)
    rows = np.zeros((n, len(FIELDS)), dtype=np.int64)
    cpu[[1, 2, 3, 4, 5]] = [900_000, 600_000, 400_000, 300_000, 200_000]
    rows[1, FIELDS.index("nivcsw")] = 1
    rows[1, FIELDS.index("switches_before")] = 1       # switched before and inside: counted as preempted
    rows[2, FIELDS.index("switches_before")] = 2
    rows[3, FIELDS.index("minflt")] = 3
    rows[3, FIELDS.index("majflt")] = 1
    rows[4, FIELDS.index("migrated")] = 1
    s = summarise(cpu, rows, deadline_ns=500_000)
    assert s["undisturbed"] == {"ticks": n - 4, "median": 10.0, "p999": pytest.approx(s["undisturbed"]["p999"]),
                                "max": 200.0, "deadline_misses": 0}
    assert s["disturbed"] == {"ticks": 4, "deadline_misses": 2}       # 900 and 600 us against a 500 us tick
    assert s["page_faults"] == {"ticks": 1, "faults": 4, "major": 1, "median": 400.0, "max": 400.0}
    assert s["preempted"] == {"ticks": 1, "median": 900.0, "max": 900.0}
    assert s["switched_before"] == {"ticks": 1, "median": 600.0, "max": 600.0}
    assert s["migrated"] == {"ticks": 1, "median": 300.0, "max": 300.0}
    assert s["worst_disturbed"] == {"ticks": 1, "disturbed": 1, "page_faults": 0, "preempted": 1}


def test_recurrence_finds_the_work_that_stays_and_the_noise_that_moves():
    """Three replays of 100 ticks: tick 40 costs 150 us in every replay (the firmware's work);
    each replay has one 500 us tick elsewhere (the machine: 10, 20, 30). The least time per tick
    names tick 40 first at 150 us with its three times; each replay's costliest tick is its own
    noise; of each replay's two costliest ticks, the first replay's set keeps tick 40 only.
    Catches the maximum over replays taken instead of the minimum (the noise would lead), and
    the ticks matched by rank instead of by time."""
    t = [5_000_000 + 1000 * i for i in range(100)]
    runs = np.full((3, 100), 10_000, dtype=np.int64)
    runs[:, 40] = 150_000
    for k, i in enumerate((10, 20, 30)):
        runs[k, i] = 500_000
    r = recurrence(runs, t, 2)
    assert r["runs"] == 3
    assert r["worst"][0] == {"t_us": t[40], "min_us": 150.0, "cpu_us": [150.0, 150.0, 150.0]}
    assert r["min_us"]["max"] == 150.0 and r["min_us"]["median"] == 10.0
    assert r["max_at"] == [t[10], t[20], t[30]]
    assert r["worst_kept"] == [2, 1, 1]
    with pytest.raises(ValueError):
        recurrence(runs, t[:50], 2)


def test_recorder_keeps_no_python_object_per_tick():
    """The recorder's per-tick records go into arrays made at start: 3000 ticks of a stand-in
    firmware (a tick that does nothing) leave the interpreter's live blocks where 300 left them
    (within 200: no per-tick object kept), and the figures are all there. Catches the records
    kept in growing lists again: a Python int or tuple per tick grows the heap, and the
    firmware's own short-lived objects then land on pages touched for the first time inside its
    timed ticks (a page fault each)."""
    from coiltrack.firmware.loop import PHASES
    from coiltrack.tools.commands.perf import _TickRecorder

    r = _TickRecorder(warm=0, worst=5, core=None, capacity=3000)
    fw = SimpleNamespace(receiver=SimpleNamespace(imu_received=0), tracker=SimpleNamespace())
    r.fw, r._models, r._filters = fw, (), ()
    r._tw = SimpleNamespace(begin=lambda: None, end=lambda: "idle")
    r._real_tick = lambda t, out: None
    for t in range(0, 300_000, 1000):
        r.tick(t)
    before = sys.getallocatedblocks()
    for t in range(300_000, 3_000_000, 1000):
        r.tick(t)
    assert sys.getallocatedblocks() - before < 200
    assert r.n == 3000 and r._cpu.size == 3000
    assert list(r.t_us[:2]) == [0, 1000] and r.phase_ns.shape == (len(PHASES), 3000)
    assert r.kinds == ["idle"] * 3000 and r.machine.shape == (3000, len(FIELDS))
    assert len(r.per_tick) == 3000 and r.per_tick[0][8] == "idle"


def test_perf_reports_the_machine_and_the_replays():
    """``roetenberg-bench``, 3 s recorded, 2 s of warm-up, two replays: the report keeps its keys
    and adds ``machine`` (the undisturbed ticks and the disturbances partition no more than the
    ticks) and ``repeat`` (the least time per tick is at most each replay's time at that tick);
    the worst ticks carry their machine row and work class; the table names both."""
    from coiltrack.tools.commands.perf import _record, format_table, measure

    header, reads = _record("roetenberg-bench", 1, 3.0)
    rep = measure(header, reads, 2.0, worst=4, repeat=2)
    for key in ("tick_cpu_us_max", "tick_cpu_us_p999", "cpu_deadline_misses", "work_classes", "worst_ticks"):
        assert key in rep
    m = rep["machine"]
    assert m["undisturbed"]["ticks"] + m["preempted"]["ticks"] + m["switched_before"]["ticks"] <= rep["ticks"]
    assert m["undisturbed"]["max"] is None or m["undisturbed"]["max"] <= rep["tick_cpu_us_max"]
    r = rep["repeat"]
    assert r["runs"] == 2 and len(r["max_at"]) == 2
    for w in r["worst"]:
        assert w["t_us"] >= 2_000_000 and len(w["cpu_us"]) == 2 and w["min_us"] == min(w["cpu_us"])
    assert r["min_us"]["max"] <= rep["tick_cpu_us_max"]
    for w in rep["worst_ticks"]:
        assert set(w["machine"]) == set(FIELDS) and w["work_class"]
    # neither the recorder nor the firmware keeps a Python object per tick (1001 ticks measured)
    assert isinstance(rep["python_blocks_kept"], int) and rep["python_blocks_kept"] < rep["ticks"] // 10
    table = format_table(rep)
    assert "the machine" in table and "2 replays" in table and "Python objects kept" in table
