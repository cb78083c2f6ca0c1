"""A :class:`~coiltrack.firmware.ring.Ring` a compiled kernel can push to and pop from in place.

The fused trackers' per-IMU-sample path (``core/src/fusimu.c``, ``ext.ImuSample``) takes one sample
off a sensor's IMU ring and keeps it in the fusion filter's IMU ring, its pose in the live history
and the fused pose in the output queue, all in one call. :class:`KernelRing` keeps the ring's head
and count in a two-element int64 array (``hc``) the kernel binds once, instead of two Python ints:
every :class:`~coiltrack.firmware.ring.Ring` operation is the same (they read and write ``_head``
and ``_count``, here the array's two entries), and the kernel's ``ct_ring_push`` / ``ct_ring_pop``
are :meth:`Ring.push` and :meth:`Ring.pop`. Nothing here allocates after ``__init__``.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.ring import Ring


class KernelRing(Ring):
    """:class:`~coiltrack.firmware.ring.Ring` with its head and count in ``hc`` (int64, ``state``
    entries: head, count, then any further state a subclass keeps beside them)."""

    def __init__(self, capacity: int, fields: tuple[tuple[str, int], ...], state: int = 2):
        self.hc = np.zeros(state, dtype=np.int64)
        self._hcv = memoryview(self.hc)
        super().__init__(capacity, fields)
        self._df = memoryview(self.d.reshape(-1))      # the rows, flat: a run of slots is one slice

    def copy_slots_from(self, other: "KernelRing", h: int, n: int) -> None:
        """Slots ``h, h + 1, ...`` (``n`` of them, modulo the capacity) of ``other`` (same capacity and width)
        into this ring, times and rows; head and count unchanged (:meth:`take_position`)."""
        cap = self.capacity
        if h >= cap:
            h -= cap
        e = h + n
        if e <= cap:
            self._copy_range(other, h, e)
        else:
            self._copy_range(other, h, cap)
            self._copy_range(other, 0, e - cap)

    def _copy_range(self, other: "KernelRing", a: int, b: int) -> None:
        w = self.width
        self.tv[a:b] = other.tv[a:b]
        self._df[a * w:b * w] = other._df[a * w:b * w]

    def take_position(self, other: "KernelRing") -> None:
        """``other``'s head and count (the end of :meth:`Ring.copy_from` after :meth:`copy_slots_from`)."""
        hc = self._hcv
        ohc = other._hcv
        hc[0] = ohc[0]
        hc[1] = ohc[1]

    def _set_head(self, v: int) -> None:
        self._hcv[0] = v

    def _set_count(self, v: int) -> None:
        self._hcv[1] = v

    _head = property(lambda self: self._hcv[0], _set_head)     # slot of the next push
    _count = property(lambda self: self._hcv[1], _set_count)   # entries held

    # the operations of every tick, on the array directly (the same as Ring's through the properties)
    def __len__(self) -> int:
        return self._hcv[1]

    @property
    def full(self) -> bool:
        return self._hcv[1] == self.capacity

    def push(self, t_us: int) -> int:
        hc = self._hcv
        p = hc[0]
        self.tv[p] = t_us
        n = p + 1
        hc[0] = 0 if n == self.capacity else n
        if hc[1] < self.capacity:
            hc[1] += 1
        return p

    def pop(self) -> int:
        hc = self._hcv
        c = hc[1]
        if c == 0:
            return -1
        p = hc[0] - c
        if p < 0:
            p += self.capacity
        hc[1] = c - 1
        return p

    def slot(self, i: int) -> int:
        hc = self._hcv
        p = hc[0] - hc[1] + i
        cap = self.capacity
        if p < 0:
            p += cap
        elif p >= cap:
            p -= cap
        return p
