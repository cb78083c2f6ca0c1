"""End to end: the roetenberg-fusion scenario (thesis Table 6.1 bench test
with IMU fusion), its report keys and targets, frame logs, replay,
``coiltrack perf`` and ``coiltrack smooth``."""
import json

import pytest

from coiltrack.tools import scenarios
from coiltrack.tools.cli import main as cli_main
from coiltrack.tools.bench.framelog import read_log, replay
from coiltrack.tools.bench.runner import run_inproc


@pytest.fixture(scope="module")
def fusion_run(tmp_path_factory):
    log = tmp_path_factory.mktemp("fusion") / "run.log"
    rep = run_inproc(scenarios.get("roetenberg-fusion"), seed=1, duration_s=60.0, log_path=log)
    return rep, log


def test_fused_beats_magnetic_only_by_half(fusion_run):
    rep, _ = fusion_run
    for key in ("position_rms_mm", "orientation_rms_deg", "magnetic_position_rms_mm",
                "magnetic_orientation_rms_deg", "fused_to_magnetic_position", "magnetic_by_range", "fusion"):
        assert key in rep
    assert rep["position_rms_mm"] <= 0.5 * rep["magnetic_position_rms_mm"]
    assert rep["orientation_rms_deg"] <= 1.5
    assert rep["pose_rate_hz"] > 110                     # a pose per IMU sample (120 Hz)
    assert rep["magnetic_poses"] >= 95
    f = rep["fusion"]
    assert f["fusion_updates"] >= 90 and f["fusion_reinits"] == 0 and f["fusion_output_dropped"] == 0
    # closest band: the compensated fusion is better than the magnetic solutions
    near = rep["by_range"]["10-30cm"]
    assert near["position_rms_mm"] < near["magnetic_position_rms_mm"]


def test_log_replays_to_the_same_firmware_outputs(fusion_run):
    rep, log = fusion_run
    header, reads = read_log(log)
    assert header["scenario"] == "roetenberg-fusion" and header["config"]["fusion"]["measurement_model"] == 3
    from coiltrack.firmware.loop import Firmware

    fw = replay(Firmware, header, reads)
    st = fw.status()
    assert st["fused_poses"] == rep["fusion"]["fused_poses"]
    assert st["fusion_updates"] == rep["fusion"]["fusion_updates"]


def test_perf_command_reports_the_figures(fusion_run, tmp_path, capsys):
    _, log = fusion_run
    out = tmp_path / "perf.json"
    assert cli_main(["perf", "--log", str(log), "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    for key in ("tick_us_median", "tick_us_p99", "tick_us_p999", "tick_us_max", "tick_cpu_us_max", "allocs_per_tick",
                "state_bytes", "max_field_evals_per_tick",
                "filterpy_step_us", "fused_step_us", "fused_tick_us_median", "phases_us"):
        assert key in r
    assert set(r["phases_us"]) == {"receive", "measure", "track", "actuate", "supervise", "transmit"}
    assert r["allocs_per_tick"] == 0 and r["ticks"] > 50_000
    assert 50_000 < r["state_bytes"] < 2_000_000
    assert "fused tick" in capsys.readouterr().out


def test_smooth_command_improves_on_the_forward_filter(fusion_run, tmp_path):
    _, log = fusion_run
    summary = tmp_path / "smooth.json"
    poses = tmp_path / "poses.jsonl"
    assert cli_main(["smooth", str(log), "--json", str(summary), "--out", str(poses)]) == 0
    s = json.loads(summary.read_text())
    assert s["smoothed_position_rms_mm"] < 0.7 * s["forward_position_rms_mm"]
    assert s["smoothed_orientation_rms_deg"] < s["forward_orientation_rms_deg"]
    first = json.loads(poses.read_text().splitlines()[0])
    assert set(first) == {"node", "t_us", "p", "q", "sigma_p", "sigma_rot"}


def test_bad_log_is_refused(tmp_path, capsys):
    bad = tmp_path / "bad.log"
    bad.write_text('{"format": "something else"}\n')
    assert cli_main(["perf", "--log", str(bad)]) == 2
    assert cli_main(["smooth", str(bad)]) == 2
