"""Fixed X, Y, Z cycles of the Schepers set-up, for the energy-accuracy front of the adaptive
policy (README "Adaptive actuation", ``docs/adaptive.md``).

``schepers-fixed-<mA>`` runs the fixed cycle that ``schepers-adaptive`` is compared with
(same trajectory, seeds, sensor, pulse length and single-coil filter) at the nominal current
``<mA>`` on every coil; ``coiltrack sweep --set timing.cycle_us=...`` varies its rate.
"""
from __future__ import annotations

from coiltrack.tools.scenarios import thesis as _sc
from coiltrack.tools.scenarios.base import Family, Scenario

SCENARIOS = Family()        # this family's scenarios (listed in scenarios/__init__.py)
register = SCENARIOS.add

#: nominal currents of the fixed-cycle baselines (A): Schepers' 0.91 A and two lower ones
FIXED_CURRENTS_A = (0.91, 0.64, 0.45)


def _fixed(current: float):
    def make(**kw):
        return _sc.schepers_fixed_config(coils=_sc._schepers_coils(current), **kw)
    return make


for _i in FIXED_CURRENTS_A:
    register(Scenario(
        name=f"schepers-fixed-{int(round(_i * 1000))}",
        summary=f"the schepers-adaptive fixed X/Y/Z cycle at {_i} A (60 ms pulses), for the energy front",
        description=f"The fixed X, Y, Z cycle of schepers-adaptive (60 ms pulses, 140 ms apart, 600 ms cycle, "
                    f"each pulse a single-coil update of the same EKF) at {_i} A on every coil, on the same "
                    f"trajectory and sensor; timing.cycle_us sets its rate.",
        duration_s=60.0,
        build_world=_sc._schepers_world,
        firmware_config=_fixed(_i),
        sensor=_sc._SCHEPERS_SENSOR,
        reference=_sc._SCHEPERS_REFERENCE,
        parameters={**_sc._SCHEPERS_PARAMETERS, "coils": f"3 orthogonal, 50 turns, r=5.5 cm, {_i} A"},
    ))
