"""The extended measurement model (eq 32, sub-volume integrals from the bench's lattice solution)
against the base model (eq 1) on emulated runs with the object fixed to the emitters."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from coiltrack.tools.bench import gietler as G
from coiltrack.tools.scenarios.gietler import _split


@pytest.mark.parametrize("scenario, factor", [("gietler-ferro-dc", 0.2), ("gietler-copper", 0.5), ("gietler-ferro", 0.2)])
def test_compensation_cuts_the_error(scenario, factor):
    """Three seeds, 8 s, sigma^2 = 1e-4, a coarse bench lattice (5^3 cells) so the test is fast:
    the iterated EKF with the extended model has at most ``factor`` times the MSE of the same
    filter with the base model (a base run that diverges counts as 1 m^2), and never diverges.
    Catches compensation dipoles not rotated with the platform, placed at the wrong sub-volume
    centres, of the wrong sign, or a table from the wrong emitter."""
    spec, cfg = _split(scenario, (("noise.var", 1e-4),))
    spec = replace(spec, lattice_n=5, duration_s=8.0)
    ext, base = [], []
    for seed in (1, 2, 3):
        r = G.run(spec, cfg, seed, variants=(("", "extended", True), ("_base", "base", True)))
        assert r["diverged"] == 0
        ext.append(r["mse_m2"])
        base.append(1.0 if r["diverged_base"] else r["mse_m2_base"])
    assert np.mean(ext) <= factor * np.mean(base), (ext, base)
