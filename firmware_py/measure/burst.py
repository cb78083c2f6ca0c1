"""The measurement stage of a burst: close each window of the open burst as
soon as its trailing baseline is in (:class:`WindowCloser`), and mark the
burst complete when every coil's window is closed on every channel.

The burst stays open (``schedule.burst_start`` set) until the tracker has
used it and calls :meth:`BurstMeasurement.release`.
"""
from __future__ import annotations


class BurstMeasurement:
    """``budget``: windows closed per tick at most (``[budget] windows_budget``); the rest of a
    pulse's windows close in the next ticks, so sixteen sensors' windows of one pulse do not
    make one tick sixteen extractions long."""

    def __init__(self, channels, schedule, closer, budget: int = 1 << 30):
        self.channels = tuple(channels)
        self.schedule = schedule
        self.closer = closer
        self.n = schedule.n
        self.budget = int(budget)
        self.complete = False
        self.closed_last = 0             # windows closed by the last step (the tracker charges them)

    def step(self, now_us: int) -> None:
        self.closed_last = 0
        sched = self.schedule
        if sched.burst_start is None or self.complete or sched.commanded < self.n:
            return
        closer = self.closer
        all_done = True
        left = self.budget
        for j in range(self.n):
            start, end = int(sched.start[j]), int(sched.end[j])
            open_ = False
            for ch in self.channels:
                if not ch.done[j]:
                    open_ = True
                    break
            if not open_:
                continue
            if not closer.ready(start, end, now_us):
                all_done = False
                continue
            pid = int(sched.pulse_id[j])
            for ch in self.channels:
                if not ch.done[j]:
                    if left == 0:
                        self.complete = False
                        return
                    closer.close_one(ch, j, pid, start, end)
                    left -= 1
                    self.closed_last += 1
        self.complete = all_done

    def release(self) -> None:
        """The tracker is done with the burst: the next one may open."""
        self.complete = False
        self.schedule.end_burst()
