"""The measurement stage of a burst: close each window of the open burst as
soon as its trailing baseline is in (:class:`WindowCloser`), and mark the
burst complete when every coil's window is closed on every channel.

The burst stays open (``schedule.burst_start`` set) until the tracker has
used it and calls :meth:`BurstMeasurement.release`.
"""
from __future__ import annotations

from coiltrack.firmware.measure.pulse import NO_TIME_US


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
        # the closer's channels are these, in this order: a run of them closes in one call
        # (``WindowCloser.close_run``; compiled: ``ct_window_run``)
        cc = tuple(getattr(closer, "channels", ()))
        self._same_channels = hasattr(closer, "close_run") and len(cc) == len(self.channels) and all(
            a is b for a, b in zip(cc, self.channels))
        self._first = None               # run at the start of each step (run_first)

    def run_first(self, check) -> None:
        """``check(now_us)`` runs at the start of every :meth:`step`, before any window closes (the
        fixed cycle's drop of a burst whose pulse the driver refused as late:
        ``actuate.burst.BurstActuation.check_refused``)."""
        self._first = check

    def step(self, now_us: int) -> None:
        if self._first is not None:
            self._first(now_us)
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
            k = m - c if m - c < left else left
            if k:                        # the channels' windows the budget leaves room for, in order
                if self._same_channels:
                    closer.close_run(j, pid, start, end, c, c + k)
                else:
                    for i in range(c, c + k):
                        closer.close_one(chs[i], j, pid, start, end)
                c += k
                left -= k
                self.closed_last += k
            if c < m:                    # the budget is spent: the rest in the next ticks
                upto[j] = c
                self.complete = False
                return
            upto[j] = c
        self.complete = all_done

    def completing_sample_us(self) -> int:
        """When the sample that completes the open burst on the first channel is expected (us,
        master clock), once its next sample is expected to make the last window ready
        (``WindowExtractor.completing_sample_us``); ``NO_TIME_US`` before, after, and between
        bursts. The wall-clock loop starts a tick just after it (``[timing] align_us``,
        ``tools.bench.realtime.firmware_loop``); it reads, and changes nothing. One channel: the
        sensors of a multi-sensor bench sample at phases of their own, and the loop's grid can
        sit after one of them (moving it after each would only add jitter)."""
        sched = self.schedule
        j = self.n - 1
        if sched.burst_start is None or self.complete or sched.commanded < self.n or self.closed_upto[j]:
            return NO_TIME_US
        return self.channels[0].extractor.completing_sample_us(int(sched.start[j]), int(sched.end[j]))

    def release(self) -> None:
        """The tracker is done with the burst: the next one may open."""
        self.complete = False
        for j in range(self.n):
            self.closed_upto[j] = 0
            self.ready_upto[j] = 0
        self.schedule.end_burst()
