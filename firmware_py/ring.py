"""The one fixed-capacity ring of timestamped entries with named rows.

A :class:`Ring` is the firmware's FIFO of measurements and results (the
shape of PX4's ``RingBuffer``): storage allocated once, an int64 time per
entry (``t``) and a float64 row per entry (``d``) whose columns are named
fields, e.g. ``Ring(128, (("F", 3), ("W", 3)))`` gives ``ring.F ==
slice(0, 3)`` and ``ring.W == slice(3, 6)``. Entries are addressed by their
physical slot (the row of ``t`` and ``d``); the operations return slots:

* :meth:`push` ``(t) -> slot``: a new newest entry, overwriting the oldest
  when the ring is full (callers that must not lose the oldest test
  :attr:`full` first);
* :meth:`pop` ``() -> slot``: remove the oldest entry (its slot stays
  readable until the next push), ``-1`` when empty;
* :meth:`peek` ``(age) -> slot``: the entry ``age`` pushes old (0 the newest),
  ``-1`` when there is none;
* :meth:`slot` ``(i)``: logical index ``i`` (0 the oldest) to slot;
  :meth:`index_at_or_after` ``(t)``: binary search on time;
* :meth:`drop_newer_than` ``(t)`` (rewind), :meth:`clear`,
  :meth:`copy_from` (a second ring of the same shape takes this one's
  contents: the shadow copies of a delayed-measurement filter).

Times pushed must increase (the search relies on it). Single elements are
read and written through the memoryviews ``tv`` and ``dv`` (Python ints
and floats, no numpy scalars); nothing here creates an array after
``__init__``.
"""
from __future__ import annotations

import operator

import numpy as np


def field_slices(fields: tuple[tuple[str, int], ...]) -> dict[str, slice]:
    """Columns of each named field of a row (in order), e.g. for module constants."""
    out = {}
    width = 0
    for name, size in fields:
        size = operator.index(size)
        if size < 1 or not name.isidentifier() or hasattr(Ring, name) or name in out:
            raise ValueError(f"ring field {name!r}: needs a new identifier and size >= 1")
        out[name] = slice(width, width + size)
        width += size
    if width < 1:
        raise ValueError("ring fields: at least one column")
    return out


class Ring:
    """Fixed-capacity ring (see module docstring).

    Parameters
    ----------
    capacity : int
        Entries kept (>= 2).
    fields : tuple of (name, size)
        Named columns of an entry's row, in order (total width >= 1).
    """

    def __init__(self, capacity: int, fields: tuple[tuple[str, int], ...]):
        capacity = operator.index(capacity)
        if capacity < 2:
            raise ValueError(f"ring capacity must be >= 2, got {capacity}")
        cols = field_slices(fields)
        for name, sl in cols.items():
            setattr(self, name, sl)
        names = tuple(cols)
        width = sl.stop
        self.fields = tuple(names)
        self.capacity = capacity
        self.width = width
        self.t = np.zeros(capacity, dtype=np.int64)
        self.d = np.zeros((capacity, width))
        self.tv = memoryview(self.t)
        self.dv = memoryview(self.d)
        self._head = 0          # slot of the next push
        self._count = 0

    # ------------------------------------------------------------ size
    def __len__(self) -> int:
        return self._count

    @property
    def full(self) -> bool:
        return self._count == self.capacity

    # ------------------------------------------------------------ FIFO
    def push(self, t_us: int) -> int:
        """Append an entry at time ``t_us`` (its row is the caller's to fill);
        a full ring overwrites its oldest entry. Returns the slot."""
        p = self._head
        self.tv[p] = t_us
        n = p + 1
        self._head = 0 if n == self.capacity else n
        if self._count < self.capacity:
            self._count += 1
        return p

    def pop(self) -> int:
        """Remove the oldest entry; its slot (readable until the next push), or -1."""
        if self._count == 0:
            return -1
        p = self._head - self._count
        if p < 0:
            p += self.capacity
        self._count -= 1
        return p

    def peek(self, age: int) -> int:
        """Slot of the entry ``age`` pushes old (0: the newest), -1 if not held."""
        if not 0 <= age < self._count:
            return -1
        p = self._head - 1 - age
        return p + self.capacity if p < 0 else p

    def last_pushed_slot(self) -> int:
        """Slot the latest :meth:`push` wrote (its row stays readable until overwritten, also
        after a :meth:`pop`); meaningful once anything was pushed."""
        return self._head - 1 if self._head > 0 else self.capacity - 1

    # ------------------------------------------------------------ by index, by time
    def slot(self, i: int) -> int:
        """Slot of logical index ``i`` (0: the oldest; ``0 <= i < len``)."""
        p = self._head - self._count + i
        cap = self.capacity
        if p < 0:
            p += cap
        elif p >= cap:
            p -= cap
        return p

    def index_at_or_after(self, t_us: int) -> int:
        """Logical index of the first entry with time >= ``t_us`` (``len`` if none)."""
        lo = 0
        hi = self._count
        tv = self.tv
        base = self._head - self._count
        cap = self.capacity
        while lo < hi:
            mid = (lo + hi) >> 1
            p = base + mid
            if p < 0:
                p += cap
            elif p >= cap:
                p -= cap
            if tv[p] < t_us:
                lo = mid + 1
            else:
                hi = mid
        return lo

    # ------------------------------------------------------------ whole ring
    def drop_newer_than(self, t_us: int) -> None:
        """Forget the newest entries with time > ``t_us`` (a rewind)."""
        n = self.index_at_or_after(t_us + 1)
        h = self._head - (self._count - n)
        self._head = h + self.capacity if h < 0 else h
        self._count = n

    def clear(self) -> None:
        self._head = 0
        self._count = 0

    def advance(self, n: int) -> None:
        """Account for ``n`` entries a compiled kernel pushed: it wrote their times and rows into
        ``t`` and ``d`` at the slots ``n`` calls of :meth:`push` would have given (from
        ``slot(0) + len`` on, overwriting the oldest when full)."""
        cap = self.capacity
        self._head = (self._head + n) % cap
        c = self._count + n
        self._count = c if c < cap else cap

    def copy_from(self, other: "Ring") -> None:
        """Take ``other``'s entries (same capacity and width); one array copy each."""
        if other.capacity != self.capacity or other.width != self.width:
            raise ValueError("copy_from needs a ring of the same capacity and width")
        np.copyto(self.t, other.t)
        np.copyto(self.d, other.d)
        self._head = other._head
        self._count = other._count
