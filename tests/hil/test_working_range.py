"""A solution or a fused pose outside the working volume is not a pose.

A diverged fused state warm-starts the solve far away and the solve follows it (a body-worn run
without eq 6.8 sent positions of 1e24 m flagged valid). With ``working_range_m`` below the sensor's
distance every estimate is outside: nothing may be sent as valid."""
from __future__ import annotations

from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID

from .conftest import run_bench


def test_nothing_beyond_the_working_range_is_valid():
    """Catches a missing range check on the magnetic solutions or on the fused poses (either would
    leave valid poses), and a check that is always false (no valid pose with the default range)."""
    ok = run_bench("roetenberg-fusion", seed=2, duration_s=4.0)
    st = [rp["msg"].status for rp in ok.bench.recorder.poses]
    assert any(s & POSE_VALID and s & POSE_FUSED for s in st) and any(s & POSE_VALID and not s & POSE_FUSED for s in st)
    run = run_bench("roetenberg-fusion", seed=2, duration_s=4.0, cfg={"working_range_m": 0.05})
    poses = run.bench.recorder.poses
    assert poses and not any(rp["msg"].status & POSE_VALID for rp in poses)
    assert run.fw.status()["solutions_out_of_range"] >= 3
