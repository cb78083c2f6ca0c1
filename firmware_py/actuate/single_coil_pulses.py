"""The single-coil pulses in flight: their slots, the coils' duty history, the quiet gaps.

Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``) sec. 2.1: one coil
is pulsed at a time, and each pulse's amplitude updates the EKF at the
instant it describes. :class:`PulseBook` is the one owner of what was
commanded (``PulseSchedule.command``): the slots of the pulses whose windows
are not closed yet, the EKF clone each one feeds, the pulses per coil kept
for the driver's duty limit, the earliest start the next pulse may take (the
quiet gap its windows need, or a set/reset flip's baseline) and the latest
flip command. The actuation policies (``actuate.single_coil_policy``) and the
acquisition burst (``track.single_coil_acquire``) command through it; the
tracker closes its windows through it. All arrays are allocated here.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE

__all__ = ["PulseSlot", "PulseBook", "DUTY_HIST"]

#: pulses per coil remembered for the duty-cycle check (an array size: at most
#: ``coil_duty_window_us`` / (pulse + gap) pulses fit in the window, 12 at the defaults)
DUTY_HIST = 32
#: ``PulseSlot.clone`` of an acquisition pulse whose window is closed (kept until the burst is)
CLOSED_ACQ = -2


class PulseSlot:
    """One commanded pulse whose window is not closed yet (owned by :class:`PulseBook`;
    read by the others)."""

    __slots__ = ("active", "coil", "pid", "start", "end", "current", "measured", "faults", "status",
                 "clone", "acq")

    def __init__(self):
        self.active = False
        self.coil = 0
        self.pid = 0
        self.start = 0
        self.end = 0
        self.current = 0.0
        self.measured = 0.0
        self.faults = 0
        self.status = False
        self.clone = -1
        self.acq = False


class PulseBook:
    """The pulses of the single-coil mode, from command to closed window.

    ``schedule``: the firmware's ``PulseSchedule`` (numbers and sends each command; its
    ``energy_j``). ``filters``: the sensors' EKFs, told to clone the pose at each pulse's
    measurement time (``mid_us`` after its start edge). ``gap_us``: the quiet time a pulse
    needs after its end (fall, baseline, guard). ``core``: the numeric core (on the compiled one
    :meth:`duty_ok` is ``ct_scp_duty_ok``, bound to the history once)."""

    def __init__(self, cfg, n_coils: int, schedule, filters, mid_us: int, gap_us: int, first_free_us: int,
                 core=_DEFAULT_CORE):
        self.cfg = cfg
        self.schedule = schedule
        self.filters = tuple(filters)
        self.mid_us = int(mid_us)
        self.gap_us = int(gap_us)
        self.slots = tuple(PulseSlot() for _ in range(max(2, n_coils)))
        self._order = [0] * len(self.slots)
        # recent pulses per coil (start, end), to stay within the driver's duty limit
        self._hist = np.zeros((n_coils, DUTY_HIST, 2), dtype=np.int64)
        self._histv = memoryview(self._hist.reshape(-1))     # elements read as Python ints
        self._hist_k = [0] * n_coils
        self.next_free_us = int(first_free_us)
        self.last_pulse_end = 0
        self.last_pulse_us = 0                   # the length of that pulse
        self.last_flip_cmd_us = -(1 << 62)
        self.pulses = 0
        if core.ext is not None:
            lim = cfg.limits
            self._duty = core.ext.DutyCore(self._hist, n_coils, DUTY_HIST, lim.coil_duty_window_us,
                                           cfg.adaptive.duty_margin * lim.coil_max_duty * lim.coil_duty_window_us)
            self.duty_ok = self._duty.ok

    # ------------------------------------------------------------ commands
    def command(self, coil: int, current: float, start: int, length: int, acq: bool, mid_us: int = -1) -> int:
        """Command one pulse; returns its slot, or -1 when every slot is taken. A tracking
        pulse (``acq`` false) gets the EKF clone no other pulse in flight uses, taken
        ``mid_us`` after the start (default: the book's)."""
        i = self.free_slot()
        if i < 0:
            return -1
        sl = self.slots[i]
        pid, sl.current = self.schedule.command(coil, current, start, length)   # as the driver regulates it
        sl.active = True
        sl.coil = coil
        sl.pid = pid
        sl.start = start
        sl.end = start + length
        sl.measured = 0.0
        sl.faults = 0
        sl.status = False
        sl.acq = acq
        sl.clone = -1
        if not acq:
            used0 = used1 = False
            for o in self.slots:
                if o is not sl and o.active and not o.acq:
                    used0 |= o.clone == 0
                    used1 |= o.clone == 1
            sl.clone = 0 if not used0 else (1 if not used1 else -1)
            if sl.clone >= 0:
                t_m = start + (self.mid_us if mid_us < 0 else mid_us)
                for f in self.filters:
                    f.schedule_clone(sl.clone, t_m)
        self.next_free_us = start + length + self.gap_us
        self.last_pulse_end = start + length
        self.last_pulse_us = length
        k = self._hist_k[coil]
        self._hist[coil, k, 0] = start
        self._hist[coil, k, 1] = start + length
        self._hist_k[coil] = (k + 1) % DUTY_HIST
        self.pulses += 1
        return i

    def hold_until(self, t_us: int) -> None:
        """No pulse may start before ``t_us`` (a flip's trailing baseline)."""
        if t_us > self.next_free_us:
            self.next_free_us = t_us

    def note_flip(self, now_us: int) -> None:
        self.last_flip_cmd_us = now_us

    def on_status(self, msg, lsb: float) -> None:
        """The driver's ``COIL_STATUS`` of a pulse in flight: measured current (``lsb`` A per
        count), faults, and the edges as executed."""
        for sl in self.slots:
            if sl.active and sl.coil == msg.coil and sl.pid == msg.pulse_id:
                sl.measured = msg.current_ma * lsb
                sl.faults = msg.faults
                sl.status = True
                if msg.end_us > msg.start_us:
                    sl.start = msg.start_us
                    sl.end = msg.end_us
                return

    def release(self, sl: PulseSlot) -> None:
        sl.active = False

    def close_acq(self, sl: PulseSlot) -> None:
        """An acquisition pulse's window is closed; the slot stays taken until the burst is."""
        sl.clone = CLOSED_ACQ

    def end_burst(self) -> None:
        for sl in self.slots:
            if sl.acq:
                sl.active = False
                sl.acq = False
                sl.clone = -1

    # ------------------------------------------------------------ queries
    def free_slot(self) -> int:
        for i, sl in enumerate(self.slots):
            if not sl.active:
                return i
        return -1

    def n_active(self) -> int:
        k = 0
        for sl in self.slots:
            if sl.active:
                k += 1
        return k

    def burst_open(self) -> bool:
        """Whether an acquisition pulse's window is still open."""
        for sl in self.slots:
            if sl.active and sl.acq and sl.clone != CLOSED_ACQ:
                return True
        return False

    def in_flight_order(self) -> int:
        """The slots whose windows are open, oldest first, into ``order``; returns their count."""
        m = 0
        order = self._order
        for i, sl in enumerate(self.slots):
            if sl.active and not (sl.acq and sl.clone == CLOSED_ACQ):
                order[m] = i
                m += 1
        for a in range(1, m):
            j = a
            while j > 0 and self.slots[order[j - 1]].start > self.slots[order[j]].start:
                order[j - 1], order[j] = order[j], order[j - 1]
                j -= 1
        return m

    def ordered(self, k: int) -> PulseSlot:
        return self.slots[self._order[k]]

    def duty_ok(self, c: int, start: int, length: int) -> bool:
        """Whether coil ``c`` may carry a pulse ``[start, start + length)``
        within ``coil_max_duty`` over any ``coil_duty_window_us`` (the limit
        the driver enforces; a refused pulse is a wasted decision)."""
        cfg = self.cfg
        end = start + length
        w0 = end - cfg.limits.coil_duty_window_us
        on = length
        h = self._histv
        b = 2 * DUTY_HIST * c                   # coil c's (start, end) pairs, flat
        for k in range(b + 1, b + 2 * DUTY_HIST, 2):
            e0 = h[k]
            if e0 > w0:                         # most ended before the window: their start not read
                s0 = h[k - 1]
                if e0 > s0:
                    on += min(e0, end) - max(s0, w0)
        return on <= cfg.adaptive.duty_margin * cfg.limits.coil_max_duty * cfg.limits.coil_duty_window_us

    def quiet_at(self, t: int, pulse_us: int) -> bool:
        """Whether a magnetometer sample taken at ``t`` saw no coil current (outside every
        window in flight and the last pulse's, with their guards and fall; ``pulse_us``:
        the last pulse's length as the policy reckons it)."""
        cfg = self.cfg
        for sl in self.slots:
            if sl.active and sl.start - cfg.pulse.guard_us <= t <= sl.end + cfg.pulse.fall_us + cfg.pulse.guard_us:
                return False
        if self.last_pulse_end and self.last_pulse_end - pulse_us - cfg.pulse.guard_us <= t <= \
                self.last_pulse_end + cfg.pulse.fall_us + cfg.pulse.guard_us:
            return False
        return True
