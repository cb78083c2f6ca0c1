"""``coiltrack bench`` with timed faults scores each fault's recovery against the same run without
them (``tools.bench.recovery``): the command runs that no-fault run itself, with the link faults
kept and the timed ones left out, on the same scenario, seed and duration."""
import json

from coiltrack.tools.bench import runner
from coiltrack.tools.cli import main


def test_bench_runs_the_no_fault_reference_for_timed_faults(tmp_path, monkeypatch):
    """static, 2 s, a magnet on the board at 0.5-1 s beside a 1 % frame drop: two runs, the
    second with the drop and without the magnet; the report says its recovery was held against
    the no-fault run. Without a timed fault (the drop alone) there is one run and no recovery to
    score. Catches the reference run left out, or run with the fault it is the reference for."""
    calls = []
    real = runner.run_inproc

    def spy(sc, seed, duration_s, faults=None, **kw):
        calls.append((sc.name, seed, duration_s, faults))
        return real(sc, seed, duration_s, faults=faults, **kw)

    monkeypatch.setattr(runner, "run_inproc", spy)
    out = tmp_path / "r.json"
    rc = main(["bench", "--scenario", "static", "--seed", "3", "--duration", "2", "--quiet",
               "--faults", "drop=0.01,sat=0.5s-1s", "--json", str(out)])
    assert rc == 0
    assert [(n, s, d) for n, s, d, _ in calls] == [("static", 3, 2.0)] * 2
    assert [f.kind for f in calls[0][3].timed] == ["sat"] and calls[1][3].timed == []
    assert calls[1][3].link.drop == calls[0][3].link.drop == 0.01
    rep = json.loads(out.read_text())
    assert rep["recovery_reference"] == "no-fault run" and list(rep["fault_recovery_s"]) == ["sat=sensor:@0.5s-1s"]
    calls.clear()
    assert main(["bench", "--scenario", "static", "--seed", "3", "--duration", "2", "--quiet",
                 "--faults", "drop=0.01", "--json", str(out)]) == 0
    assert len(calls) == 1 and "recovery_reference" not in json.loads(out.read_text())
