"""The IMU sample ring: received IMU samples waiting for the tracker."""
from __future__ import annotations

import numpy as np

from coiltrack.protocol.schema import ACC_LSB, GYR_LSB


class ImuRing:
    """Fixed-capacity ring of received IMU samples (time, specific force
    m/s^2, rate rad/s; sensor frame), drained by the tick. A full ring drops
    its oldest sample (counted)."""

    def __init__(self, capacity: int):
        self.cap = int(capacity)
        self.t = np.zeros(self.cap, dtype=np.int64)
        self.d = np.zeros((self.cap, 6))
        self._tv = memoryview(self.t)
        self._dv = memoryview(self.d)
        self.head = 0
        self.count = 0
        self.dropped = 0
        self.received = 0
        self.last_t = -(1 << 62)

    def push(self, msg) -> None:
        t = msg.t_us
        if t <= self.last_t:          # not newer than the previous sample: refused
            self.dropped += 1
            return
        self.last_t = t
        if self.count == self.cap:
            self.head = self.head + 1 if self.head + 1 < self.cap else 0
            self.count -= 1
            self.dropped += 1
        k = self.head + self.count
        if k >= self.cap:
            k -= self.cap
        self._tv[k] = t
        d = self._dv
        d[k, 0] = msg.ax * ACC_LSB
        d[k, 1] = msg.ay * ACC_LSB
        d[k, 2] = msg.az * ACC_LSB
        d[k, 3] = msg.gx * GYR_LSB
        d[k, 4] = msg.gy * GYR_LSB
        d[k, 5] = msg.gz * GYR_LSB
        self.count += 1
        self.received += 1

    def pop(self) -> int:
        """Slot of the oldest sample (then released), or -1."""
        if self.count == 0:
            return -1
        k = self.head
        self.head = k + 1 if k + 1 < self.cap else 0
        self.count -= 1
        return k
