"""A fault's recovery held against the same run without the fault.

``fault_recovery_s`` (``tools.outputs.faultreport``) asks how long after a fault the fused
error is back to what it would have been without it. What it would have been is measured,
not assumed: :func:`add_recovery_reference` runs the same scenario, seed, duration,
configuration and transport with the link faults and clock drifts but without the timed
faults (every emulated source of noise is seeded, so the two runs are the same pose for pose
until the first fault), keeps the error trace of its valid fused poses and scores each fault
window of the faulted run against it (``faultreport.recovery_time``). A single level for the
whole run cannot stand in for it: where the trajectory is at far range the tracker with no
fault at all is above twice its whole-run level (roetenberg-fusion seed 5, 45-62 s at 715-768
mm: 25-67 mm against a level of 8.2 mm), and that stretch would be counted against the fault.

:class:`TraceKeeper` is the outputs object (``wrap``, ``tick``, ``finish``, as
``tools.outputs.sinks.Outputs``) that keeps a run's trace while passing everything on to the
run's own outputs, if any.
"""
from __future__ import annotations

import dataclasses

from ..outputs.faultreport import fused_trace, recovery_keys


class TraceKeeper:
    """Keeps :func:`faultreport.fused_trace` of the run it is the outputs of (``trace``),
    and forwards everything else to ``inner`` (a ``tools.outputs.sinks.Outputs``) if given."""

    def __init__(self, inner=None):
        self.inner = inner
        self.trace = None

    def __getattr__(self, name):
        if name == "inner" or self.__dict__.get("inner") is None:
            raise AttributeError(name)
        return getattr(self.inner, name)

    def wrap(self, port, **kw):
        return self.inner.wrap(port, **kw) if self.inner is not None else port

    def tick(self, t_us: int) -> None:
        if self.inner is not None:
            self.inner.tick(t_us)

    def finish(self, bench=None, rep: dict | None = None) -> None:
        self.trace = fused_trace(bench.recorder)
        if self.inner is not None:
            self.inner.finish(bench, rep)


def needs_reference(faults) -> bool:
    """Has the run timed faults, whose recovery the report measures?"""
    return faults is not None and bool(faults.timed)


def reference_trace(scenario, seed: int, duration_s: float, faults=None, cfg=None, transport: str = "inproc"):
    """The no-fault run's fused error trace (true times s, errors m): ``faults`` without its
    timed faults, on the simulated clock (``transport`` inproc or can; inproc otherwise)."""
    from .runner import run_inproc

    keep = TraceKeeper()
    quiet = dataclasses.replace(faults, timed=[]) if faults is not None else None
    run_inproc(scenario, seed, duration_s, faults=quiet, cfg=cfg, outputs=keep,
               transport=transport if transport in ("inproc", "can") else "inproc")
    return keep.trace


def add_recovery_reference(rep: dict, trace, faults, reference) -> dict:
    """``rep``'s ``fault_recovery_s`` scored again against ``reference`` (the no-fault run's
    trace), from the faulted run's ``trace`` and ``faults.timed``, with the same level."""
    ft, fe = trace
    rep.update(recovery_keys(ft, fe, list(faults.timed), rep.get("no_fault_level_mm"), reference))
    return rep
