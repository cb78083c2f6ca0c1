"""Shared inputs of the command-line tests: short runs on the simulated clock."""
from __future__ import annotations

import pytest

from coiltrack.tools import scenarios
from coiltrack.tools.runner import run_inproc


@pytest.fixture(scope="session")
def fusion_log(tmp_path_factory):
    """A 4 s frame log of roetenberg-fusion, seed 1 (enough for the fusion filter to start)."""
    path = tmp_path_factory.mktemp("logs") / "fusion.log"
    run_inproc(scenarios.get("roetenberg-fusion"), seed=1, duration_s=4.0, log_path=path)
    return path
