"""The warm-up's fixed-cycle current where the sensor is near the source (``[adaptive] warmup_range_m``).

After a start the adaptive mode runs the fixed X, Y, Z cycle until its reference has settled
(``accuracy.FixedCycleReference``, ``reference_settle_drop``): about 10 s at the nominal current,
18 % of the fixed cycle's energy over a 60 s run, whatever the range. A pulse's information on the
orientation grows as ``I^2 |B|^2 ~ I^2 r^-6`` (the field falls as ``r^-3``; Schepers & Veltink 2010,
eqs 5 and 11: the orientation columns of ``H`` are ``[h]x``, ``|h| ~ r^-3``), so a sensor nearer than
``r_ref`` gets from ``I_nom (r / r_ref)^3`` what a sensor at ``r_ref`` gets from ``I_nom``: the
warm-up converges (heading, gyroscope offsets) as it would at ``r_ref``, for ``(r / r_ref)^6`` of the
energy. The position's information (``~ I^2 r^-8``) then exceeds what it would be at ``r_ref``.
"""
from __future__ import annotations

import math

from coiltrack.protocol.schema import CURRENT_LSB_A

__all__ = ["warmup_current"]


def warmup_current(nominal: float, r: float, r_ref: float, i_min: float) -> float:
    """The warm-up pulse's current for a sensor at range ``r`` (m): ``nominal (r / r_ref)^3``,
    rounded up to the command's resolution, at most ``nominal`` and at least ``i_min``
    (``r_ref <= 0`` or an unknown range: ``nominal``)."""
    if not (r_ref > 0.0 and r > 0.0) or r >= r_ref:
        return nominal
    x = r / r_ref
    i = nominal * x * x * x
    i = math.ceil(i / CURRENT_LSB_A - 1e-9) * CURRENT_LSB_A
    if i < i_min:
        i = i_min
    return i if i < nominal else nominal
