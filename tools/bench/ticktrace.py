"""A per-tick trace of the in-process bench's firmware tick, piece by piece: where a tick's time
goes between the firmware's own work, its port's reads and writes, and (on the CAN transport)
the bus's ``send`` and ``recv`` inside them.

Off by default: ``tools.bench.runner`` runs without it (``trace=None``: no wrapper, no
array, nothing allocated). On: ``python -m coiltrack.tools.bench.ticktrace --scenario multi16
--transport can`` runs the scenario as ``coiltrack bench`` does (simulated clock), the
firmware's port and bus wrapped by timers that add each call's thread CPU time
(``time.thread_time_ns``) into arrays sized up front, and prints per piece the median, p99 and
maximum and the deadline misses the replay (``tools.bench.timing.inproc_timing``) counts on
the wall time, the CPU time, the CPU time without the bus and without the port's I/O. The
timers' own cost (two clock reads a call, ~1 us) is in the traced tick's figures.
"""
from __future__ import annotations

import time

import numpy as np

#: the pieces traced, in the order of :attr:`TickTrace.ns`'s rows
PIECES = ("wall", "cpu", "read", "write", "bus_send", "bus_recv", "frames_tx", "frames_rx", "gc")


class TickTrace:
    """Per-tick sums, ``ns[piece, tick]`` (``PIECES``; the frame counts are counts). The
    loop calls :meth:`begin` and :meth:`end` around each tick; the timers add into the current
    tick's column."""

    def __init__(self, ticks: int):
        self.ns = np.zeros((len(PIECES), ticks), dtype=np.int64)
        self.k = 0
        self.n = 0
        self.in_tick = False
        self._gc_t0 = 0

    def begin(self, k: int) -> None:
        self.k = k
        self.in_tick = True

    def end(self, k: int, wall_ns: int, cpu_ns: int) -> None:
        self.in_tick = False
        self.ns[0, k] = wall_ns
        self.ns[1, k] = cpu_ns
        self.n = k + 1

    def on_gc(self, phase: str, info: dict) -> None:
        """``gc.callbacks``: the collector's CPU time inside a traced tick (piece ``gc``)."""
        if not self.in_tick:
            return
        if phase == "start":
            self._gc_t0 = time.thread_time_ns()
        else:
            self.add(8, time.thread_time_ns() - self._gc_t0)

    def add(self, row: int, ns: int) -> None:
        self.ns[row, self.k] += ns

    def summary(self, tick_us: int) -> dict:
        """Per piece: median, p99, max (us; frames: counts); misses on each measure."""
        from .timing import inproc_timing

        a = self.ns[:, :self.n]
        out: dict = {"ticks": self.n}
        for i, name in enumerate(PIECES):
            v = a[i] / (1.0 if name.startswith("frames") else 1000.0)
            if not v.size:
                continue
            out[name] = {"median": round(float(np.median(v)), 1), "p99": round(float(np.percentile(v, 99)), 1),
                         "max": round(float(v.max()), 1)}
        own = a[1] - a[2] - a[3]
        out["cpu_without_io"] = {"median": round(float(np.median(own)) / 1e3, 1),
                                 "p99": round(float(np.percentile(own, 99)) / 1e3, 1),
                                 "max": round(float(own.max()) / 1e3, 1)}
        miss = lambda ns: inproc_timing(ns, tick_us)["deadline_misses"]  # noqa: E731
        out["misses"] = {"wall": miss(a[0]), "cpu": miss(a[1]), "cpu_without_gc": miss(a[1] - a[8]),
                         "cpu_without_bus": miss(a[1] - a[4] - a[5]), "cpu_without_io": miss(own)}
        heavy = a[1] >= tick_us * 1000
        out["ticks_over_period_cpu"] = [{"tick": int(k), "cpu_us": round(a[1, k] / 1e3), "read_us": round(a[2, k] / 1e3),
                                         "write_us": round(a[3, k] / 1e3), "bus_us": round((a[4, k] + a[5, k]) / 1e3),
                                         "gc_us": round(a[8, k] / 1e3),
                                         "frames_tx": int(a[6, k]), "frames_rx": int(a[7, k])}
                                        for k in np.flatnonzero(heavy)[:20]]
        return out


class TimedPort:
    """The firmware's port with each ``read``/``write`` timed (thread CPU) into a trace."""

    def __init__(self, port, trace: TickTrace):
        self.port = port
        self.trace = trace

    def read(self) -> bytes:
        c = time.thread_time_ns()
        data = self.port.read()
        self.trace.add(2, time.thread_time_ns() - c)
        return data

    def write(self, data: bytes) -> None:
        c = time.thread_time_ns()
        self.port.write(data)
        self.trace.add(3, time.thread_time_ns() - c)

    def close(self) -> None:
        self.port.close()


class TimedBus:
    """A python-can bus with ``send``/``recv`` timed (thread CPU) and counted into a trace; the
    rest of the bus is reached through it (``shutdown``, an slcan adapter's port)."""

    def __init__(self, bus, trace: TickTrace):
        self.bus = bus
        self.trace = trace

    def send(self, msg, timeout=None) -> None:
        c = time.thread_time_ns()
        self.bus.send(msg, timeout=timeout)
        self.trace.add(4, time.thread_time_ns() - c)
        self.trace.add(6, 1)

    def recv(self, timeout=None):
        c = time.thread_time_ns()
        m = self.bus.recv(timeout=timeout)
        self.trace.add(5, time.thread_time_ns() - c)
        if m is not None:
            self.trace.add(7, 1)
        return m

    def __getattr__(self, name):
        return getattr(self.bus, name)


def run_traced(scenario, seed: int, duration_s: float, transport: str = "can", cfg=None, bus: str = "inproc") -> dict:
    """Run ``scenario`` in process (``transport`` inproc or can: on ``bus`` inproc, the bench's,
    or python-can's ``virtual``) with the trace on; returns
    :meth:`TickTrace.summary` and the run's pose count and position RMS."""
    from coiltrack.firmware.loop import Firmware

    from ..outputs import report as report_mod
    from .links import inproc_pair
    from .runner import BenchSetup, Progress, _tick_loop

    cfg = cfg or scenario.firmware_config()
    tick = cfg.timing.tick_us
    trace = TickTrace(int(duration_s * 1e6) // tick + 2)
    if transport == "can":
        from coiltrack.protocol.can import CanLink, virtual_bus_pair
        from coiltrack.protocol.interfaces.inproc import inproc_bus_pair
        from coiltrack.protocol.schema import NODE_COIL_DRIVER, NODE_FIRMWARE

        a, b = virtual_bus_pair() if bus == "virtual" else inproc_bus_pair()
        fw_end, emu_end = CanLink(TimedBus(a, trace), NODE_FIRMWARE), CanLink(b, NODE_COIL_DRIVER)
    elif transport == "inproc":
        fw_end, emu_end = inproc_pair()
    else:
        raise ValueError(f"transport '{transport}' does not run on the simulated clock")
    bench = BenchSetup(scenario, seed, duration_s, emu_end, cfg=cfg)
    fw = Firmware(cfg, TimedPort(fw_end, trace))
    import gc

    gc.callbacks.append(trace.on_gc)
    try:
        _tick_loop(bench, fw, None, int(duration_s * 1e6), tick, Progress(False, duration_s, ""), trace=trace)
    finally:
        gc.callbacks.remove(trace.on_gc)
    fw_end.close()
    emu_end.close()
    rep = report_mod.build(bench, fw.status(), duration_s, transport=transport, cfg=cfg)
    out = trace.summary(tick)
    out.update({k: rep.get(k) for k in ("poses", "position_rms_mm", "orientation_rms_deg")})
    return out


def main(argv=None) -> int:
    import argparse
    import json

    from .. import args as A
    from .. import scenarios

    p = argparse.ArgumentParser(prog="python -m coiltrack.tools.bench.ticktrace", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", type=scenarios.known, default="multi16")
    p.add_argument("--seed", type=A.seed, default=1)
    p.add_argument("--duration", type=A.bench_seconds, default=10.0, help="simulated seconds (default 10)")
    p.add_argument("--transport", choices=("inproc", "can"), default="can")
    p.add_argument("--bus", choices=("inproc", "virtual"), default="inproc",
                   help="--transport can: the bench's in-process bus or python-can's virtual (default inproc)")
    a = p.parse_args(argv)
    print(json.dumps(run_traced(scenarios.get(a.scenario), a.seed, a.duration, a.transport, bus=a.bus), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
