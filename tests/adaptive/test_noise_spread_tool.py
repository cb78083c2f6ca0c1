"""The analyses of the policy's run-to-run spread and of its orientation error's directions
(``tools/analyses/adaptive_noise_spread.py``, ``adaptive_orientation_axes.py``): their pure parts
against hand-computed figures and closed forms; bad arguments refused with status 2."""
import math

import numpy as np
import pytest

from coiltrack.tools.analyses import adaptive_noise_spread as ns
from coiltrack.tools.analyses import adaptive_orientation_axes as ax


def _run(seed, draw, fp, fo, ratios=None):
    f = {"fixed_position_rms_mm": fp, "fixed_orientation_rms_deg": fo, "fixed_coil_energy_j": 30.0}
    if ratios:
        f.update(energy_ratio=ratios[0], position_rms_ratio=ratios[1], orientation_rms_ratio=ratios[2])
    return {"seed": seed, "params": {"bench.noise_draw": draw} if draw else {}, "figures": f}


def test_spread_is_each_draws_rms_over_the_seeds_mean():
    """Seed 1 over draws 0, 1, 2 (orientation 0.2, 0.3, 0.4: mean 0.3, relative values 2/3, 1,
    4/3, sample std 1/3); the policy's ratios per draw and their std; draws read from the params
    (none: 0); a second sweep's run of the same seed and draw does not count twice."""
    a = {"scenario": ns.SCENARIO, "duration_s": 60.0,
         "runs": [_run(1, 0, 3.0, 0.2, (0.9, 1.0, 1.2)), _run(1, 1, 3.0, 0.3, (0.8, 1.0, 0.9))]}
    b = {"scenario": ns.SCENARIO, "duration_s": 60.0, "runs": [_run(1, 2, 3.0, 0.4), _run(1, 1, 9.0, 9.0)]}
    fixed, policy = ns.gather([a, b], 60.0)
    assert sorted(fixed) == [(1, 0), (1, 1), (1, 2)] and fixed[(1, 1)]["orientation_rms_deg"] == 0.3
    row, = ns.spread(fixed, policy, [1])
    assert row["draws"] == [0, 1, 2] and row["mean_ori"] == pytest.approx(0.3)
    assert row["sd_ori"] == pytest.approx(1 / 3, abs=1e-4) and row["sd_pos"] == 0.0
    assert row["orientation_rms_ratio"] == [1.2, 0.9]
    assert row["sd_orientation_rms_ratio"] == pytest.approx(math.sqrt(0.045), abs=1e-4)
    with pytest.raises(ValueError, match="schepers-adaptive"):
        ns.gather([{**a, "duration_s": 20.0}], 60.0)


def test_a_pulse_sees_no_rotation_about_its_own_field():
    """``[h]x^T [h]x``: the information of a rotation about ``h`` is 0, of one across it |h|^2
    (eq 11's orientation columns ``[h]x``); built by hand from the cross product."""
    rng = np.random.default_rng(4)
    for _ in range(5):
        h = rng.normal(size=3)
        K = np.cross(np.eye(3), h)             # rows e_i x h: (e_i x h) = -[h]x e_i
        np.testing.assert_allclose(ax._skew_info(h), K @ K.T, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(ax._skew_info(h) @ h, 0.0, atol=1e-12)
        v = np.cross(h, rng.normal(size=3))
        v /= np.linalg.norm(v)
        assert v @ ax._skew_info(h) @ v == pytest.approx(h @ h)


@pytest.mark.parametrize("mod,args", [(ns, ["--seeds", "x", "--json", "/tmp/x.json"]),
                                      (ns, ["--workers", "5", "--json", "/tmp/x.json"]),
                                      (ns, ["--with", "/nonexistent.json", "--json", "/tmp/x.json"]),
                                      (ax, ["--window-s", "0"])])
def test_bad_arguments_exit_2(mod, args, capsys):
    assert mod.main(args) == 2
    assert capsys.readouterr().err.startswith(mod.__name__.rsplit(".", 1)[1])
