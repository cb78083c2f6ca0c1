"""Trackers: measurements in, poses out (the *track* stage of :mod:`coiltrack.firmware.loop`).

A tracker is chosen once, by :mod:`coiltrack.firmware.compose` (its table ``TRACKERS``), and
never by a flag in the loop. The trackers here:

* :mod:`.magnetic`: a 6-DOF pose per burst and sensor (Kuipers' closed form, least squares;
  thesis ``002_cd7f1fdb7fc67471.txt`` App. 5.A);
* :mod:`.burst_fusion`: the bursts fused with the IMU (thesis ch. 6);
* :mod:`.tight_fusion`: each pulse window a measurement at its own time;
* :mod:`.single_coil_tracker`: Schepers & Veltink 2010 (``000_e46ec0e8bf7ea271.txt``), one
  coil per update, with its own actuation;
* :mod:`.ac`: the burst trackers fed with AC blocks (Raab et al. 1979).

Their contract is :class:`Tracker` (every tracker) and :class:`BurstTracker` (the trackers
of bursts, which the burst actuation tells of each burst it opens).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

__all__ = ["Tracker", "BurstTracker"]


@runtime_checkable
class Tracker(Protocol):
    """What the receiver and the loop know of a tracker.

    Reads: the decoded messages the receiver routes to it (below), the sensor channels and
    the pulse schedule it was built with (never written), the measurement stage's output.
    Owns: its estimators, its pose solvers and their buffers, all allocated at start-up.
    Returns: nothing; its poses leave through the transmitter it was given
    (``POSE``, ``FAULT_EVENT``), its figures through :meth:`counters`.
    Work bound: each input call is O(1) (a sample is queued, never processed, in the
    receive stage); the tick's work is done in the track stage, at most
    ``[budget] track_budget_evals`` coil field evaluations per tick (a unit that does not fit
    waits for the next tick; ``docs/tick-budget.md``).
    """

    def on_mag(self, msg, lsb: float) -> None:
        """A ``MAG_SAMPLE`` of a node that is not one of the tracked sensors (``lsb``: T per count)."""

    def on_imu(self, msg, now_us: int) -> None:
        """An ``IMU_SAMPLE`` (or one step of an ``IMU_DELTA`` pair) of any node."""

    def on_coil_status(self, msg) -> None:
        """A ``COIL_STATUS`` of the coil driver (the pulse schedule has seen it first)."""

    def counters(self) -> dict:
        """The tracker's figures for the firmware's status (``Firmware.status``)."""


@runtime_checkable
class BurstTracker(Tracker, Protocol):
    """A tracker of bursts: the measurement stage (:class:`coiltrack.firmware.measure.Measurement`)
    hands it every coil's window (or AC block) of a burst at once.

    Reads: the channels' signal matrices (``ch.S``, ``ch.sigma``) once the measurement is
    ``complete``; releases the burst (``Measurement.release``) when done with it.
    Work bound: :meth:`step` does at most ``track_budget_evals`` field evaluations and the
    tick's charges (``[budget] window_evals``, ``imu_sample_evals``) together.
    """

    def on_burst(self, t_ref: int) -> None:
        """The actuation opened a burst whose pose refers to ``t_ref`` (us, master clock)."""

    def step(self, now_us: int) -> None:
        """The track stage of one tick."""
