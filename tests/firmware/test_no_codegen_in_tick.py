"""No tick generates code: the straight-line linear algebra (``linalg._generated``: Jacobi
eigen-solvers, Cholesky inverses and solves per size) is made when the firmware is composed.

A size first asked for inside a tick builds its Python source and compiles it there (2-3 ms:
multi16's first acquisition missed its deadline for it), so every caller takes its function at
start-up (``jacobi_eigh_of``, ``spd_inverse``, ``damped_spd_solve``). The check: after the
firmware is built, a run through its first acquisitions, solves and covariance reports calls the
generator not once (a caller that calls ``jacobi_eigh(a, n, ...)`` on the tick fails it)."""
import pytest

from coiltrack.firmware import linalg
from coiltrack.firmware.loop import Firmware
from coiltrack.tools import scenarios
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup


@pytest.mark.parametrize("name", ["roetenberg-bench", "multi16"])
def test_no_tick_generates_code(name, monkeypatch):
    sc = scenarios.get(name)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, 2.0, emu_end)
    fw = Firmware(sc.firmware_config(), fw_end)
    calls = []
    real = linalg._generated
    monkeypatch.setattr(linalg, "_generated", lambda kind, n, source: calls.append((kind, n)) or real(kind, n, source))
    for t in range(0, 1_500_001, 1000):
        bench.emulator.step(t)
        fw.tick(t)
    assert fw.poses > 0                  # the run got through acquisition to reported poses
    assert calls == [], f"code generated inside a tick: {calls}"
