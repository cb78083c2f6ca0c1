"""The IMU sample ring: received IMU samples waiting for the tracker."""
from __future__ import annotations

import numpy as np

from coiltrack.protocol.schema import ACC_LSB, GYR_LSB

from coiltrack.firmware.estimate.fusion_rings import KernelRing

#: the ring's state, int64 slots of one array (``core/include/ct_fusimu.h`` CT_IR_*)
_LAST_T, _DROPPED, _RECEIVED, _N = range(4)


def _state(k: int, doc: str):
    return property(lambda self: int(self._stv[k]), doc=doc)


class ImuRing(KernelRing):
    """Fixed-capacity ring of received IMU samples (time, specific force
    m/s^2, rate rad/s; sensor frame), drained by the tick (``pop``). A full
    ring drops its oldest sample (counted). Its head and count are shared with the compiled
    per-sample path (``estimate.fusion_rings.KernelRing``). ``core``: on the compiled core
    (``coiltrack.firmware.core.Core`` with its extension) :meth:`push` is
    ``ct_imu_ring_push`` (``core/src/fusimu.c``: the same operations, the state in the same
    array), bound here."""

    last_t = _state(_LAST_T, "the newest sample's time (us)")
    dropped = _state(_DROPPED, "samples refused (not newer) or overwritten (a full ring)")
    received = _state(_RECEIVED, "samples taken")

    def __init__(self, capacity: int, core=None):
        super().__init__(capacity, (("F", 3), ("W", 3)))
        self.st = np.zeros(_N, dtype=np.int64)
        self._stv = memoryview(self.st)
        self._stv[_LAST_T] = -(1 << 62)
        ext = getattr(core, "ext", None)
        if ext is not None:
            assert ext.FUS_IR_N == _N
            self.push = ext.ImuPush(self.t, self.d, self.hc, self.st, ACC_LSB, GYR_LSB).push

    def push(self, msg) -> None:
        t = msg.t_us
        st = self._stv
        if t <= st[_LAST_T]:          # not newer than the previous sample: refused
            st[_DROPPED] += 1
            return
        st[_LAST_T] = t
        if self.full:
            st[_DROPPED] += 1
        k = KernelRing.push(self, t)
        d = self.dv
        d[k, 0] = msg.ax * ACC_LSB
        d[k, 1] = msg.ay * ACC_LSB
        d[k, 2] = msg.az * ACC_LSB
        d[k, 3] = msg.gx * GYR_LSB
        d[k, 4] = msg.gy * GYR_LSB
        d[k, 5] = msg.gz * GYR_LSB
        st[_RECEIVED] += 1

    def pop_sample(self, out) -> int:
        """Release the oldest sample into ``out[0:6]`` (specific force m/s^2,
        rate rad/s) and return its time (us), or -1 when the ring is empty."""
        k = self.pop()
        if k < 0:
            return -1
        d = self.dv
        out[0], out[1], out[2], out[3], out[4], out[5] = d[k, 0], d[k, 1], d[k, 2], d[k, 3], d[k, 4], d[k, 5]
        return self.tv[k]
