"""The current cap at the knee of a pulse's information per joule (``firmware_py/actuate/saturation_knee.py``):
against the bound's own pulse weight (``tools/analyses/pulse_cost.pulse_weight``, ``I^2 / (a + b I^2)``)
and closed forms; the key refused out of range."""
import math

import numpy as np
import pytest

from coiltrack.firmware.actuate.saturation_knee import cap_at_knee, knee_current
from coiltrack.tools.analyses.pulse_cost import pulse_weight

VAR, REL, TAU = 4e-18, 3e-3, 1e-4           # T^2, relative, A


@pytest.mark.parametrize("kappa", [0.5, 1.0, 3.0])
def test_information_per_joule_at_the_knee_is_one_over_one_plus_kappa(kappa):
    """At ``I_knee`` the weight per ``I^2`` is ``1 / ((1 + kappa) a)``, ``a = var + tau^2 |h|^2``:
    the model error's variance ``(rho I |h|)^2`` is ``kappa a`` there (a dropped ``kappa`` or the
    current's term left out of ``a`` moves it)."""
    h = np.array([3e-6, -4e-6, 12e-6])                  # |h| 13e-6 T/A
    hn2 = float(h @ h)
    a = VAR + TAU * TAU * hn2
    i = knee_current(*h, VAR, REL, TAU, kappa)
    assert (REL * i) ** 2 * hn2 == pytest.approx(kappa * a, rel=1e-12)
    s = pulse_weight(i, a, REL * REL * hn2)
    assert s / i ** 2 == pytest.approx(1.0 / ((1.0 + kappa) * a), rel=1e-12)
    # far less than that per joule well below the knee? no: more, towards 1 / a
    assert pulse_weight(0.01 * i, a, REL * REL * hn2) / (0.01 * i) ** 2 > 0.99 / a


def test_the_knee_falls_as_the_field_grows():
    """``I_knee ~ 1 / |h|`` where the noise dominates ``a`` (no current error): a coil ten times
    nearer in field has a knee ten times lower."""
    i1 = knee_current(1e-6, 0.0, 0.0, VAR, REL, 0.0, 1.0)
    i10 = knee_current(10e-6, 0.0, 0.0, VAR, REL, 0.0, 1.0)
    assert i1 == pytest.approx(math.sqrt(VAR) / (REL * 1e-6))
    assert i1 / i10 == pytest.approx(10.0)


def test_cap_lowers_only_limits_above_the_knee_and_is_off_at_zero():
    h = np.array([[1e-6, 0.0, 0.0], [0.0, 20e-6, 0.0], [0.0, 0.0, 0.0]])
    knee0 = knee_current(1e-6, 0.0, 0.0, VAR, REL, TAU, 1.0)          # ~0.67 A
    knee1 = knee_current(0.0, 20e-6, 0.0, VAR, REL, TAU, 1.0)
    lim = np.array([0.5, 1.5, 1.5])
    cap_at_knee(lim, h, VAR, REL, TAU, 1.0)
    assert knee0 > 0.5 and lim[0] == 0.5                              # below its knee: kept
    assert lim[1] == knee1 < 1.5                                      # above: lowered to it
    assert lim[2] == 1.5                                              # no field: no knee
    lim = np.array([0.5, 1.5, 1.5])
    cap_at_knee(lim, h, VAR, REL, TAU, 0.0)
    assert lim.tolist() == [0.5, 1.5, 1.5]
    assert knee_current(1e-6, 0, 0, VAR, 0.0, TAU, 1.0) == math.inf    # no model error: no knee


@pytest.mark.parametrize("bad", [-0.1, float("nan"), 101.0])
def test_the_key_is_refused_out_of_range(bad):
    from coiltrack.firmware.config import ConfigError, FirmwareConfig

    with pytest.raises(ConfigError, match="saturation_knee"):
        FirmwareConfig().with_keys(saturation_knee=bad).validate()
