"""The single-coil tracker's NIS monitor on the compiled core.

:class:`CompiledNisMonitor` is ``actuate.coil_choice.NisMonitor`` (the reference, unchanged) with
its per-update steps, :meth:`~NisMonitor.add` (the windowed chi-square test with hysteresis and
the covariance-matching scale, Schepers & Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt``
sec. 3.3) and :meth:`~NisMonitor.add_used` (the long-run excess), run by ``ct_nis_add`` and
``ct_nis_add_used`` (``core/src/sc_policy.c``): the same operations in the same order, so the same
bits. Its state (count, ring head, mean, the verdict, the scale, the counters, the excess) lives in
one float64 array the kernels write, read and written through properties under the reference's
names, so every reader (the tracker, the policy, ``reset``) sees the reference's interface.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.actuate.coil_choice import NisMonitor

__all__ = ["CompiledNisMonitor", "nis_monitor"]

# the slots of the state array (ct_sc_policy.h CT_NIS_*)
_COUNT, _HEAD, _MEAN, _INC, _SCALE, _TOTAL, _FLAGGED, _EXCESS = range(8)


def _int_slot(k: int, doc: str) -> property:
    def get(self) -> int:
        return int(self._sv[k])

    def put(self, v) -> None:
        self._sv[k] = v
    return property(get, put, doc=doc)


def _float_slot(k: int, doc: str) -> property:
    def get(self) -> float:
        return self._sv[k]

    def put(self, v) -> None:
        self._sv[k] = v
    return property(get, put, doc=doc)


class CompiledNisMonitor(NisMonitor):
    """:class:`NisMonitor` whose ``add`` and ``add_used`` run compiled (module docstring).
    ``ext``: the compiled extension (``coiltrack.firmware.core.Core.ext``); the other parameters
    are :class:`NisMonitor`'s."""

    count = _int_slot(_COUNT, "values in the window")
    _head = _int_slot(_HEAD, "the ring's next slot")
    mean = _float_slot(_MEAN, "mean NIS over the window")
    r_scale = _float_slot(_SCALE, "the measurement covariance's factor")
    total = _int_slot(_TOTAL, "values recorded")
    flagged = _int_slot(_FLAGGED, "updates made while inconsistent")
    excess = _float_slot(_EXCESS, "long-run mean of NIS / dof with the covariance used")

    @property
    def inconsistent(self) -> bool:
        """Whether the window's mean is beyond the chi-square bound (with hysteresis)."""
        return self._sv[_INC] != 0.0

    @inconsistent.setter
    def inconsistent(self, v) -> None:
        self._sv[_INC] = 1.0 if v else 0.0

    def __init__(self, ext, **kw):
        self._st = np.zeros(ext.NIS_NST)
        self._sv = memoryview(self._st)
        super().__init__(**kw)
        self._ck = ext.NisCore(self._buf, self._bound, self._st, self.window, self.min_count, float(self.dof),
                               self.min_mean, self.max_scale, self.excess_gate, self._alpha)
        self.add = self._ck.add
        self.add_used = self._ck.add_used
        self.kernels = "compiled"


def nis_monitor(core, **kw) -> NisMonitor:
    """The NIS monitor of ``core`` (``coiltrack.firmware.core.Core``): the compiled twin where the
    extension is loaded, else the reference."""
    if core.ext is not None:
        return CompiledNisMonitor(core.ext, **kw)
    return NisMonitor(**kw)
