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

    def plan(self, now_us: int, quiet_from_us: int, quiet_to_us: int, send, command=None) -> None:
        """One ``MAG_FLIP_CMD`` per sensor for the gap ``[quiet_from_us, quiet_to_us]`` (module
        docstring), each through ``send(msg)``, or ``command(node, at_us, state)`` when given
        (``Transmitter.mag_flip``: the same frame, built on the compiled core without the message)."""
        flip = quiet_to_us - quiet_from_us >= self.min_gap_us
        at = (quiet_from_us + quiet_to_us) // 2 if flip else now_us
        for i, node in enumerate(self.sensor_ids):
            st = self.state[i]
            if flip:
                st ^= 1
                self.flips_planned += 1
            if command is None:
                send(FlipMsg(node, at, st))
            else:
                command(node, at, st)
            self.sent += 1
        self.last_at_us = at
