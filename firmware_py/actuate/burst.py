"""Actuation by bursts of the fixed cycle: every cycle's X, Y, Z pulses form
one burst that the tracker solves together (thesis ``002_cd7f1fdb7fc67471.txt``
sec. 5.3). Each pulse is commanded ``lead_us`` before it starts, at the
coil's nominal current; a cycle does not open while the previous burst is
still in use, and one that can no longer be commanded in time is skipped.
"""
from __future__ import annotations

from coiltrack.firmware.actuate.fixed_cycle import FixedCycle
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.measure.windows import ChannelBursts


class BurstActuation:
    """The fixed cycle's bursts (an :class:`coiltrack.firmware.actuate.Actuation`); tells
    ``tracker`` (a :class:`coiltrack.firmware.track.BurstTracker`) of each burst it opens. The
    channels' new burst is one step (:class:`ChannelBursts`: one compiled call on ``core``), and so
    is the tracker's :meth:`on_burst` where it has one compiled (sixteen sensors: ``multi16``)."""

    def __init__(self, cfg, schedule, channels, tracker, core=_DEFAULT_CORE):
        n = len(cfg.source.coils)
        self.cycle = FixedCycle(n, cfg.timing.first_cycle_us, cfg.timing.cycle_us, cfg.timing.spacing_us, cfg.timing.pulse_us, cfg.timing.lead_us)
        self.schedule = schedule
        self.channels = tuple(channels)
        self._bursts = ChannelBursts(self.channels, core)
        self.tracker = tracker
        self.nominal = tuple(float(c.current) for c in cfg.source.coils)
        self._waited = False

    def step(self, now_us: int) -> None:
        cyc = self.cycle
        if now_us < cyc.due_us:          # nothing due: the next command's time, kept by the cycle
            return
        while cyc.due(now_us):
            if cyc.coil == 0 and not self._open(now_us):
                return
            j = cyc.coil
            self.schedule.command(j, self.nominal[j], cyc.start_us(), cyc.pulse_us)
            cyc.advance(now_us)

    def _open(self, now_us: int) -> bool:
        """Open the next cycle's burst, unless the previous one is still in use."""
        cyc = self.cycle
        sched = self.schedule
        if sched.burst_start is not None:
            self._waited = True
            return False
        if self._waited:          # the previous burst was in use past this cycle's command time
            self._waited = False
            cyc.skip_late(now_us)
            if not cyc.due(now_us):
                return False
        t0 = cyc.cycle_start
        sched.open_burst(t0, t0 + (cyc.n - 1) * cyc.spacing_us + cyc.pulse_us)
        self._bursts.new_burst()
        self.tracker.on_burst(cyc.t_ref())
        return True
