"""coiltrack sweep: the same runs on a local process pool and on a Dask cluster, summary
statistics against numpy, outputs, and bad arguments refused before any work.

One small sweep (scenario static, 3 seeds x 2 pulse lengths, 2.5 s simulated) per executor;
the Dask LocalCluster (2 worker processes on 127.0.0.1) is started once for the module."""
import csv
import json
import math
import os
import signal
import sys

import numpy as np
import pytest

from coiltrack.tools.bench import sweep
from coiltrack.tools.cli import main

SWEEP = ["sweep", "--scenario", "static", "--seeds", "1-3", "--duration", "2.5", "--set", "pulse_us=40000,60000"]


@pytest.fixture(scope="module")
def local_doc(tmp_path_factory):
    d = tmp_path_factory.mktemp("sweep")
    assert main([*SWEEP, "--workers", "2", "--json", str(d / "runs.json"), "--csv", str(d / "runs.csv"),
                 "--plot", str(d / "runs.png")]) == 0
    return d, json.loads((d / "runs.json").read_text())


@pytest.fixture(scope="module")
def dask_address():
    pytest.importorskip("distributed")
    with sweep.dask_client(2, None) as client:   # the LocalCluster the command starts without --scheduler
        yield client.scheduler.address


def test_dask_cluster_gives_the_local_pool_numbers(local_doc, dask_address, tmp_path):
    _, local = local_doc
    out = tmp_path / "dask.json"
    assert main([*SWEEP, "--executor", "dask", "--scheduler", dask_address, "--json", str(out)]) == 0
    dask = json.loads(out.read_text())
    assert dask["executor"] == "dask" and local["executor"] == "local"
    assert dask["runs"] == local["runs"] and dask["summary"] == local["summary"]   # exact, every figure


def test_runs_follow_their_seed_and_grid_point(local_doc):
    _, doc = local_doc
    runs = doc["runs"]
    assert [(r["params"]["pulse_us"], r["seed"]) for r in runs] == [(p, s) for p in (40000, 60000) for s in (1, 2, 3)]
    # the seed reaches the world: the three seeds of a grid point differ
    assert len({r["figures"]["position_rms_mm"] for r in runs[3:]}) == 3
    # the override reaches the firmware: coil energy I^2 R t per pulse scales with the pulse length
    for short, full in zip(runs[:3], runs[3:]):
        assert short["figures"]["coil_pulses"] == full["figures"]["coil_pulses"]
        assert short["figures"]["coil_energy_j"] / full["figures"]["coil_energy_j"] == pytest.approx(4 / 6, rel=1e-3)
    assert not any(k.startswith("tick_") or k in ("wall_s", "speedup") for r in runs for k in r["figures"])


def test_summary_matches_numpy_on_the_runs(local_doc):
    _, doc = local_doc
    assert [g["params"] for g in doc["summary"]] == [{"pulse_us": 40000}, {"pulse_us": 60000}]
    for g in doc["summary"]:
        rs = [r["figures"] for r in doc["runs"] if r["params"] == g["params"]]
        assert g["runs"] == len(rs) == 3
        for name in ("position_rms_mm", "orientation_rms_deg", "coil_energy_j"):   # errors: worst = max
            x = np.array([f[name] for f in rs if f[name] is not None], dtype=float)
            s = g["figures"][name]
            assert s["median"] == pytest.approx(np.median(x), rel=1e-12)
            assert s["p90"] == pytest.approx(np.percentile(x, 90), rel=1e-12)
            assert s["worst"] == pytest.approx(x.max(), rel=1e-12)
            assert s["missing"] == len(rs) - x.size
        poses = np.array([f["poses"] for f in rs], dtype=float)                   # more is better: worst = min
        assert g["figures"]["poses"]["p90"] == pytest.approx(np.percentile(poses, 10), rel=1e-12)
        assert g["figures"]["poses"]["worst"] == poses.min()


def test_stats_leave_out_missing_values_and_face_the_bad_side():
    s = sweep.stats("position_rms_mm", [1.0, None, math.nan, 4.0, 2.0])
    assert s == {"median": 2.0, "p90": pytest.approx(np.percentile([1, 2, 4], 90)), "worst": 4.0, "missing": 2}
    s = sweep.stats("poses", [5, 3, 4, 5])
    assert s["worst"] == 3 and s["p90"] == pytest.approx(np.percentile([5, 3, 4, 5], 10))
    assert sweep.stats("poses", [None])["median"] is None


def test_csv_has_one_row_per_run_and_plot_is_drawn(local_doc):
    d, doc = local_doc
    rows = list(csv.DictReader((d / "runs.csv").open()))
    assert len(rows) == len(doc["runs"]) == 6
    for row, run in zip(rows, doc["runs"]):
        assert int(row["pulse_us"]) == run["params"]["pulse_us"] and int(row["seed"]) == run["seed"]
        cell = row["position_rms_mm"]           # empty where a run had no valid pose (None in JSON)
        assert (float(cell) if cell else None) == run["figures"]["position_rms_mm"]
    import matplotlib.image as mpimg

    img = mpimg.imread(d / "runs.png")
    assert img.shape[0] >= 300 and img.shape[1] >= 800
    assert img[..., :3].std() > 0.05          # not blank


def test_parsers():
    assert sweep.parse_seeds("1-3,7") == [1, 2, 3, 7]
    assert sweep.parse_set("fusion.mag_sigma_t=1e-8,2e-8") == ("fusion.mag_sigma_t", [1e-8, 2e-8])
    assert [type(sweep.parse_value(v)) for v in ("3", "1.5", "true", "exact")] == [int, float, bool, str]
    assert sweep.override_dict([("fusion.a", 1), ("b", 2), ("fusion.c", 3)]) == {"fusion": {"a": 1, "c": 3}, "b": 2}
    assert sweep.grid([("a", [1, 2]), ("b", [3, 4])]) == [(("a", 1), ("b", 3)), (("a", 1), ("b", 4)),
                                                          (("a", 2), ("b", 3)), (("a", 2), ("b", 4))]


def test_progress_bar_eta_from_the_injected_clock():
    class Out(list):
        write = list.append

        def flush(self):
            pass

    now = [100.0]
    out = Out()
    bar = sweep.ProgressBar(8, True, out, clock=lambda: now[0], width=16)
    now[0] = 110.0
    bar.update(2)                               # 5 s a run: 6 more take 30 s
    assert out[-1] == "\r[####............] 2/8 runs  0:10 elapsed  ETA 0:30\033[K"
    quiet = Out()
    sweep.ProgressBar(8, False, quiet).update(3)
    assert quiet == []


BAD = [
    (["--seeds", "5-1"], "--seeds"), (["--seeds", "a"], "--seeds"), (["--seeds", "-3"], "--seeds"),
    (["--seeds", "1,1"], "--seeds"), (["--seeds", ""], "--seeds"), (["--seeds", "1-99999999999"], "--seeds"),
    (["--set", "no_such_key=1,2"], "no_such_key"), (["--set", "fusion.no_such_key=1"], "--set"),
    (["--set", "pulse_us=abc"], "pulse_us"), (["--set", "pulse_us="], "--set"), (["--set", "=3"], "--set"),
    (["--set", "pulse_us=1000000"], "pulse_us"), (["--set", "mag_sigma_t=nan"], "mag_sigma_t"),
    (["--set", "pulse_us=40000", "--set", "pulse_us=60000"], "--set"),
    (["--workers", "0"], "--workers"), (["--workers", "x"], "--workers"), (["--workers", "-2"], "--workers"),
    (["--workers", "5000"], "--workers"),
    (["--duration", "nan"], "--duration"), (["--duration", "inf"], "--duration"), (["--duration", "0"], "--duration"),
    (["--duration", "-1"], "--duration"), (["--duration", "1e9"], "--duration"),
    (["--scheduler", "tcp://127.0.0.1:9"], "--scheduler"),
    (["--executor", "dask", "--scheduler", "tcp://127.0.0.1:9", "--workers", "2"], "--workers"),
    (["--scenario", "nope"], "--scenario"),
    (["--json", "/nonexistent/dir/x.json"], "--json"), (["--csv", "/"], "--csv"),
]


@pytest.mark.parametrize("extra,named", BAD, ids=[" ".join(a) for a, _ in BAD])
def test_bad_arguments_are_refused_before_any_work(extra, named, monkeypatch, capsys):
    monkeypatch.setattr(sweep, "run_tasks", lambda *a, **k: pytest.fail("work started"))
    assert main(["sweep", "--scenario", "static", "--seeds", "1-2", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("coiltrack sweep: ") and "\n" not in err and named in err


@pytest.mark.parametrize("executor,module,extra", [("ray", "ray", "coiltrack[ray]"),
                                                   ("dask", "distributed", "coiltrack[sweep]")])
def test_missing_executor_names_its_extra(executor, module, extra, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, module, None)       # import fails as if not installed
    monkeypatch.setattr(sweep, "run_tasks", lambda *a, **k: pytest.fail("work started"))
    assert main(["sweep", "--scenario", "static", "--executor", executor]) == 2
    assert extra in capsys.readouterr().err


def _ctrl_c():
    raise KeyboardInterrupt


def _signal(sig):
    def send():
        os.kill(os.getpid(), sig)    # the handler raises in this thread before kill returns
        pytest.fail(f"{signal.Signals(sig).name} did not stop the sweep")
    return send


STOPS = [(_ctrl_c, 130), (_signal(signal.SIGINT), 130), (_signal(signal.SIGTERM), 143)]


@pytest.mark.parametrize("stop,code", STOPS, ids=["KeyboardInterrupt", "SIGINT", "SIGTERM"])
def test_interrupted_sweep_writes_the_runs_done(stop, code, local_doc, monkeypatch, tmp_path, capsys):
    """Stopped after one finished run, by Ctrl-C as Python raises it, by SIGINT as the command
    line turns it into ``Interrupted`` (the runs were lost before), or by SIGTERM: the run
    done is summarised and written to the JSON and the CSV, and the exit status is the
    exit-status table's (130 SIGINT, 143 SIGTERM)."""
    _, doc = local_doc

    def stopped(tasks, workers, scheduler):
        yield 1, doc["runs"][1]
        stop()

    monkeypatch.setitem(sweep.EXECUTORS, "local", stopped)
    out, table = tmp_path / "part.json", tmp_path / "part.csv"
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    assert main([*SWEEP, "--json", str(out), "--csv", str(table)]) == code
    assert {s: signal.getsignal(s) for s in before} == before
    part = json.loads(out.read_text())
    assert part["interrupted"] is True and part["runs"] == [doc["runs"][1]] and part["summary"][0]["runs"] == 1
    rows = list(csv.DictReader(table.open()))
    assert [(int(r["seed"]), int(r["pulse_us"])) for r in rows] == [(2, 40000)]
    assert float(rows[0]["position_rms_mm"]) == doc["runs"][1]["figures"]["position_rms_mm"]
    captured = capsys.readouterr()
    assert "1 runs in" in captured.out and "stopped by" in captured.err and "1 finished run of 6" in captured.err


@pytest.mark.parametrize("executor", ["local", "dask"])
def test_an_error_in_a_worker_names_its_run(executor, dask_address):
    bad = [sweep.Task("static", 4, 1.0, (("no_such_key", 1),))]   # refused by config_from_dict in the worker
    with pytest.raises(sweep.SweepError, match="run seed 4 no_such_key=1 failed: ConfigError"):
        sweep.run_tasks(bad, executor, workers=1 if executor == "local" else None,
                        scheduler=dask_address if executor == "dask" else None)


def test_failed_run_exits_1(monkeypatch, capsys):
    def broken(tasks, workers, scheduler):
        raise ValueError("worker lost")
        yield

    monkeypatch.setitem(sweep.EXECUTORS, "local", broken)
    assert main([*SWEEP]) == 1
    assert "worker lost" in capsys.readouterr().err


def test_gietler_experiment_same_on_dask_and_local(dask_address, tmp_path):
    """A measurement-level experiment (gietler-air, 2 seeds x 2 levels, 2 s) gives the same runs
    and levels table on the Dask cluster as on the local pool: catches an experiment whose
    runs depend on process state (a cache, a shared random generator)."""
    base = ["sweep", "--scenario", "gietler-air", "--seeds", "1-2", "--duration", "2", "--set", "noise.var=1e-2,1e-4"]
    docs = []
    for extra in (["--workers", "2"], ["--executor", "dask", "--scheduler", dask_address]):
        out = tmp_path / f"{len(docs)}.json"
        assert main([*base, *extra, "--json", str(out)]) == 0
        docs.append(json.loads(out.read_text()))
    assert docs[0]["runs"] == docs[1]["runs"] and docs[0]["levels"] == docs[1]["levels"]
