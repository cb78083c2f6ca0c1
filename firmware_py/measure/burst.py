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
    make one tick sixteen extractions long.

    A coil's windows close on the channels in their order, and only here (the burst's windows
    are reset when it opens: ``SensorChannel.new_burst``), and a window once ready stays ready
    (``WindowCloser.ready_upto``), so the stage keeps per coil how many channels are closed
    (``closed_upto``) and how many are known ready (``ready_upto``), both 0 again at
    :meth:`release`, instead of asking every channel each tick: a tick's work scales with the
    windows and samples due, not with the sensors."""

    def __init__(self, channels, schedule, closer, budget: int = 1 << 30):
        self.channels = tuple(channels)
        self.schedule = schedule
        self.closer = closer
        self.n = schedule.n
        self.budget = int(budget)
        self.complete = False
        self.closed_last = 0             # windows closed by the last step (the tracker charges them)
        self.closed_upto = [0] * self.n  # per coil: its windows are closed on channels[:closed_upto[j]]
        self.ready_upto = [0] * self.n   # ... and ready (or timed out) on channels[:ready_upto[j]]

    def step(self, now_us: int) -> None:
        self.closed_last = 0
        sched = self.schedule
        if sched.burst_start is None or self.complete or sched.commanded < self.n:
            return
        closer = self.closer
        chs = self.channels
        m = len(chs)
        upto = self.closed_upto
        ready = self.ready_upto
        all_done = True
        left = self.budget
        for j in range(self.n):
            c = upto[j]
            if c == m:
                continue                 # closed on every channel
            start, end = int(sched.start[j]), int(sched.end[j])
            r = ready[j]
            if r < m:
                r = ready[j] = closer.ready_upto(start, end, now_us, r)
                if r < m:
                    all_done = False
                    continue
            pid = int(sched.pulse_id[j])
            while c < m:
                if left == 0:
                    upto[j] = c
                    self.complete = False
                    return
                closer.close_one(chs[c], j, pid, start, end)
                c += 1
                left -= 1
                self.closed_last += 1
            upto[j] = c
        self.complete = all_done

    def release(self) -> None:
        """The tracker is done with the burst: the next one may open."""
        self.complete = False
        for j in range(self.n):
            self.closed_upto[j] = 0
            self.ready_upto[j] = 0
        self.schedule.end_burst()
