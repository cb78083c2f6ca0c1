"""The policy-against-floor comparison (``tools/analyses/adaptive_gap.py``): its bookkeeping on a
hand-made schedule of two windows and two coils, checked against sums done by hand."""
import types

import numpy as np
import pytest

from coiltrack.tools.analyses import adaptive_gap as ag


def _pulses(rows):
    dt = [("t", "i8"), ("coil", "i4"), ("current", "f8"), ("length", "i8"), ("who", "U12"), ("reached", "?"),
          ("target", "i4")]
    return np.array(rows, dtype=dt)


def test_energy_split_by_phase_coil_and_goal():
    """Windows of 0.6 s; unit ``I0^2 T0`` = 0.05 A^2 s per coil and window, so the normaliser is
    2 x 2 x 0.05 = 0.2. Window 0 has one warm-up pulse (1 A, 50 ms: 0.05), window 1 two policy pulses
    (coil 0 at 0.5 A for 40 ms: 0.01, reached; coil 1 at 1 A for 40 ms: 0.04, unreached). The floor spends
    0.02 per coil-window. Policy 0.1 / 0.2 = 0.5, floor 0.08 / 0.2 = 0.4; the warm-up window's gap
    (0.05 - 0.04) / 0.2 = 0.05, the rest's (0.05 - 0.04) / 0.2 = 0.05, coil 1's after it 0.02 / 0.2 = 0.1."""
    model = types.SimpleNamespace(x0=np.ones((2, 2)), D=0.6, ref_energy=0.05, p=np.array([[0.2, 0, 0], [0.3, 0, 0]]))
    kinds = types.SimpleNamespace(slot=np.array([0.08]), T=np.array([0.04]))
    detail = {"energy": np.full((2, 2), 0.02), "time": np.full((2, 2), 0.16), "kind": np.zeros((2, 2), int),
              "current": np.full((2, 2), 0.7)}
    pulses = _pulses([(100_000, 0, 1.0, 50_000, ag.WARM, True, -1), (700_000, 0, 0.5, 40_000, ag.OWN, True, 0),
                      (900_000, 1, 1.0, 40_000, ag.OWN, False, 3)])
    res = ag.compare(model, kinds, {"detail": detail, "converged": True}, pulses, 1.2)
    assert res["policy_fraction"] == pytest.approx(0.5) and res["floor_fraction"] == pytest.approx(0.4)
    assert res["warmup_windows"] == 1
    g = res["gap"]
    assert g["warmup"] == pytest.approx(0.05) and g["after"] == pytest.approx(0.05)
    assert g["coils_after"] == pytest.approx([-0.05, 0.1])
    assert g["reached"] == pytest.approx(0.05) and g["unreached"] == pytest.approx(0.2)
    assert res["policy_after"]["pulses_per_s"] == pytest.approx(2 / 0.6)
    assert res["floor_after"]["pulses_per_s"] == pytest.approx(4 / 0.6)        # 0.16 s / 0.08 s per coil
    assert res["policy_after"]["current_rms_a"] == pytest.approx(np.sqrt((0.01 * 0.25 + 0.04 * 1.0) / 0.05))
    split = res["policy_split"]
    assert split["position/reached/far"][0] == 1 and split["orientation/unreached/far"][1] == pytest.approx(0.2)
