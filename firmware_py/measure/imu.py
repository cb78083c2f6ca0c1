"""The IMU sample ring: received IMU samples waiting for the tracker."""
from __future__ import annotations

from coiltrack.protocol.schema import ACC_LSB, GYR_LSB

from coiltrack.firmware.estimate.fusion_rings import KernelRing


class ImuRing(KernelRing):
    """Fixed-capacity ring of received IMU samples (time, specific force
    m/s^2, rate rad/s; sensor frame), drained by the tick (``pop``). A full
    ring drops its oldest sample (counted). Its head and count are shared with the compiled
    per-sample path (``estimate.fusion_rings.KernelRing``)."""

    def __init__(self, capacity: int):
        super().__init__(capacity, (("F", 3), ("W", 3)))
        self.dropped = 0
        self.received = 0
        self.last_t = -(1 << 62)

    def push(self, msg) -> None:
        t = msg.t_us
        if t <= self.last_t:          # not newer than the previous sample: refused
            self.dropped += 1
            return
        self.last_t = t
        if self.full:
            self.dropped += 1
        k = KernelRing.push(self, t)
        d = self.dv
        d[k, 0] = msg.ax * ACC_LSB
        d[k, 1] = msg.ay * ACC_LSB
        d[k, 2] = msg.az * ACC_LSB
        d[k, 3] = msg.gx * GYR_LSB
        d[k, 4] = msg.gy * GYR_LSB
        d[k, 5] = msg.gz * GYR_LSB
        self.received += 1

    def pop_sample(self, out) -> int:
        """Release the oldest sample into ``out[0:6]`` (specific force m/s^2,
        rate rad/s) and return its time (us), or -1 when the ring is empty."""
        k = self.pop()
        if k < 0:
            return -1
        d = self.dv
        out[0], out[1], out[2], out[3], out[4], out[5] = d[k, 0], d[k, 1], d[k, 2], d[k, 3], d[k, 4], d[k, 5]
        return self.tv[k]
