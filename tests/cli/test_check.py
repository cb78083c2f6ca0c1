"""``coiltrack check``, the robustness sweep: a short slice of it on real runs (the scenario and
seed that used to end in a traceback among them), and its bookkeeping on runs that raise or are
stopped (monkeypatched runs: no bench)."""
from __future__ import annotations

import json
import signal

import pytest

from coiltrack.tools.bench import check
from coiltrack.tools.cli import main
from coiltrack.tools.stopping import Interrupted


def test_a_slice_of_the_sweep_runs_to_the_end(tmp_path, capsys):
    """3 scenarios x 2 seeds, 0.6 s each: roetenberg-walking-leg seed 4 raised EncodeError on
    IMU_SAMPLE (the source module stamped a sample before the master's zero), the source-IMU
    fusion and the static bench. No exception, every run's poses counted."""
    out = tmp_path / "check.json"
    rc = main(["check", "--scenarios", "roetenberg-walking-leg,roetenberg-fusion-srcimu,static", "--seeds", "4-5",
               "--duration", "0.6", "--json", str(out), "--quiet"])
    doc = json.loads(out.read_text())
    assert rc == 0, capsys.readouterr().out
    s = doc["summary"]
    assert s["runs"] == 6 and s["exceptions"] == 0 and s["scenarios"] == 3
    assert [(r["scenario"], r["seed"]) for r in doc["runs"]] == [
        (n, k) for n in ("roetenberg-fusion-srcimu", "roetenberg-walking-leg", "static") for k in (4, 5)]
    assert all(r["exception"] is None and r["poses"] is not None for r in doc["runs"])
    assert not doc["interrupted"]


def _fake_runs(monkeypatch, fail=(), stop_at=None):
    """check_run on a stub bench: ``fail`` (scenario, seed) raise inside hil/, ``stop_at`` is
    interrupted by SIGINT."""
    from coiltrack.tools.bench import runner

    def run_inproc(sc, seed, duration_s, faults=None):
        if (sc.name, seed) == stop_at:
            raise Interrupted(signal.SIGINT)
        if (sc.name, seed) in fail:
            from coiltrack.hil import imu_delta
            imu_delta.DeltaIntegrator(0, 0.01)        # raises ValueError inside hil/
        return {"poses": 10, "poses_invalid": 2, "faults_unreported": []}

    monkeypatch.setattr(runner, "run_inproc", run_inproc)


def test_an_exception_is_counted_with_its_scenario_seed_and_place(tmp_path, monkeypatch, capsys):
    _fake_runs(monkeypatch, fail={("static", 2)})
    out = tmp_path / "c.json"
    rc = main(["check", "--scenarios", "static", "--seeds", "1-3", "--duration", "1", "--json", str(out)])
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert rc == 1
    bad = [r for r in doc["runs"] if r["exception"]]
    assert [(r["scenario"], r["seed"]) for r in bad] == [("static", 2)]
    assert bad[0]["exception"].startswith("ValueError: a delta interval")
    assert bad[0]["side"] == "bench" and bad[0]["where"].startswith("hil/imu_delta.py:")
    assert bad[0]["origin"] is None             # raised in the bench's own code
    assert doc["summary"]["exceptions"] == 1 and doc["summary"]["poses_invalid"] == 4
    assert "EXCEPTION static seed 2: ValueError" in text


def test_stopped_it_keeps_the_runs_finished(tmp_path, monkeypatch):
    """SIGINT during the third run: the two finished are written, marked interrupted, exit 130."""
    _fake_runs(monkeypatch, stop_at=("static", 3))
    out = tmp_path / "c.json"
    rc = main(["check", "--scenarios", "static", "--seeds", "1-5", "--duration", "1", "--json", str(out),
               "--quiet"])
    doc = json.loads(out.read_text())
    assert rc == 130 and doc["interrupted"]
    assert [r["seed"] for r in doc["runs"]] == [1, 2]


@pytest.mark.parametrize("argv, word", [
    (["--scenarios", "nosuch-*"], "--scenarios"), (["--seeds", "5-1"], "--seeds"),
    (["--faults", "sat=bogus"], "--faults"), (["--duration", "0"], "--duration")])
def test_bad_arguments_are_refused_before_any_run(argv, word, capsys, monkeypatch):
    _fake_runs(monkeypatch)
    with pytest.raises(SystemExit) as e:
        rc = main(["check", "--scenarios", "static", *argv])
        raise SystemExit(rc)
    assert e.value.code == 2
    assert word in capsys.readouterr().err


def test_select_and_one_fault():
    names = ["a-x", "a-y", "b"]
    assert check.select("a-*", names) == ["a-x", "a-y"]
    assert check.select("b,a-y", names) == ["a-y", "b"]
    with pytest.raises(ValueError, match="'c'"):
        check.select("c", names)
    kinds = {check.one_fault(s, 5.0, 3).split("=")[0] for s in range(8)}
    assert kinds == {"sat", "node_off", "open_circuit", "short", "overheat", "sag", "metal"}
    assert check.one_fault(3, 5.0, 3) == "open_circuit=0@1.500s-2.500s"
    assert check.one_fault(2, 5.0, 3) == "node_off=driver@1.500s-4.500s"      # the driver's 2.5 s timeout
