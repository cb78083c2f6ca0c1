"""The single-coil filter's per-coil gain states (``[adaptive] coil_gain_sigma``,
``estimate.single_coil``: ``y = (1 + g_c) I R^T B_c(p)``, Schepers & Veltink 2010 eq 5 with the
coil's true current).

Pinned to the closed form of a linear Gaussian estimate of one scalar (the gain is linear in the
measurement, so repeated pulses at a known pose give exactly the batch posterior), and the compiled
update to the Python reference."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.estimate.layout import SCHEPERS_LAYOUT, schepers_layout
from coiltrack.firmware.estimate.single_coil import CoilGainEKF, SchepersEKF, filter_class
from coiltrack.firmware.estimate.single_coil_update import CoilMeasurement
from coiltrack.firmware.model.field import Coil

COILS = [Coil((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.055, 50),
         Coil((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 0.055, 50),
         Coil((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.055, 50)]


def test_the_gain_rows_come_after_the_clones_and_only_when_asked():
    lay = schepers_layout(2, 3)
    assert lay.n == 30 and lay.GAIN == slice(27, 30)
    assert schepers_layout(2).n == SCHEPERS_LAYOUT.n == 27 and "GAIN" not in SCHEPERS_LAYOUT.names()
    cfg = FirmwareConfig()
    assert filter_class(cfg) is SchepersEKF and SchepersEKF.from_config(cfg, core=core.PYTHON).nx == 27
    cfg = cfg.with_keys(coil_gain_sigma=4e-3)
    g = filter_class(cfg).from_config(cfg, core=core.PYTHON)
    assert type(g) is CoilGainEKF and g.gains.n == 3 and g.nx == 30 and g.gains.sigma == 4e-3


def test_a_bad_gain_sigma_is_refused_by_name():
    with pytest.raises(Exception, match="coil_gain_sigma"):
        FirmwareConfig().with_keys(coil_gain_sigma=-1e-3).validate()
    with pytest.raises(ValueError, match="coil_gains"):
        CoilGainEKF.from_config(FirmwareConfig(), coil_gains=3, gain_sigma=0.0, core=core.PYTHON)


def _known_pose_filter(cfg_core, sigma0: float):
    e = CoilGainEKF.from_config(FirmwareConfig(), coil_gains=3, gain_sigma=sigma0, iterations=1, core=cfg_core)
    p0 = np.array([0.22, -0.09, 0.13])
    R0 = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    e.initialize(p0, R0, np.diag([1e-18] * 3 + [1e-18] * 3), 0, 1e-9, 1e-9, 1e-9)
    return e, p0, R0


@pytest.mark.parametrize("which", ["python", "compiled"])
def test_repeated_pulses_of_one_coil_estimate_its_gain_as_the_closed_form(which):
    """At a known pose, N noise-free pulses of coil 1 whose true current is ``(1 + g) I``: the
    gain's posterior is the batch one, ``J = N I^2 |h|^2 / s^2``, ``mean = g J / (J + 1 / s0^2)``,
    ``var = 1 / (J + 1 / s0^2)``; the other coils' gains stay at 0 with their prior variance, and
    the pose is not pulled (a filter without the gain state would move it)."""
    if which == "compiled":
        pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
    c = core.PYTHON if which == "python" else core.load("compiled")
    s0, g, I, s2, N = 5e-3, 4.0e-3, 0.7, 1e-16, 12
    e, p0, R0 = _known_pose_filter(c, s0)
    model = SingleCoilModel(COILS, "exact", c)
    model.evaluate(p0, R0)
    h = np.array(model.h[1], dtype=float)
    y = (1.0 + g) * I * h
    var = np.full(3, s2)
    m = CoilMeasurement()
    for _ in range(N):
        assert e.update_pulse(-1, m.set(y, var, 1, I, 0.0, 1.0, False), model) & 0b1111 == 0
    J = N * I * I * float(h @ h) / s2
    post = 1.0 / (J + 1.0 / (s0 * s0))
    G = e.layout.GAIN
    assert e.gains.gain[1] == pytest.approx(g * J * post, rel=1e-6)
    assert e.P[G.start + 1, G.start + 1] == pytest.approx(post, rel=1e-6)
    assert e.gains.gain[0] == 0.0 and e.gains.gain[2] == 0.0
    assert e.P[G.start, G.start] == pytest.approx(s0 * s0, rel=1e-12)
    np.testing.assert_allclose(e.p, p0, atol=1e-7)
    # without the gain state the same pulses pull the pose: the bias goes into it
    b = SchepersEKF.from_config(FirmwareConfig(), iterations=1, core=c)
    b.initialize(p0, R0, np.diag([1e-6] * 3 + [1e-4] * 3), 0, 1e-9, 1e-9, 1e-9)
    for _ in range(N):
        b.update_pulse(-1, m.set(y, var, 1, I, 0.0, 1.0, False), model)
    assert np.linalg.norm(b.p - p0) > 1e-4


def _imu(rng, t):
    s = t * 1e-6
    f = np.array([0.3 * math.sin(2.1 * s), -0.2 * math.cos(1.3 * s), 9.81]) + rng.normal(0, 0.02, 3)
    w = np.array([0.8 * math.sin(1.7 * s), 0.5, -0.6 * math.cos(0.9 * s)]) + rng.normal(0, 0.01, 3)
    return f, w


@pytest.mark.parametrize("iterations, offset_m", [(1, 0.0), (3, 0.03)])
def test_the_compiled_gain_update_matches_the_reference(iterations, offset_m):
    """Pulses of each coil with the gains on, through clone 0 and the current state, a prior off by
    ``offset_m`` (iterated passes): the same flags, state, gains and P to 1e-10 relative."""
    pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
    cfg = FirmwareConfig()
    ref = CoilGainEKF.from_config(cfg, iterations=iterations, coil_gains=3, gain_sigma=3e-3, core=core.PYTHON)
    got = CoilGainEKF.from_config(cfg, iterations=iterations, coil_gains=3, gain_sigma=3e-3,
                                  core=core.load("compiled"))
    assert (ref.kernels, got.kernels) == ("python", "compiled")
    rng = np.random.default_rng(7 + iterations)
    R0 = Rotation.from_rotvec(rng.normal(0, 0.5, 3)).as_matrix()
    p0 = np.array([0.25, -0.1, 0.15])
    sp = max(offset_m, 3e-3)
    for e in (ref, got):
        e.initialize(p0, R0, np.diag([sp * sp] * 3 + [0.02 ** 2] * 3), 0, 0.05, 0.02, 0.003)
    models = (SingleCoilModel(COILS, "exact", core.PYTHON), SingleCoilModel(COILS, "exact", core.load("compiled")))
    truth = SingleCoilModel(COILS, "exact", core.PYTHON)
    true_gain = (3e-3, -2e-3, 5e-3)
    t = 0
    m = CoilMeasurement()
    for j in range(9):
        coil = j % 3
        for e in (ref, got):
            e.schedule_clone(0, t + 2_000)
        t += 10_000
        f, w = _imu(rng, t)
        for e in (ref, got):
            e.propagate(t, f, w)
        p_true = ref.clone_p[0] + rng.normal(0, offset_m + 1e-4, 3)
        truth.evaluate(p_true, ref.clone_R[0])
        y = (1.0 + true_gain[coil]) * 0.8 * np.asarray(truth.h[coil]) + rng.normal(0, 3e-9, 3)
        var = np.full(3, 1e-17)
        k = 0 if j % 2 == 0 else -1
        flags = [e.update_pulse(k, m.set(y, var, coil, 0.8, 3e-3, 1.0, True), mod)
                 for e, mod in zip((ref, got), models)]
        assert flags[0] == flags[1]
        for name in ("p", "v", "R", "ba", "bg", "gains", "clone_p", "clone_R"):
            a, b = (ref.gains.gain, got.gains.gain) if name == "gains" else (getattr(ref, name), getattr(got, name))
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-10 * max(float(np.abs(a).max()), 1e-300), err_msg=name)
        np.testing.assert_allclose(got.P, ref.P, rtol=0, atol=1e-10 * float(np.abs(ref.P).max()))
        for e in (ref, got):
            e.release_clone(0)
    assert ref.updates == got.updates > 0
    assert np.count_nonzero(ref.gains.gain) >= 2


def test_the_gain_update_allocates_no_array():
    pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
    from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available
    if not available():
        pytest.skip("numpy allocation counting needs numpy's C API hooks")
    for c in (core.PYTHON, core.load("compiled")):
        e, p0, R0 = _known_pose_filter(c, 3e-3)
        model = SingleCoilModel(COILS, "exact", c)
        model.evaluate(p0, R0)
        y = np.array(model.h[2], dtype=float) * 0.9
        var = np.full(3, 1e-17)
        m = CoilMeasurement()
        e.update_pulse(-1, m.set(y, var, 2, 0.9, 3e-3, 1.0, True), model)
        with NumpyAllocationCounter() as n:
            for _ in range(5):
                e.update_pulse(-1, m.set(y, var, 2, 0.9, 3e-3, 1.0, True), model)
        assert n.count == 0, c


def test_the_bias_summary_recovers_a_known_constant_part():
    """``adaptive_coil_bias.summarise``: truth means that are the driver's and the coil model's parts
    plus a known offset give slope, residual and chi-square by hand."""
    from coiltrack.tools.analyses.adaptive_coil_bias import summarise

    d = [-2e-3, 1e-3, 2.5e-3, -0.5e-3]
    rows = [{"coils": [{"updates": 10, "driver": x, "coil_model": 2.5e-4, "truth": x + 2.5e-4 + 1e-4,
                        "truth_se": 1e-4} for x in d]}]
    s = summarise(rows)
    md = np.array(d) + 2.5e-4
    assert s["coil_runs"] == 4
    assert s["model+driver"]["corr"] == pytest.approx(1.0)
    assert s["model+driver"]["chi2_per_coil"] == pytest.approx(1.0)
    assert s["model+driver"]["residual_rms"] == pytest.approx(1e-4)
    assert s["model+driver"]["slope"] == pytest.approx(float((md + 1e-4) @ md / (md @ md)))
    assert s["coil_model"]["corr"] is None


def test_policy_runs_take_the_fixed_figures_and_ratios_as_the_runner(tmp_path):
    """``adaptive_policy_runs``: the fixed cycle's figures of a sweep run and the ratios rounded as
    ``bench.runner.add_fixed_comparison`` rounds them; a sweep of another duration is refused."""
    import json

    from coiltrack.tools.analyses import adaptive_policy_runs as apr
    from coiltrack.tools.bench.runner import FIXED_KEYS

    fixed = {"fixed_" + k: 1.0 for k in FIXED_KEYS}
    fixed.update(fixed_position_rms_mm=4.0, fixed_orientation_rms_deg=0.3, fixed_coil_energy_j=30.0)
    got = apr.with_fixed({"position_rms_mm": 3.0, "orientation_rms_deg": 0.31, "coil_energy_j": 25.0}, fixed)
    assert (got["position_rms_ratio"], got["orientation_rms_ratio"], got["energy_ratio"]) == (0.75, 1.033, 0.833)
    assert all(got["fixed_" + k] == fixed["fixed_" + k] for k in FIXED_KEYS)
    p = tmp_path / "s.json"
    p.write_text(json.dumps({"scenario": "schepers-adaptive", "duration_s": 20.0, "interrupted": False,
                             "runs": [{"seed": 1, "params": {}, "figures": fixed}]}))
    with pytest.raises(ValueError, match="60.0 s"):
        apr._fixed_figures(str(p), [1], 60.0)
    assert apr._fixed_figures(str(p), [1], 20.0)[1]["fixed_coil_energy_j"] == 30.0
    with pytest.raises(ValueError, match=r"seeds \[2\]"):
        apr._fixed_figures(str(p), [1, 2], 20.0)
    # a sweep over bench draws: each draw's own fixed cycle, never another draw's
    d1 = dict(fixed, fixed_coil_energy_j=31.0)
    p.write_text(json.dumps({"scenario": "schepers-adaptive", "duration_s": 20.0, "interrupted": False,
                             "runs": [{"seed": 1, "params": {"bench.noise_draw": 1}, "figures": d1},
                                      {"seed": 1, "params": {"bench.noise_draw": 0}, "figures": fixed}]}))
    assert apr._fixed_figures(str(p), [1], 20.0)[1]["fixed_coil_energy_j"] == 30.0
    assert apr._fixed_figures(str(p), [1], 20.0, draw=1)[1]["fixed_coil_energy_j"] == 31.0
    with pytest.raises(ValueError, match="bench draw 2"):
        apr._fixed_figures(str(p), [1], 20.0, draw=2)


def test_adaptive_ticks_with_coil_gains_allocate_no_numpy_array():
    """``schepers-adaptive`` with ``coil_gain_sigma`` on, 8 s (acquisition, warm-up cycle, pulses on
    demand): each sensor's filter carries the gains, they are updated, and no tick creates a numpy
    array (``tools.bench.alloc``)."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools import scenarios
    from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.bench.runner import BenchSetup

    if not available():
        pytest.skip("numpy memory handler API not reachable")
    sc = scenarios.get("schepers-adaptive")
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 3, 8.0, emu_end)
    # the scenario's filter with the policy keys at the configuration's defaults (pulses back to back)
    fw = Firmware(sc.firmware_config().with_keys(coil_gain_sigma=3e-3, pulse_length="fixed", baseline_sharing="ignore",
                                                 reference_settle_drop=0.0, unreached_share=0.0, reference_hold="bound",
                                                 adaptive_current_step_a=0.0), fw_end)
    counter = NumpyAllocationCounter()
    allocating, t = 0, 0
    while t <= 8_000_000:
        bench.emulator.step(t)
        before = counter.count
        with counter:
            fw.tick(t)
        allocating += counter.count != before
        t += fw.cfg.timing.tick_us
    ekfs = [s.ekf for s in fw.tracker.sensors.values()]
    assert ekfs and all(type(e) is CoilGainEKF for e in ekfs)
    assert fw.status()["adaptive_updates"] > 40 and all(np.count_nonzero(e.gains.gain) == 3 for e in ekfs)
    assert allocating == 0
