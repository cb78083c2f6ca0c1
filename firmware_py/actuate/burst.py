"""Actuation by bursts of the fixed cycle: every cycle's X, Y, Z pulses form
one burst that the tracker solves together (thesis ``002_cd7f1fdb7fc67471.txt``
sec. 5.3). Each pulse is commanded ``lead_us`` before it starts, at the
coil's nominal current; a cycle does not open while the previous burst is
still in use, and one that can no longer be commanded in time is skipped.

**A pulse refused as late.** A command that reaches the driver after its
start (the firmware or the link stalled: a virtual machine's CPU taken away
for 100 ms) is refused (``COIL_FAULT_REFUSED | COIL_FAULT_LATE``,
``docs/protocol.md`` "Refusals and fault bits"): that coil is not driven in
this burst, so the burst can give no pose (the refusal is fatal for it). The
burst is dropped as soon as the refusal is in, before it completes: its
measurement released, its pulses not yet commanded not sent, no pose reported
from it (neither a solution nor an invalid one), and the next cycle opens on
the fixed timetable (the flips and time syncs planned around it stay where
they were planned). A late command costs one cycle's pose, never a bad pose.
Any other refusal (over current, duty, not synchronised: a configuration or a
driver that cannot serve the cycle) stays fatal and is reported with the
burst's pose (``POSE_COIL_FAULT``), as is a late refusal that comes in after
the burst completed. A pulse whose start has passed when its command is due
(the firmware itself stalled) is not sent at all: its burst is dropped then,
or, for a cycle's first pulse, that cycle skipped.
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

    def __init__(self, cfg, schedule, channels, tracker, core=_DEFAULT_CORE, measurement=None):
        """``measurement``: the bursts' ``BurstMeasurement`` (default the tracker's ``burst``); when
        given, it runs :meth:`check_refused` at the start of each of its steps
        (``BurstMeasurement.run_first``)."""
        n = len(cfg.source.coils)
        self.cycle = FixedCycle(n, cfg.timing.first_cycle_us, cfg.timing.cycle_us, cfg.timing.spacing_us, cfg.timing.pulse_us, cfg.timing.lead_us)
        self.schedule = schedule
        self.channels = tuple(channels)
        self._bursts = ChannelBursts(self.channels, core)
        self.tracker = tracker
        self.nominal = tuple(float(c.current) for c in cfg.source.coils)
        self._waited = False
        # the burst's measurement (``BurstMeasurement``): released when a late refusal drops the burst
        self.measurement = measurement if measurement is not None else getattr(tracker, "burst", None)
        self._late_seen = 0             # the schedule's late refusals already looked at
        self.dropped = 0                # bursts dropped for a pulse refused as late
        if measurement is not None:
            measurement.run_first(self.check_refused)

    def check_refused(self, now_us: int) -> None:
        """Drop the burst if the tick's receive brought a late refusal of one of its pulses; run by
        the measurement stage before its step (``BurstMeasurement.run_first``), so no window of the
        burst closes, and it does not complete, on a refused pulse's edges."""
        if self.schedule.late_refusals != self._late_seen:
            self._late_seen = self.schedule.late_refusals
            self._drop_refused(now_us)

    def step(self, now_us: int) -> None:
        cyc = self.cycle
        if now_us < cyc.due_us:          # nothing due: the next command's time, kept by the cycle
            return
        while cyc.due(now_us):
            if cyc.start_us() <= now_us:     # a stall: this pulse can no longer be commanded in time
                self._drop(now_us)
                continue
            if cyc.coil == 0 and not self._open(now_us):
                return
            j = cyc.coil
            self.schedule.command(j, self.nominal[j], cyc.start_us(), cyc.pulse_us)
            cyc.advance(now_us)

    def _drop_refused(self, now_us: int) -> None:
        """Drop the open burst if the driver refused one of its pulses as late and the burst has
        not completed (module docstring): the pulses it has commanded are the cycle's first
        ``commanded``, in coil order."""
        sched = self.schedule
        m = self.measurement
        if sched.burst_start is None or m is None or m.complete:
            return
        for j in range(min(sched.commanded, sched.n)):
            if sched.refused_late(j):
                break
        else:
            return                      # a refusal of an earlier burst's pulse
        self._drop(now_us, True)

    def _drop(self, now_us: int, refused: bool = False) -> None:
        """Give up the cycle's remaining pulses (the next command is the next cycle's first that
        can still leave in time) and drop the burst they belong to: the open one when a pulse of
        it was refused or is yet to be commanded (not a cycle's first pulse) and it is not
        complete."""
        m = self.measurement
        if (refused or self.cycle.coil) and self.schedule.burst_start is not None and m is not None \
                and not m.complete:
            m.release()
            self.dropped += 1
        self.cycle.abandon(now_us)

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
