"""SIGINT and SIGTERM stop a run cleanly: its children go, no temporary file is
left, and the report of what was done is written marked interrupted. The
subprocess tests wait for conditions (a child exists, bytes arrive), never for
a fixed time, and bound each wait generously."""
from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys

import pytest

from coiltrack.tools.bench import runner
from coiltrack.tools.cli import main
from coiltrack.tools.bench.links import GuardedPort
from coiltrack.tools.bench.realtime import firmware_loop
from coiltrack.tools.stopping import EXIT_PEER_SILENT, PeerSilent, Stopped

WAIT_S = 20.0
COILTRACK = [sys.executable, "-m", "coiltrack.tools.cli"]


def _poll(cond, timeout_s: float = WAIT_S, step_s: float = 0.05):
    """Wait until ``cond()`` is truthy (returned) or fail after ``timeout_s``."""
    import time

    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(step_s)
    pytest.fail("condition not reached")


def _children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as fh:
            return [int(x) for x in fh.read().split()]
    except OSError:
        return []


def _cpu_s(pid: int) -> float:
    """CPU time (user + system, s) a process has used: how far it got, whatever the machine's load."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            f = fh.read().split(") ")[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(") ")[1][0] == "Z"      # a zombie has finished
    except OSError:
        return True


class SimClock:
    def __init__(self):
        self.t = 0

    def now(self) -> int:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += max(1, int(s * 1e6))


class SilentPort:
    def read(self) -> bytes:
        return b""

    def write(self, data: bytes) -> None:
        pass


class CountingFirmware:
    def __init__(self, port):
        self.port = port
        self.ticks = 0

    def tick(self, t: int) -> None:
        self.port.read()
        self.ticks += 1


def test_a_silent_peer_stops_the_firmware_loop_with_its_statistics():
    clock = SimClock()
    fw = CountingFirmware(GuardedPort(SilentPort(), clock, silence_s=0.5))
    with pytest.raises(PeerSilent) as e:
        firmware_loop(fw, clock, 10_000_000, 1000, spin_us=0)
    assert e.value.exit_code == EXIT_PEER_SILENT and "0.5 s" in e.value.reason
    assert 500 <= fw.ticks <= 502 and e.value.partial["ticks"] == fw.ticks


def test_a_signal_before_the_first_tick_still_carries_the_statistics():
    """A signal that lands while the loop reads its first clock value (the loop's set-up, before
    any tick) must still hand over the timing keys, with zero ticks: the command's report of a
    run stopped at once has the same shape as that of a long one."""
    from coiltrack.tools.stopping import Interrupted

    class StoppedClock(SimClock):
        def now(self):
            raise Interrupted(signal.SIGTERM)

    with pytest.raises(Interrupted) as e:
        firmware_loop(CountingFirmware(SilentPort()), StoppedClock(), 10_000, 1000, spin_us=0)
    part = e.value.partial
    assert part["ticks"] == 0 and part["tick_us"] == 1000 and part["deadline_misses"] == 0
    assert part["tick_exec_us_max"] is None


def test_bytes_keep_the_peer_alive_and_zero_waits_forever():
    clock = SimClock()

    class Chatty(SilentPort):
        def read(self):
            return b"x" if clock.t % 400_000 < 1000 else b""

    fw = CountingFirmware(GuardedPort(Chatty(), clock, silence_s=0.5))
    assert firmware_loop(fw, clock, 3_000_000, 1000, spin_us=0)["ticks"] == 3000
    fw = CountingFirmware(GuardedPort(SilentPort(), clock, silence_s=0.0))
    clock.t = 0
    assert firmware_loop(fw, clock, 3_000_000, 1000, spin_us=0)["ticks"] == 3000


def test_sigterm_mid_run_writes_the_partial_report_and_log(tmp_path, monkeypatch):
    """In-process bench: the signal arrives at 2 s of simulated time."""
    real_update = runner.Progress.update

    def update(self, sim_s, poses, extra=""):
        if sim_s >= 2.0:
            os.kill(os.getpid(), signal.SIGTERM)
        real_update(self, sim_s, poses, extra)

    monkeypatch.setattr(runner.Progress, "update", update)
    out, log = tmp_path / "r.json", tmp_path / "run.log"
    assert main(["bench", "--scenario", "static", "--duration", "20", "--quiet", "--json", str(out),
                 "--log", str(log)]) == 128 + signal.SIGTERM
    rep = json.loads(out.read_text())
    assert rep["interrupted"] is True and rep["stopped_by"] == "SIGTERM"
    assert 2.0 <= rep["duration_s"] <= 2.1 and rep["poses"] >= 2
    from coiltrack.tools.bench.framelog import read_log

    header, reads = read_log(log)
    assert header["duration_s"] == rep["duration_s"] and reads


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and PR_SET_PDEATHSIG")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_a_stopped_pty_bench_leaves_no_process_and_no_file(sig, tmp_path):
    out = tmp_path / "r.json"
    env = dict(os.environ, TMPDIR=str(tmp_path))
    parent = subprocess.Popen(COILTRACK + ["bench", "--transport", "pty", "--scenario", "static",
                                           "--duration", "60", "--quiet", "--json", str(out)],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        child = _poll(lambda: _children(parent.pid))[0]
        parent.send_signal(sig)
        code = parent.wait(timeout=WAIT_S)
    finally:
        if parent.poll() is None:
            parent.kill()
    _poll(lambda: _gone(child))
    assert not [p for p in os.listdir(tmp_path) if p.startswith("coiltrack-")]
    if sig == signal.SIGTERM:
        assert code == 128 + signal.SIGTERM, parent.stderr.read().decode()
        rep = json.loads(out.read_text())
        assert rep["interrupted"] is True and rep["stopped_by"] == "SIGTERM"
        # the child stops with its statistics, or dies of the signal if it came during its start-up
        assert rep["firmware_exit_code"] in (128 + signal.SIGTERM, -signal.SIGTERM)


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals")
def test_sigterm_stops_the_firmware_with_its_statistics(tmp_path):
    from coiltrack.tools.bench.links import make_raw_pty

    master, slave, name = make_raw_pty()
    stats = tmp_path / "fw.json"
    fw = subprocess.Popen(COILTRACK + ["firmware", "--port", name, "--peer-timeout", "0",
                                       "--stats-json", str(stats)], stderr=subprocess.PIPE)
    try:
        # running once its first frames (TIME_SYNC, HEARTBEAT) arrive
        assert select.select([master], [], [], WAIT_S)[0]
        fw.send_signal(signal.SIGTERM)
        assert fw.wait(timeout=WAIT_S) == 128 + signal.SIGTERM
    finally:
        if fw.poll() is None:
            fw.kill()
        os.close(master)
        os.close(slave)
    rep = json.loads(stats.read_text())
    assert rep["interrupted"] is True and rep["stopped_by"] == "SIGTERM"
    # the timing statistics of the ticks run (the signal may come within the first one)
    assert {"ticks", "tick_us", "deadline_misses", "tick_exec_us_max"} <= set(rep["timing"])
    assert rep["timing"]["tick_us"] == 1000 and "ticks" in rep["status"]


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals")
def test_sigint_stops_the_emulator_with_its_report(tmp_path):
    out = tmp_path / "emu.json"
    emu = subprocess.Popen(COILTRACK + ["emulator", "--create-pty", "--scenario", "static", "--duration", "60",
                                        "--json", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert emu.stdout.readline().startswith(b"/dev/")      # the pty's path: the loop starts
        emu.send_signal(signal.SIGINT)
        assert emu.wait(timeout=WAIT_S) == 128 + signal.SIGINT
    finally:
        if emu.poll() is None:
            emu.kill()
    text = out.read_text()
    rep = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the report"))
    assert rep["interrupted"] is True and rep["stopped_by"] == "SIGINT"
    assert rep["poses"] == 0 and rep["position_rms_mm"] is None     # no firmware: no pose, null RMS


def test_stopped_carries_its_exit_code():
    from coiltrack.tools.stopping import Interrupted

    assert Interrupted(signal.SIGINT).exit_code == 130 and isinstance(Interrupted(2), Stopped)


def _read_until(stream, pattern: bytes, timeout_s: float = 4 * WAIT_S) -> bytes:
    """Bytes of ``stream`` (a pipe) up to and with the first ``pattern`` match (a regex); fails
    after ``timeout_s`` or at the end of the stream. A hang guard, not a timing."""
    import re
    import time

    fd, got = stream.fileno(), b""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if select.select([fd], [], [], 0.5)[0]:
            chunk = os.read(fd, 4096)
            if not chunk:
                break
            got += chunk
            if re.search(pattern, got):
                return got
    pytest.fail(f"no {pattern!r} in {got[-500:]!r}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_sweep_writes_its_finished_runs(sig, tmp_path):
    """A real sweep (one worker process) stopped by Ctrl-C or SIGTERM once its progress bar
    shows two finished runs: it exits 130 (SIGINT) or 143 (SIGTERM) and its JSON and CSV hold
    the runs finished, at least the two seen and fewer than all."""
    import csv

    out, table = tmp_path / "sw.json", tmp_path / "sw.csv"
    seeds = 40
    proc = subprocess.Popen(COILTRACK + ["sweep", "--scenario", "static", "--seeds", f"1-{seeds}", "--duration", "0.5",
                                         "--workers", "1", "--progress", "--json", str(out), "--csv", str(table)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path)
    try:
        _read_until(proc.stderr, rb"\] ([2-9]|\d\d+)/%d runs" % seeds)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=4 * WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + sig, stderr.decode()
    assert b"Traceback" not in stderr
    doc = json.loads(out.read_text())
    assert doc["interrupted"] is True and 2 <= len(doc["runs"]) < seeds
    assert doc["summary"][0]["runs"] == len(doc["runs"])
    rows = list(csv.DictReader(table.open()))
    assert sorted(int(r["seed"]) for r in rows) == sorted(r["seed"] for r in doc["runs"])
    assert f"{len(doc['runs'])} runs in".encode() in stdout


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_soak_writes_the_seeds_it_ran(sig, tmp_path, monkeypatch, capsys):
    """Three soak seeds of 2 s each, stopped in the middle of the second (its 12th memory sample
    of 24): the first seed's report whole, the second's to where it stopped, marked
    interrupted, in the JSON; exit 130 or 143."""
    from coiltrack.tools.bench import soak

    real, calls = soak.footprint, []

    def footprint(fw):
        calls.append(1)
        if len(calls) == soak.MEMORY_SAMPLES + 1 + 12:     # the first seed takes 25 samples (t = 0 .. end)
            os.kill(os.getpid(), sig)
        return real(fw)

    monkeypatch.setattr(soak, "footprint", footprint)
    out = tmp_path / "soak.json"
    assert main(["soak", "--scenario", "static", "--seeds", "1-3", "--duration", "2", "--json", str(out)]) == 128 + sig
    doc = json.loads(out.read_text())
    assert doc["interrupted"] is True and doc["stopped_by"] == signal.Signals(sig).name
    first, second = doc["runs"]
    assert first["seed"] == 1 and first["duration_s"] == 2.0 and "interrupted" not in first
    assert second["seed"] == 2 and second["interrupted"] is True and 0.5 < second["duration_s"] < 2.0
    assert [r["seed"] for r in doc["summary"]] == [1, 2]
    assert "stopped by" in capsys.readouterr().err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_calibration_stopped_while_fitting_keeps_its_recording(sig, tmp_path, monkeypatch, capsys):
    """``calibrate --record`` stopped by a signal during the fit (the long part): exit 130 or
    143, no calibration file, and the recording kept beside it, equal to the one recorded."""
    import numpy as np

    from coiltrack.hil.calibrun import load_recording
    from coiltrack.tools.calibration import fits as calibrate

    real = calibrate.RECORDERS["grid"]
    recorded = {}

    def fit(rec, cfg):
        os.kill(os.getpid(), sig)              # the handler raises in this thread before kill returns
        pytest.fail("the signal did not stop the fit")

    def record(unit, seed, grid):
        recorded.update(real(unit, seed, grid))
        return recorded

    monkeypatch.setitem(calibrate.METHODS, "grid", fit)
    monkeypatch.setitem(calibrate.RECORDERS, "grid", record)
    out = tmp_path / "cal.toml"
    assert main(["calibrate", "--method", "grid", "--record", "--grid", "2", "--out", str(out)]) == 128 + sig
    assert not out.exists()
    kept = load_recording(tmp_path / "cal.recording.npz")
    assert kept["kind"] == "grid" and kept["meta"] == recorded["meta"]
    for k in ("p_true", "R_true", "b_on", "b_off"):
        np.testing.assert_array_equal(kept[k], recorded[k])
    assert f"--input {tmp_path / 'cal.recording.npz'}" in capsys.readouterr().err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_bench_writes_its_pose_table(sig, tmp_path, monkeypatch):
    """A bench stopped at 1 s of simulated time writes the poses it had (read back strictly)
    and its report, and exits 130 or 143."""
    from coiltrack.tools.outputs.posecsv import read_csv

    real_update = runner.Progress.update

    def update(self, sim_s, poses, extra=""):
        if sim_s >= 1.0:
            os.kill(os.getpid(), sig)
        real_update(self, sim_s, poses, extra)

    monkeypatch.setattr(runner.Progress, "update", update)
    out, poses = tmp_path / "r.json", tmp_path / "poses.csv"
    assert main(["bench", "--scenario", "static", "--duration", "20", "--quiet", "--json", str(out),
                 "--poses", str(poses)]) == 128 + sig
    rep = json.loads(out.read_text())
    assert rep["interrupted"] is True and rep["stopped_by"] == signal.Signals(sig).name
    table = read_csv(poses)
    assert len(table["t_us"]) == rep["poses"] >= 1 and table["t_s"].max() <= rep["duration_s"]


def test_a_parallel_soak_stopped_reports_its_seeds_under_way_and_leaves_no_worker(tmp_path):
    """``soak --workers 2`` of three 10-minute seeds, SIGINT once both workers exist: exit 130,
    the JSON written (marked interrupted) with the reports of the seeds under way, each to
    where it stopped, and no worker left behind (the parent does not wait for a seed's end)."""
    out = tmp_path / "soak.json"
    proc = subprocess.Popen(COILTRACK + ["soak", "--scenario", "static", "--seeds", "1-3", "--duration", "600",
                                         "--workers", "2", "--json", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        # the resource tracker and the two workers; then the seeds' first ticks: both workers past their
        # imports and set-up (about 2 s of CPU), counted in CPU time so a loaded machine only waits longer
        kids = _poll(lambda: (lambda k: k if len(k) >= 3 else None)(_children(proc.pid)), timeout_s=4 * WAIT_S)
        _poll(lambda: sum(1 for k in _children(proc.pid) if _cpu_s(k) >= 4.0) >= 2, timeout_s=8 * WAIT_S)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=4 * WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr.decode()
    assert b"Traceback" not in stderr
    for k in kids:
        _poll(lambda: _gone(k))
    doc = json.loads(out.read_text())
    assert doc["interrupted"] is True and doc["stopped_by"] == "SIGINT"
    for r in doc["runs"]:                                 # a seed stopped mid-way: its report to where it stopped
        assert r["interrupted"] is True and 0 < r["duration_s"] < 600 and r["seed"] in (1, 2, 3)
    assert [r["seed"] for r in doc["summary"]] == [r["seed"] for r in doc["runs"]]
