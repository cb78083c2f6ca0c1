"""The measurement stage of a burst: close each window of the open burst as
soon as its trailing baseline is in (:class:`WindowCloser`), and mark the
burst complete when every coil's window is closed on every channel.

The burst stays open (``schedule.burst_start`` set) until the tracker has
used it and calls :meth:`BurstMeasurement.release`.
"""
from __future__ import annotations


class BurstMeasurement:
    def __init__(self, channels, schedule, closer):
        self.channels = tuple(channels)
        self.schedule = schedule
        self.closer = closer
        self.n = schedule.n
        self.complete = False

    def step(self, now_us: int) -> None:
        sched = self.schedule
        if sched.burst_start is None or self.complete or sched.commanded < self.n:
            return
        closer = self.closer
        all_done = True
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
                    closer.close_one(ch, j, pid, start, end)
        self.complete = all_done

    def release(self) -> None:
        """The tracker is done with the burst: the next one may open."""
        self.complete = False
        self.schedule.end_burst()
