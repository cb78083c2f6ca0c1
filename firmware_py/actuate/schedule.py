"""The pulse schedule: the one place coil commands are numbered and sent.

Every excitation policy commands its pulses through :meth:`PulseSchedule.command`;
the driver's ``COIL_STATUS`` replies land in :meth:`PulseSchedule.on_status`.
The per-coil arrays (the latest pulse of each coil: its edges on the master
clock, its id, the measured current and the driver's fault bits) are written
here only; the supervisor, the measurement and the trackers read them.

A *burst* is the group of pulses whose windows a tracker solves together
(the fixed X, Y, Z cycle, or an acquisition burst); ``burst_start`` is its
first pulse's start while its windows are open, else ``None``.
"""
from __future__ import annotations

import numpy as np

from coiltrack.protocol.schema import (BUS_START_LSB_US, COIL_FAULT_LATE, COIL_FAULT_REFUSED, CURRENT_LSB_A,
                                       EVT_COIL_FAULT, PULSE_ID_MASK)

#: the driver's answer to a command that arrived after its start (``docs/protocol.md``, "Refusals")
REFUSED_LATE = COIL_FAULT_REFUSED | COIL_FAULT_LATE


class PulseSchedule:
    """Per-coil schedule of the latest commanded pulses.

    Attributes (arrays of length ``n``, indexed by coil): ``start``, ``end``
    (us, master clock), ``pulse_id``, ``measured`` (A, 0 until reported),
    ``faults`` (``COIL_FAULT_*`` bits).
    """

    def __init__(self, n_coils: int, tx, resistance):
        self.n = n_coils
        self.tx = tx
        self.start = np.zeros(n_coils, dtype=np.int64)
        self.end = np.zeros(n_coils, dtype=np.int64)
        self.pulse_id = np.zeros(n_coils, dtype=np.int64)
        self.measured = np.zeros(n_coils)
        self.faults = np.zeros(n_coils, dtype=np.int64)
        self._mv = memoryview(self.measured)
        self._fv = memoryview(self.faults)
        self._resistance = tuple(float(r) for r in resistance)
        self.next_id = 0
        self.burst_start: int | None = None
        self.burst_end = 0             # planned end of the burst's last pulse
        self.commanded = 0             # pulses commanded since the burst opened
        self.pulses = 0
        self.energy_j = 0.0            # sum of I^2 R t over the commanded pulses (J)
        self.late_refusals = 0         # latest pulses the driver refused as late (REFUSED | LATE)

    def open_burst(self, start_us: int, end_us: int) -> None:
        self.burst_start = start_us
        self.burst_end = end_us
        self.commanded = 0

    def end_burst(self) -> None:
        self.burst_start = None

    def command(self, coil: int, current_a: float, start_us: int, length_us: int) -> tuple[int, float]:
        """Send one ``COIL_PULSE_CMD`` (``Transmitter.coil_pulse``); returns ``(pulse_id, current)`` with
        the current as the driver is told to regulate it (1 mA steps).

        The command is the one the CAN bus form carries exactly (``docs/protocol.md``, "Bus forms"):
        ``pulse_id`` numbered modulo 4096, ``start_us`` rounded up to the form's 8 us grid (a
        start on the 1 ms tick is on it already)."""
        start_us = -(-int(start_us) // BUS_START_LSB_US) * BUS_START_LSB_US
        pid = self.next_id
        self.next_id = (pid + 1) & PULSE_ID_MASK      # 12 bits: the bus form's pulse_id
        self.start[coil] = start_us
        self.end[coil] = start_us + length_us
        self.pulse_id[coil] = pid
        self._mv[coil] = 0.0
        self._fv[coil] = 0
        ma = max(-32768, min(32767, int(round(current_a / CURRENT_LSB_A))))
        self.tx.coil_pulse(coil, pid, ma, start_us, length_us)
        self.pulses += 1
        self.commanded += 1
        self.energy_j += current_a * current_a * self._resistance[coil] * length_us * 1e-6
        return pid, ma * CURRENT_LSB_A

    def on_status(self, msg) -> bool:
        """A ``COIL_STATUS``: True when it reports the coil's latest pulse
        (its current, faults and actual edges are kept; a fault is reported)."""
        c = msg.coil
        if c >= self.n or msg.pulse_id != self.pulse_id[c]:
            return False
        self._mv[c] = msg.current_ma * CURRENT_LSB_A
        self._fv[c] = msg.faults
        if msg.faults:
            self.tx.event(EVT_COIL_FAULT, (c << 8) | msg.faults)
            if msg.faults & REFUSED_LATE == REFUSED_LATE:
                self.late_refusals += 1
        if msg.end_us > msg.start_us:      # the driver reports the actual edges on the master clock
            self.start[c] = msg.start_us
            self.end[c] = msg.end_us
        return True

    def ac_block(self, start_us: int, end_us: int, others_end_us: int, currents) -> None:
        """An AC block (``measure.ac_blocks``) as every coil's latest pulse: from ``start_us``
        to ``end_us`` for the last coil and to ``others_end_us`` for the others (kept a block
        past the end: the supervisor then treats every sample as taken with the coils on), the
        measured current of coil ``j`` ``currents[j]`` (A)."""
        n = self.n
        for j in range(n):
            self.start[j] = start_us
            self.end[j] = others_end_us if j < n - 1 else end_us
            self._mv[j] = currents[j]

    def refused_late(self, coil: int) -> bool:
        """Whether the driver refused ``coil``'s latest pulse as late (its command arrived after
        the pulse's start less the driver's minimum lead)."""
        return int(self.faults[coil]) & REFUSED_LATE == REFUSED_LATE

    def any_faults(self) -> int:
        f = 0
        fv = self._fv
        for j in range(self.n):
            f |= fv[j]
        return f
