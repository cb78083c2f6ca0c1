"""Every tracker's recorded run replayed through both cores gives the same poses (issue 30's
equivalence, tracker by tracker; the adaptive single coil's is
test_core_single_coil.py::test_a_replayed_adaptive_run_gives_the_same_poses_on_either_core).

Each case records a short seeded bench run once (the bytes the firmware read, tick by tick:
``tools.bench.framelog``) and replays it into a fresh firmware on the Python core and one on the
compiled core. Every POSE record each sends (node, time, status bits, quality, position,
quaternion, variances) is compared: the same number of poses, node, time, status and quality
equal, every floating-point field equal to 1e-12 of its column's largest magnitude, and bit for
bit where the operations are the same (the magnetic-only LM trackers; where the reference sums a
product through BLAS in another order, the fused trackers and AC, the last bits differ: 1e-13 of
a column at most observed). A wrong sign, a dropped term or a gate decided differently in either
core moves a pose far more, or changes a status bit or the count.

The trackers: the burst solver (magnetic only, LM), the loosely coupled fusion (burst solutions
into the ch. 6 filter with its delayed update and replay), the tightly coupled fusion (each pulse
window a measurement), AC frequency division with Raab's tracker, Raab's tracker on pulsed DC
acquiring from far off, sixteen sensors on one source, and a calibrated source and sensor with
the room's distortion map (the calibration file's ``[source]``, ``[sensor.N]`` and
``[distortion]``). Seeded; skips where the extension is not built."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

from coiltrack.firmware.loop import Firmware  # noqa: E402
from coiltrack.firmware.transmit import POSE_VALID  # noqa: E402
from coiltrack.tools import scenarios  # noqa: E402
from coiltrack.tools.bench.framelog import replay  # noqa: E402

#: columns of a pose row: node, t_us, status, quality (compared exactly), then the floats
EXACT = 4


def _record(name: str, seed: int, duration: float, cfg=None):
    """The frame log of a bench run of scenario ``name`` (its configuration, or ``cfg``), recorded
    on the compiled core (as ``coiltrack perf`` records)."""
    from coiltrack.tools.bench.runner import record_log

    sc = scenarios.get(name)
    return record_log(sc, seed, duration, (cfg or sc.firmware_config()).with_(core={"impl": "compiled"}))


def _poses(header, reads, impl: str, cfg_change=None) -> np.ndarray:
    """The POSE records a firmware on core ``impl`` sends when the log is replayed into it (its
    configuration changed by ``cfg_change``, a dict of sections, where given)."""
    rows = []

    def factory(cfg, port):
        fw = Firmware(cfg.with_(core={"impl": impl}, **(cfg_change or {})), port)
        assert fw.core == impl
        send = fw.tx.pose

        def pose(r):
            rows.append((r.node, r.t_us, r.status, r.quality, *r.p, *r.q, *r.var))
            send(r)
        fw.tx.pose = pose
        return fw

    replay(factory, header, reads)
    return np.array(rows, dtype=float).reshape(-1, EXACT + 13)


def _same_poses(header, reads, min_valid: int, nodes: int = 1, bitwise: bool = False) -> np.ndarray:
    """The Python core's poses, after checking the compiled core's are the same (``bitwise``: to
    the bit)."""
    a = _poses(header, reads, "python")
    b = _poses(header, reads, "compiled")
    assert a.shape == b.shape, (a.shape, b.shape)
    valid = (a[:, 2].astype(np.int64) & POSE_VALID) != 0
    assert valid.sum() >= min_valid, f"{valid.sum()} valid poses"
    assert len(set(a[valid, 0])) == nodes
    np.testing.assert_array_equal(b[:, :EXACT], a[:, :EXACT])
    for j in range(EXACT, a.shape[1]):
        scale = max(float(np.abs(a[:, j]).max()), 1e-300)
        np.testing.assert_allclose(b[:, j], a[:, j], rtol=0, atol=1e-12 * scale, err_msg=f"pose column {j}")
    if bitwise:
        np.testing.assert_array_equal(b, a)
    return a


# scenario, simulated seconds, valid poses at least, sensors, bit for bit: the LM trackers on
# pulsed DC (the same scalar operations in both cores); the fused ones, AC's demodulation and
# Raab's covariance (its information matrix H^T W H) have products the reference sums through
# BLAS (observed 1e-13 at most; Raab's covariance 7e-15 relative)
CASES = {
    "burst": ("roetenberg-bench", 5.0, 5, 1, True),
    "fused": ("roetenberg-fusion", 2.0, 100, 1, False),
    "tight": ("roetenberg-flexion-back", 1.5, 100, 1, False),
    "ac-raab": ("raab-ac", 0.7, 100, 1, False),
    "raab-acquire": ("raab-acquire", 4.0, 5, 1, False),
    "multi-sensor": ("multi16", 1.5, 16, 16, True),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_replayed_run_gives_the_same_poses_on_either_core(case):
    """The tracker's recorded run, replayed through each core: the same poses (module docstring)."""
    name, duration, min_valid, nodes, bitwise = CASES[case]
    header, reads = _record(name, 1, duration)
    _same_poses(header, reads, min_valid, nodes, bitwise)


def _calibration_with_map(path) -> None:
    """The imperfect bench's calibration file (the true imperfections of its source and sensor,
    tools.scenarios.imperfect) with a ``[distortion]`` map added: per coil two equivalent dipoles
    under the source (the image of a coil over a sheet), moments ~1 % of the coil's field at the
    working distance, so the map is felt but the poses stay valid."""
    import tomllib

    from coiltrack.firmware.calibration import dumps_toml
    from coiltrack.tools.scenarios.imperfect import write_truth_calibration

    tab = write_truth_calibration(path)
    with open(path, "rb") as fh:
        doc = tomllib.load(fh)
    assert doc["source"] and doc["sensor"]
    rng = np.random.default_rng(3)
    dist = {"model": "dipoles", "coils": 3}
    for j in range(3):
        dist[f"coil{j}_position_m"] = [[0.05 * rng.normal(), 0.05 * rng.normal(), -0.25 - 0.1 * k] for k in range(2)]
        dist[f"coil{j}_moment_am2_per_a"] = (3e-3 * rng.normal(size=(2, 3))).tolist()
    doc["distortion"] = dist
    with open(path, "w") as fh:
        fh.write(dumps_toml(doc))
    assert tab


def test_a_calibrated_run_with_a_distortion_map_gives_the_same_poses_on_either_core(tmp_path):
    """imperfect-bench with its calibration file holding the source's and the sensor's
    calibration and a distortion map (the calibrated loop kernels; the map added between the
    compiled fields and projection, the Python LM on the compiled signal model): recorded, then
    replayed through each core, the same poses; without the map (``distortion_apply = false``)
    the same log gives other positions, so the map is applied in the runs compared."""
    path = tmp_path / "calibration.toml"
    _calibration_with_map(path)
    sc = scenarios.get("imperfect-bench")
    cfg = sc.firmware_config().with_(calibration={"calibration_file": str(path)})
    header, reads = _record("imperfect-bench", 1, 4.0, cfg)
    a = _same_poses(header, reads, 5, bitwise=True)
    # the map is applied in these runs: without it the same log gives other positions
    b = _poses(header, reads, "compiled", {"distortion": {"distortion_apply": False}})
    assert b.shape == a.shape and np.max(np.abs(b[:, EXACT:EXACT + 3] - a[:, EXACT:EXACT + 3])) > 1e-5
