"""The in-process bench's tick timing (tools.bench.runner._tick_loop): each tick's thread CPU time
beside its wall time, replayed on the real-time schedule (timing.inproc_cpu_timing), and the
interpreter's cyclic collector held off inside the timed tick (a collection there scans every
object of the process: the world's, the nodes', the recorder's), run after it instead."""
import gc

import numpy as np

from coiltrack.tools.bench.runner import _tick_loop
from coiltrack.tools.bench.ticktrace import TickTrace
from coiltrack.tools.bench.timing import inproc_cpu_timing


class _Emu:
    def __init__(self):
        self.junk = []

    def step(self, t):
        for _ in range(50):             # cycles: the collector has work whenever it runs
            a = []
            a.append(a)
            self.junk.append(a)


class _Fw:
    poses = 0

    def __init__(self):
        self.ticks = 0
        self.junk = []

    def tick(self, t):
        self.ticks += 1
        for _ in range(3000):           # enough allocations to trigger a collection every tick
            d = {}
            d["self"] = d
            self.junk.append(d)


class _Prog:
    def update(self, *a):
        pass


def test_no_collection_inside_a_timed_tick_and_cpu_times_kept():
    fw, emu = _Fw(), _Emu()
    bench = type("B", (), {"emulator": emu})()
    trace = TickTrace(12)
    seen = {"in": 0, "out": 0}

    def cb(phase, info):
        if phase == "start":
            seen["in" if trace.in_tick else "out"] += 1

    was = gc.isenabled()
    gc.enable()
    gc.callbacks.append(cb)
    try:
        cpu = []
        t, ex, stopped = _tick_loop(bench, fw, None, 10_000, 1000, _Prog(), cpu_out=cpu, trace=trace)
    finally:
        gc.callbacks.remove(cb)
        if not was:
            gc.disable()
    assert gc.isenabled() or not was
    assert stopped is None and fw.ticks == 11 and ex.size == 11 and cpu[0].size == 11
    assert seen["in"] == 0 and seen["out"] > 0      # collections ran, all between ticks
    assert np.all(cpu[0] > 0) and trace.n == 11
    assert np.array_equal(trace.ns[1, :11], cpu[0])


def test_cpu_timing_replays_cpu_times():
    ns = np.full(100, 50_000, dtype=np.int64)
    ns[10] = 2_300_000                                 # one 2.3 ms tick: itself and the slot it swallowed
    ns[40] = 999_000                                   # under the period: no miss
    out = inproc_cpu_timing(ns, 1000)
    assert out["cpu_deadline_misses"] == 2
    assert out["tick_cpu_us_max"] == 2300.0 and out["tick_cpu_us_median"] == 50.0
    assert set(out) == {"tick_cpu_us_median", "tick_cpu_us_p99", "tick_cpu_us_p999", "tick_cpu_us_max",
                        "cpu_deadline_misses"}


def test_trace_summary_tells_the_pieces_apart():
    """A tick over the period by its port's writes alone is a miss on CPU, none without the I/O;
    one over it by the bus alone, none without the bus; the collector's time is its own piece."""
    tr = TickTrace(10)
    for k in range(10):
        tr.begin(k)
        tr.add(2, 20_000)                       # read 20 us
        if k == 3:
            tr.add(3, 1_100_000)                # a write of 1.1 ms ...
            tr.add(4, 900_000)                  # ... 0.9 ms of it the bus's send
            tr.add(6, 46)
        if k == 6:
            tr.add(8, 1_200_000)                # a 1.2 ms collection inside the tick
        own = 30_000 + (1_200_000 if k == 6 else 0)
        tr.end(k, 50_000 + own + (1_100_000 if k == 3 else 0), 20_000 + own + (1_100_000 if k == 3 else 0))
    s = tr.summary(1000)
    assert s["ticks"] == 10
    assert s["misses"] == {"wall": 2, "cpu": 2, "cpu_without_gc": 1, "cpu_without_bus": 1, "cpu_without_io": 1}
    assert [t["tick"] for t in s["ticks_over_period_cpu"]] == [3, 6]
    assert s["ticks_over_period_cpu"][0]["frames_tx"] == 46 and s["ticks_over_period_cpu"][1]["gc_us"] == 1200
    assert s["write"]["max"] == 1100.0 and s["frames_tx"]["max"] == 46
