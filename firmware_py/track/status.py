"""``POSE_*`` status bits from what a pose was made of: the one place the
window flags and the driver's coil faults become pose status."""
from __future__ import annotations

from coiltrack.protocol.schema import (COIL_FAULT_OPEN_CIRCUIT, COIL_FAULT_OVER_CURRENT, COIL_FAULT_REFUSED,
                                       POSE_COIL_FAULT, POSE_DEGRADED, POSE_SATURATED)

from coiltrack.firmware.measure.pulse import PULSE_SATURATED

#: coil faults after which a pulse's amplitude is not used
COIL_FATAL = COIL_FAULT_OPEN_CIRCUIT | COIL_FAULT_OVER_CURRENT | COIL_FAULT_REFUSED


def input_status(window_flags: int, coil_faults: int) -> int:
    """``POSE_SATURATED`` for a saturated window, ``POSE_DEGRADED`` for any
    window flag, ``POSE_COIL_FAULT`` for any driver fault."""
    bits = 0
    if window_flags & PULSE_SATURATED:
        bits |= POSE_SATURATED
    if window_flags:
        bits |= POSE_DEGRADED
    if coil_faults:
        bits |= POSE_COIL_FAULT
    return bits
