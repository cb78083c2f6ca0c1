"""Magnetometer set/reset flips kept out of the pulse windows (thesis ``002``
sec 5.5 and 7.2: flipping "can introduce oscillations during pulsing ...
timing of 'flipping' should occur before or after a burst of pulses and can
be synchronized using the bus system").

With every burst the firmware sends each sensor one ``MAG_FLIP_CMD`` for the
middle of the quiet gap between the end of this burst's last window span
(``end + fall + baseline + guard``) and the start of the next burst's first
span. The command alternates the set/reset state, so the sensor still flips
once a cycle (which keeps its offset in check). When the gap is shorter than
``min_gap_us`` the command repeats the current state (no flip); it still
keeps the sensor in commanded mode, where it does not flip on its own.
The current state of each sensor is read from its samples (flip bit).

With many sensors the supervisor sends a few commands a tick (``flips_per_tick``): the
commands are due only at the middle of the gap after the burst, and sixteen of them at once
make the burst's first tick the longest of the cycle (on CAN each is two frames).
"""
from __future__ import annotations

from coiltrack.protocol import MSG

FlipMsg = MSG["MAG_FLIP_CMD"]


class FlipScheduler:
    def __init__(self, sensor_ids, min_gap_us: int = 10_000):
        self.sensor_ids = tuple(int(s) for s in sensor_ids)
        self._slot = {s: i for i, s in enumerate(self.sensor_ids)}
        self.state = [1] * len(self.sensor_ids)     # last flip bit seen in each sensor's samples
        self.min_gap_us = int(min_gap_us)
        self.sent = 0
        self.flips_planned = 0
        self.last_at_us = 0
        self._states = [0] * len(self.sensor_ids)     # the planned commands' states
        self._next = 0                                  # the next planned command to send
        self.pending = 0                                # planned commands not sent yet

    def use_array(self, view) -> None:
        """Keep the sensors' set/reset states in ``view`` (one int64 item per sensor, shared with the
        compiled supervisor kernel): the same values."""
        for i, v in enumerate(self.state):
            view[i] = v
        self.state = view

    def observe(self, node: int, flip_bit: int) -> None:
        i = self._slot.get(node, -1)
        if i >= 0:
            self.state[i] = flip_bit & 1

    def plan(self, now_us: int, quiet_from_us: int, quiet_to_us: int, send, command=None, per_tick: int = 0) -> None:
        """One ``MAG_FLIP_CMD`` per sensor for the gap ``[quiet_from_us, quiet_to_us]`` (module
        docstring), each through ``send(msg)``, or ``command(node, at_us, state)`` when given
        (``Transmitter.mag_flip``: the same frame, built on the compiled core without the message).
        ``per_tick`` > 0: only that many now, the others by :meth:`step` in the next ticks (their
        states and time fixed here; a command is due only at its ``at_us``, the middle of the
        gap after the burst); commands still waiting from the last plan go first, all at once."""
        if self.pending:
            self.step(send, command, 0)
        flip = quiet_to_us - quiet_from_us >= self.min_gap_us
        at = (quiet_from_us + quiet_to_us) // 2 if flip else now_us
        states = self._states
        for i in range(len(self.sensor_ids)):
            st = self.state[i]
            if flip:
                st ^= 1
                self.flips_planned += 1
            states[i] = st
        self.last_at_us = at
        self._next = 0
        self.pending = len(self.sensor_ids)
        self.step(send, command, per_tick)

    def step(self, send, command=None, per_tick: int = 0) -> None:
        """Send the planned commands still waiting, at most ``per_tick`` of them (0: all)."""
        i, end = self._next, len(self.sensor_ids)
        if per_tick > 0 and end - i > per_tick:
            end = i + per_tick
        at, states, ids = self.last_at_us, self._states, self.sensor_ids
        while i < end:
            if command is None:
                send(FlipMsg(ids[i], at, states[i]))
            else:
                command(ids[i], at, states[i])
            self.sent += 1
            i += 1
        self._next = i
        self.pending = len(ids) - i
