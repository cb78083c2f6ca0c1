"""Measurement: magnetometer samples to coil amplitudes (the *measure* stage of
:mod:`coiltrack.firmware.loop`).

* pulsed DC: :mod:`.windows` (the sensor channels and the one window closer), :mod:`.pulse`
  (a pulse window's amplitude from its in-pulse samples and the baselines before and after,
  Schepers & Veltink ``000_e46ec0e8bf7ea271.txt`` sec. 2.3: first and last samples dropped,
  ``sigma / sqrt(n)``; thesis ``002_cd7f1fdb7fc67471.txt`` sec. 5.3: the earth field
  removed by the baselines), :mod:`.gyro_baseline` (the same with the samples turned by the
  gyroscope), :mod:`.burst` (a burst's windows closed within a budget);
* AC: :mod:`.demod` (synchronous demodulation, Raab et al. 1979), :mod:`.ac_blocks` (its
  blocks handed to the trackers as bursts).

Three contracts: :class:`Measurement` (the stage a burst tracker reads), :class:`WindowExtractor`
(one pulse window) and :class:`Demodulation` (AC blocks).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

__all__ = ["Measurement", "WindowExtractor", "Demodulation"]


@runtime_checkable
class Measurement(Protocol):
    """The measure stage of bursts (pulse windows or AC blocks), read by a
    :class:`coiltrack.firmware.track.BurstTracker`.

    Reads: the sensor channels' sample rings and the pulse schedule.
    Owns: the channels' burst matrices while it fills them (``ch.S``, ``ch.var``,
    ``ch.flags``, ``ch.pulse_mid``, ``ch.done``); the tracker only reads them.
    Returns: ``complete`` True once every window (block) of the burst is in; the burst
    stays until the tracker calls :meth:`release`. ``closed_last``: the windows closed in
    the last step (the tracker charges them against its budget).
    Work bound: at most ``[budget] windows_budget`` windows (pulsed DC), or a bounded number
    of samples and one block per channel (AC), per tick.
    """

    complete: bool
    closed_last: int

    def step(self, now_us: int) -> None:
        """The measure stage of one tick."""

    def release(self) -> None:
        """The tracker is done with the burst: the next one may fill."""

    def completing_sample_us(self) -> int:
        """When the sample that completes the open burst is expected (us, master clock), once
        it is the next one; ``NO_TIME_US`` otherwise (a hint for the wall-clock loop only)."""


@runtime_checkable
class WindowExtractor(Protocol):
    """One node's pulse windows, from its sample ring.

    Reads: the ring it was built on (never writes it). Owns: its scratch buffers
    (``max_samples`` samples of one window).
    Returns: per window the amplitude (3,) T and its variance (3,) T^2 in the caller's
    buffers, and ``(flags, n_used, n_base)`` (``PULSE_*`` bits, in-pulse samples used,
    baseline samples used).
    Work bound: one extraction reads at most ``max_samples`` samples.
    """

    max_samples: int

    def ready(self, start_us: int, end_us: int) -> bool:
        """Every sample the window of the pulse ``[start_us, end_us]`` reads is in."""

    def expect_complete(self, start_us: int, end_us: int) -> bool:
        """The window's last sample is in and the next one is expected after the window."""

    def completing_sample_us(self, start_us: int, end_us: int) -> int:
        """When the sample that makes the window ready is expected, once it is the next one;
        ``NO_TIME_US`` otherwise."""

    def extract(self, start_us: int, end_us: int, amp_out, var_out) -> tuple[int, int, int]:
        """The window's amplitude into ``amp_out``, its variance into ``var_out``."""

    def last_used_times(self, out) -> int:
        """The times of the in-pulse samples the last extraction used, into ``out``; how many."""

    def last_used_span(self) -> tuple[int, int]:
        """The times of the first and the last of them, ``(0, 0)`` when none."""


@runtime_checkable
class Demodulation(Protocol):
    """Synchronous demodulation of one node's samples into blocks (AC excitation).

    Reads: the samples pushed to it and the drive's current phasors (:meth:`set_currents`).
    Owns: its per-block accumulators (a fixed number of overlapping blocks).
    Returns: per finished block ``k`` the in-phase signal matrix, its variance, the
    quadrature and the DC term (the earth field); ``signal_chi2`` and ``quadrature_chi2``
    its significance and its distortion statistic.
    Work bound: O(p) per sample pushed and O(p^2) per block finished, ``p = 2 + 2 n``.
    """

    def start(self, t0_us: int, ref_us: int, amplitude, phase) -> None:
        """Blocks from ``t0_us`` on, phases against ``ref_us``."""

    def set_currents(self, amplitude, phase) -> None:
        """The drive's measured current amplitudes (A) and phases (rad)."""

    def push(self, t: int, bx: float, by: float, bz: float, sample_flags: int) -> int:
        """One sample (T); returns the block it completes, or -1."""

    def finish(self, k: int) -> bool:
        """Solve block ``k``; False when it cannot be solved."""

    def block_mid(self, k: int) -> int:
        """The middle of block ``k`` (us)."""

    def signal_chi2(self) -> float:
        """``sum S^2 / var`` of the last finished block."""

    def quadrature_chi2(self) -> float:
        """The quadrature part's chi-square of the last finished block."""
