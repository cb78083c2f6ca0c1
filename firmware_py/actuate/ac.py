"""AC actuation: the drive plan (frequency division) sent once, the driver's reports kept.

Raab et al. 1979 (``004_86267342cd7488ce.txt``) excite the source with a
carrier and demodulate synchronously; coiltrack drives every coil at its own
frequency all the time (frequency division, plan checked at start-up by
:func:`coiltrack.firmware.actuate.ac_plan.check_plan`). One ``AC_DRIVE_CMD``
per coil, ``ac_lead_us`` before the switch-on at ``boot + ac_start_us``,
with the phase reference ``ref_us`` (master clock): the driver makes the
current ``A cos(2 pi f (t - ref_us))`` and reports the measured amplitude
and phase against that reference (``AC_DRIVE_STATUS``). A plan the driver
refuses (not yet synchronised, a coil it does not have) or does not answer
within ``ac_lead_us`` after the switch-on, or whose driver has been silent
for ``ac_status_timeout_us`` (it reports about once a second), is sent
again with a new ``plan_id`` and a later switch-on.

State (allocated once, per coil): ``freq_hz``, ``amplitude_a`` (measured, A
peak; 0 until reported), ``phase_rad`` (measured, rad), ``faults``
(``AC_FAULT_*``). ``ref_us``, ``on_us``: the accepted plan's phase reference
and switch-on (master clock), ``ready``: every coil reported without a
refusal.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.protocol import MSG
from coiltrack.protocol.schema import (AC_CURRENT_LSB_A, AC_FAULT_REFUSED, AC_FREQ_LSB_HZ, AC_PHASE_LSB_RAD,
                                       EVT_COIL_FAULT)

_CMD = MSG["AC_DRIVE_CMD"]
AC_STATUS_ID = MSG["AC_DRIVE_STATUS"].ID


class ACActuation:
    """The actuate stage of AC excitation (``step(now_us)``) and the driver's reports (``on_status``)."""

    def __init__(self, cfg, tx):
        n = len(cfg.source.coils)
        self.n = n
        self.tx = tx
        self.freq_hz = np.array([float(f) for f in cfg.ac.ac_freqs_hz])
        amp = [cfg.ac.ac_current_a or abs(float(c.current)) for c in cfg.source.coils]
        self.target_ua = tuple(int(round(a / AC_CURRENT_LSB_A)) for a in amp)
        self.freq_mhz = tuple(int(round(f / AC_FREQ_LSB_HZ)) for f in cfg.ac.ac_freqs_hz)
        self.amplitude_a = np.zeros(n)
        self.phase_rad = np.zeros(n)
        self.faults = np.zeros(n, dtype=np.int64)
        self._av = memoryview(self.amplitude_a)
        self._pv = memoryview(self.phase_rad)
        self._fv = memoryview(self.faults)
        self.reported = [False] * n
        self.start_after_us = int(cfg.ac.ac_start_us)
        self.lead_us = int(cfg.ac.ac_lead_us)
        self.plan_id = -1
        self.ref_us = 0
        self.on_us = 0
        self.sent_at_us = -1
        self.ready = False
        self.plans_sent = 0
        self.refusals = 0
        self.statuses = 0
        self.timeouts = 0
        self.status_timeout_us = int(cfg.ac.ac_status_timeout_us)
        self.last_status_us = 0
        self._boot = None

    def step(self, now_us: int) -> None:
        if self._boot is None:
            self._boot = now_us
        if self.sent_at_us < 0:
            on = self._boot + self.start_after_us
            if now_us >= on - self.lead_us:
                self._send_plan(max(on, now_us + self.lead_us))
            return
        if not self.ready and now_us > self.on_us + self.lead_us:
            self._send_plan(now_us + self.lead_us)        # not answered or refused: again, later
        elif self.ready and now_us - self.last_status_us > self.status_timeout_us:
            self.timeouts += 1                            # the driver went silent (rebooted, off): again
            self._send_plan(now_us + self.lead_us)

    def _send_plan(self, on_us: int) -> None:
        self.plan_id = (self.plan_id + 1) & 0xFFFF
        self.ref_us = self.on_us = int(on_us)
        self.ready = False
        for j in range(self.n):
            self.reported[j] = False
            self._av[j] = 0.0
            self._fv[j] = 0
            self.tx.send(_CMD(j, self.plan_id, self.freq_mhz[j], self.target_ua[j], self.ref_us, self.on_us, 0))
        self.sent_at_us = self.on_us - self.lead_us
        self.plans_sent += 1

    def on_status(self, msg, now_us: int = 0) -> None:
        """An ``AC_DRIVE_STATUS`` of the current plan: keep the measured phasor and the faults."""
        c = msg.coil
        if c >= self.n or msg.plan_id != self.plan_id:
            return
        self.statuses += 1
        self.last_status_us = now_us
        self._fv[c] = msg.faults
        if msg.faults:
            self.tx.event(EVT_COIL_FAULT, (c << 8) | (msg.faults & 0xFF))
        if msg.faults & AC_FAULT_REFUSED:
            self.refusals += 1
            self.ready = False
            return
        self._av[c] = msg.amplitude_ua * AC_CURRENT_LSB_A
        self._pv[c] = msg.phase_urad * AC_PHASE_LSB_RAD
        self.reported[c] = True
        ok = True
        for j in range(self.n):
            if not self.reported[j]:
                ok = False
        self.ready = ok

    def counters(self) -> dict:
        return {"ac_plans_sent": self.plans_sent, "ac_refusals": self.refusals, "ac_statuses": self.statuses,
                "ac_status_timeouts": self.timeouts}


def wrap_phase(x: float) -> float:
    """``x`` (rad) into ``(-pi, pi]``."""
    y = math.fmod(x + math.pi, 2.0 * math.pi)
    if y <= 0.0:
        y += 2.0 * math.pi
    return y - math.pi
