"""Actuation: which coil is driven, when and how strongly (the *actuate* stage of
:mod:`coiltrack.firmware.loop`).

The policies here, one chosen by :mod:`coiltrack.firmware.compose`:

* :mod:`.burst`: the fixed X, Y, Z cycle in bursts (thesis ``002_cd7f1fdb7fc67471.txt``
  sec. 5.3), through :mod:`.fixed_cycle` and the one :mod:`.schedule`;
* :mod:`.ac`: the AC drive plan (Raab et al. 1979, ``004_86267342cd7488ce.txt``);
* the single-coil pulses on demand of Schepers & Veltink 2010 (``000_e46ec0e8bf7ea271.txt``
  sec. 2.1; :mod:`.coil_choice`, driven by
  :class:`coiltrack.firmware.track.single_coil_tracker.SingleCoilTracker`).

Their contract is :class:`Actuation`.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

__all__ = ["Actuation"]


@runtime_checkable
class Actuation(Protocol):
    """An excitation policy.

    Reads: the configuration's timing and currents, the pulse schedule's state (a burst in
    use), the tracker's estimate where the policy closes the loop.
    Owns: its cycle or plan; the commands it sends go through the one
    :class:`coiltrack.firmware.actuate.schedule.PulseSchedule` (pulsed DC) or the
    transmitter (AC plans), never around them.
    Returns: nothing; commands leave as ``COIL_PULSE_CMD`` / ``AC_DRIVE_CMD``.
    Work bound: :meth:`step` sends at most the commands that fall due in the tick (one
    cycle's pulses, one plan), no search beyond the configured candidates.
    """

    def step(self, now_us: int) -> None:
        """The actuate stage of one tick."""
