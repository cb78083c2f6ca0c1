"""The fixed X, Y, Z cycle (thesis ``002_cd7f1fdb7fc67471.txt`` sec. 5.3:
60 ms pulses, 600 ms cycle): pulse ``j`` of a cycle starts at
``cycle_start + j * spacing_us`` and is commanded ``lead_us`` before it.

:class:`FixedCycle` only keeps the timetable; the actuation stages that use
it (:mod:`coiltrack.firmware.actuate.burst`, the single-coil tracker's fixed
schedule) send the commands through the :class:`PulseSchedule`.
"""
from __future__ import annotations


class FixedCycle:
    """Timetable of the fixed cycle: which coil is due next, and when."""

    def __init__(self, n_coils: int, first_cycle_us: int, cycle_us: int, spacing_us: int, pulse_us: int,
                 lead_us: int):
        self.n = n_coils
        self.cycle_us = cycle_us
        self.spacing_us = spacing_us
        self.pulse_us = pulse_us
        self.lead_us = lead_us
        self.cycle_start = first_cycle_us
        self.coil = 0                     # next coil of the cycle to command
        self.due_us = 0                   # the next command's time (kept by _retime)
        self._retime()

    def _retime(self) -> None:
        """``due_us``: when the next pulse's command should leave (:meth:`due`), recomputed
        whenever the next pulse changes, so a tick before it is one comparison."""
        self.due_us = self.cycle_start + self.coil * self.spacing_us - self.lead_us

    def start_us(self) -> int:
        """Start of the next pulse (coil :attr:`coil`)."""
        return self.cycle_start + self.coil * self.spacing_us

    def due(self, now_us: int) -> bool:
        """Whether the next pulse's command should leave now."""
        return now_us >= self.due_us

    def t_ref(self) -> int:
        """The middle of the current cycle's burst (its pose refers to it)."""
        t0 = self.cycle_start
        return (t0 + t0 + (self.n - 1) * self.spacing_us + self.pulse_us) // 2

    def advance(self, now_us: int) -> None:
        """Move on to the next pulse; after the last coil, to the next cycle
        (a cycle that can no longer be commanded in time is skipped)."""
        self.coil += 1
        if self.coil == self.n:
            self.coil = 0
            self.cycle_start += self.cycle_us
            self.skip_late(now_us)
        self._retime()

    def abandon(self, now_us: int) -> None:
        """Give up the rest of the current cycle (its burst was dropped): the next command is the
        next cycle's first, skipping any cycle whose first command time has passed."""
        if self.coil:
            self.coil = 0
            self.cycle_start += self.cycle_us
        self.skip_late(now_us)

    def skip_late(self, now_us: int) -> None:
        """Skip whole cycles whose first command time has passed."""
        if self.coil:
            return
        while self.cycle_start - self.lead_us < now_us:
            self.cycle_start += self.cycle_us
        self._retime()
