"""What the machine did to each timed tick of ``coiltrack perf``: the firmware's work told apart from the machine's.

A tick's CPU time (``time.thread_time_ns``) leaves out the time the thread was not running,
but not what the machine's other work costs the thread when it runs again, nor the kernel
work done on the thread's behalf. Read around every tick, outside the timed window (so the
readings cost the tick nothing), with ``getrusage(RUSAGE_THREAD)`` and ``sched_getcpu``:

``minflt``     minor page faults inside the tick: memory touched for the first time (a new
               interpreter arena, a grown buffer, a fresh page of a numpy array); the
               kernel's fault handling counts in the tick's CPU time. The firmware's own
               doing, removed by touching the memory at start-up;
``majflt``     major page faults inside the tick (a page read from disk: code or data paged
               out or never loaded);
``switches``   context switches inside the tick, involuntary (preempted: the scheduler gave
               the core to another thread) and voluntary (the thread blocked). The switch's
               kernel path and the caches and TLB the other thread evicted count in the
               tick's CPU time: the machine's doing;
``before``     context switches between the end of the previous tick and the start of this
               one: the tick starts on caches the other thread left (cold);
``migrated``   the core changed during the tick or since the previous tick ended (cold
               private caches): the machine's doing.

A tick with none of these is *undisturbed*; :func:`summarise` gives the CPU figures of the
undisturbed ticks beside each kind of disturbance's count and the largest CPU time among its
ticks: a maximum that only disturbed ticks reach is the machine's, one that undisturbed ticks
reach is the firmware's (or a disturbance these counters do not see: an interrupt handled
on the thread's core, which this kernel counts in the thread's time, or the hypervisor
taking the virtual core, which the wall time shows but the CPU time does not).

:func:`recurrence` compares repeated replays of the same log (``coiltrack perf --repeat N``):
the firmware's work is the same at the same virtual time in every replay, the machine's is
not. Per tick the minimum CPU time over the replays estimates the firmware's cost; a tick
costly in every replay is the firmware's work, a costly tick that moves is the machine's.
"""
from __future__ import annotations

import resource

import numpy as np

__all__ = ["FIELDS", "MachineProbe", "recurrence", "summarise"]

#: per tick, in this order: minor faults, major faults, involuntary and voluntary context
#: switches inside the tick, context switches since the previous tick ended, core migrations
FIELDS = ("minflt", "majflt", "nivcsw", "nvcsw", "switches_before", "migrated")


def _sched_getcpu():
    """libc's ``sched_getcpu`` (the core the thread runs on), or None where it is missing."""
    try:
        import ctypes

        fn = ctypes.CDLL(None).sched_getcpu
    except (OSError, AttributeError):       # pragma: no cover - not glibc/musl
        return None
    fn.restype = ctypes.c_int
    fn.argtypes = ()
    return fn


def _thread_usage():
    """``getrusage(RUSAGE_THREAD)`` (Linux), else the process's (``RUSAGE_SELF``)."""
    who = getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF)
    return lambda: resource.getrusage(who)


class MachineProbe:
    """Reads the thread's page faults, context switches and core around each tick.

    ``usage()`` returns an object with ``ru_minflt``, ``ru_majflt``, ``ru_nivcsw`` and
    ``ru_nvcsw`` (default: the thread's ``getrusage``); ``cpu()`` the core number or -1
    (default: ``sched_getcpu``). Both are injectable, so a test gives the counts. Call
    :meth:`before` just before the timed window and :meth:`after` just after it; ``after``
    returns the tick's row (:data:`FIELDS`)."""

    def __init__(self, usage=None, cpu=None):
        self.usage = usage or _thread_usage()
        if cpu is None:
            fn = _sched_getcpu()
            cpu = fn if fn is not None else (lambda: -1)
        self.cpu = cpu
        self._end = None            # (usage, core) at the end of the previous tick
        self._start = None

    def before(self) -> None:
        self._start = (self.usage(), self.cpu())

    def after(self) -> tuple:
        u1, c1 = self.usage(), self.cpu()
        u0, c0 = self._start
        prev = self._end
        self._end = (u1, c1)
        if prev is None:
            before, moved = 0, False
        else:
            before = (u0.ru_nivcsw - prev[0].ru_nivcsw) + (u0.ru_nvcsw - prev[0].ru_nvcsw)
            moved = c0 != prev[1]
        return (u1.ru_minflt - u0.ru_minflt, u1.ru_majflt - u0.ru_majflt, u1.ru_nivcsw - u0.ru_nivcsw,
                u1.ru_nvcsw - u0.ru_nvcsw, before, int(moved or c1 != c0))


def _cpu_stats(a_us: np.ndarray) -> dict:
    if a_us.size == 0:
        return {"ticks": 0, "median": None, "p999": None, "max": None}
    return {"ticks": int(a_us.size), "median": round(float(np.median(a_us)), 2),
            "p999": round(float(np.percentile(a_us, 99.9)), 2), "max": round(float(a_us.max()), 2)}


def summarise(cpu_ns, rows, deadline_ns: int | None = None) -> dict:
    """The CPU figures of the undisturbed ticks and of each disturbance, from each tick's CPU
    time (ns) and its :class:`MachineProbe` row:

    ``undisturbed``            {ticks, median, p999, max} (us) of the ticks with no fault,
                               switch or migration;
    ``page_faults``            {ticks, faults, major, median, max}: ticks with a page fault;
    ``preempted``              ticks with a context switch inside (involuntary or voluntary);
    ``switched_before``        ticks that began after a context switch (without one inside);
    ``migrated``               ticks whose core changed (without a switch inside or before);
    ``worst_disturbed``        of the ticks at or above the p99.9 of all, how many are disturbed.

    With ``deadline_ns`` (the tick) ``undisturbed`` and ``disturbed`` also count the ticks of at
    least that CPU time (``deadline_misses``): a miss of a disturbed tick is the machine's.
    """
    c = np.asarray(cpu_ns, dtype=float) / 1e3
    r = np.asarray(rows, dtype=np.int64).reshape(-1, len(FIELDS))
    minflt, majflt, niv, nv, before, moved = (r[:, i] for i in range(len(FIELDS)))
    faults = (minflt + majflt) > 0
    inside = (niv + nv) > 0
    bef = (before > 0) & ~inside
    mig = (moved > 0) & ~inside & ~(before > 0)
    disturbed = faults | inside | (before > 0) | (moved > 0)
    out = {"undisturbed": _cpu_stats(c[~disturbed])}
    if deadline_ns is not None:
        miss = c >= deadline_ns / 1e3
        out["undisturbed"]["deadline_misses"] = int((miss & ~disturbed).sum())
        out["disturbed"] = {"ticks": int(disturbed.sum()), "deadline_misses": int((miss & disturbed).sum())}
    pf = _cpu_stats(c[faults])
    out["page_faults"] = {"ticks": pf["ticks"], "faults": int(minflt.sum() + majflt.sum()), "major": int(majflt.sum()),
                          "median": pf["median"], "max": pf["max"]}
    for key, sel in (("preempted", inside), ("switched_before", bef), ("migrated", mig)):
        s = _cpu_stats(c[sel])
        out[key] = {"ticks": s["ticks"], "median": s["median"], "max": s["max"]}
    if c.size:
        top = c >= np.percentile(c, 99.9)
        out["worst_disturbed"] = {"ticks": int(top.sum()), "disturbed": int((top & disturbed).sum()),
                                  "page_faults": int((top & faults).sum()), "preempted": int((top & inside).sum())}
    return out


def recurrence(runs_cpu_ns, t_us, worst: int) -> dict:
    """Repeated replays of one log compared tick by tick: ``runs_cpu_ns`` one CPU time (ns) per
    measured tick for each replay (the same ticks, at the virtual times ``t_us``).

    ``min_us``          {median, p99, p999, max} of each tick's minimum over the replays: the
                        firmware's work with the machine's noise taken out as far as N replays can;
    ``max_at``          per replay, the virtual time of its costliest tick;
    ``worst``           the ``worst`` ticks of the minimum (the firmware's costliest work), each
                        {t_us, min_us, cpu_us: one per replay};
    ``worst_kept``      of each replay's ``worst`` costliest ticks, how many are among the first
                        replay's (all of them: the same work; few: the machine's)."""
    a = np.asarray(runs_cpu_ns, dtype=float) / 1e3
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] != len(t_us):
        raise ValueError(f"one CPU time per tick and replay expected, got shape {a.shape} for {len(t_us)} ticks")
    t = np.asarray(t_us, dtype=np.int64)
    m = a.min(axis=0)
    k = max(1, min(worst, m.size))
    order = np.argsort(-m, kind="stable")[:k]
    tops = [set(np.argsort(-row, kind="stable")[:k].tolist()) for row in a]
    return {"runs": int(a.shape[0]),
            "min_us": {"median": round(float(np.median(m)), 2), "p99": round(float(np.percentile(m, 99)), 2),
                       "p999": round(float(np.percentile(m, 99.9)), 2), "max": round(float(m.max()), 2)},
            "max_at": [int(t[int(np.argmax(row))]) for row in a],
            "worst": [{"t_us": int(t[i]), "min_us": round(float(m[i]), 2),
                       "cpu_us": [round(float(x), 2) for x in a[:, i]]} for i in order],
            "worst_kept": [len(s & tops[0]) for s in tops]}
