"""The single-coil window update's steps around the one-call EKF update, compiled
(``core/src/sc_window.c``: ``ct_scw_prior``, ``ct_scw_after``; glue ``py_sc_window.c``
``ScUpdateCore``) against their Python reference, ``track.single_coil_window.window_prior`` and
``window_after`` (the tracker's ``_update`` runs the reference on the Python core).

``linear`` decides whether the NIS monitor hears an update and the monitor's verdict decides the
gate, so both must be the reference's bits: the prior's flag and relative error, the consistency
term and every attribute of the monitor after each step are compared with ``==`` on seeded random
covariances, clone and state positions and currents (zero, tiny, negative, NaN), and a seeded run
of NIS values with a disturbance (an inconsistent window: the monitor's verdict flips and its
scale grows), rejected updates (NIS beyond the gate, inf, NaN), updates outside the linear
region, an empty and a wrapped magnetometer ring and the quiet term off. Independent references:
``rel = sqrt(rel2 + (tol / |I|)^2)`` and the quiet term ``((|B| - earth) / sigma)^2`` through numpy
(Schepers & Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt`` sec. 3.2-3.3; ``track.quality``'s
module docstring). Seeded; skips where the extension is not built."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.actuate.coil_choice import NisMonitor
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.estimate.single_coil import POS
from coiltrack.firmware.measure.pulse import SampleRing
from coiltrack.firmware.track.quality import PoseQuality
from coiltrack.firmware.track.single_coil_nis import nis_monitor
from coiltrack.firmware.track.single_coil_window import update_core, window_after, window_prior
from coiltrack.tools.bench.alloc import NumpyAllocationCounter

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

COMPILED = core.load("compiled")
MON = dict(window=8, dof=3, gate=16.27, z=2.326, min_count=3, min_excess=1.5, max_scale=50.0, feedback_updates=30)
_MON_STATE = ("count", "_head", "mean", "inconsistent", "r_scale", "total", "flagged", "excess")


class _Ekf:
    """The arrays of a single-coil filter the core binds (``SchepersEKF``'s P, p, clone_p)."""

    def __init__(self, nP: int, n_clones: int):
        self.P = np.zeros((nP, nP))
        self.p = np.zeros(3)
        self.clone_p = np.zeros((n_clones, 3))


class _Channel:
    def __init__(self, node: int, ring):
        self.node = node
        self.ring = ring


class _Sensor:
    def __init__(self, ekf, monitor, channel):
        self.ekf, self.monitor, self.track = ekf, monitor, channel


def _cfg(quiet_sigma: float = 2e-6):
    cfg = FirmwareConfig()
    return dataclasses.replace(cfg, quality=dataclasses.replace(cfg.quality, quality_quiet_sigma_t=quiet_sigma))


def _pair(nP: int = 27, n_clones: int = 4, quiet_sigma: float = 2e-6, cap: int = 16):
    """The reference's (monitor, quality) and the compiled (core, w, monitor) on one filter and ring."""
    ekf, ring = _Ekf(nP, n_clones), SampleRing(cap)
    ch = _Channel(7, ring)
    quality = PoseQuality(_cfg(quiet_sigma), 0, [ch])
    got_mon = nis_monitor(COMPILED, **MON)
    uc, w = update_core(COMPILED.ext, _Sensor(ekf, got_mon, ch), quality, 0.2 ** 2, 0.01 ** 2, 0.002)
    return ekf, ring, quality, NisMonitor(**MON), got_mon, uc, w


def _fill(rng, ekf, spread: float):
    A = rng.normal(size=ekf.P.shape) * spread
    ekf.P[:] = A @ A.T
    ekf.p[:] = rng.normal(size=3) * 0.4
    ekf.clone_p[:] = rng.normal(size=ekf.clone_p.shape) * 0.4


@pytest.mark.parametrize("nP", [27, 30])          # SchepersEKF with 4 clones; with three coil gains
def test_the_compiled_prior_is_the_reference_bit_for_bit(nP):
    """Seeded covariances from tight to loose (both sides of the linear bound), each clone and the
    state, currents zero, tiny, negative, NaN, and tied position variances: ``linear`` and
    ``rel`` equal the reference's. Catches the clone's row taken wrongly, the state's position
    used for a clone, a variance other than the largest, the 1e-6 A floor dropped or taken on
    the signed current."""
    ekf, _, _, _, _, uc, w = _pair(nP)
    P = memoryview(ekf.P.reshape(-1))
    pv, cv = memoryview(ekf.p), memoryview(ekf.clone_p)
    rng = np.random.default_rng(3)
    currents = [0.0, 1e-9, -1e-9, 2.5, -0.7, math.nan, 1e-6, -3.0]
    seen = set()
    for i in range(600):
        _fill(rng, ekf, 10.0 ** rng.uniform(-4, -0.5))
        if i % 50 == 0:
            b = POS.start
            for j in range(3):
                ekf.P[b + j, b + j] = 0.01            # the three variances tied
        k = int(rng.integers(-1, ekf.clone_p.shape[0]))
        cur = currents[i % len(currents)] if i % 3 == 0 else float(rng.normal() * 2.0)
        lin, rel = window_prior(P, nP, pv, cv, k, 0.2 ** 2, 0.01 ** 2, 0.002, cur)
        got = uc.prior(k, cur)
        assert (w[0] != 0.0) is lin, (i, k)
        assert got == rel or (got != got and rel != rel), (i, cur, got, rel)
        a = max(abs(cur), 1e-6)
        if math.isfinite(cur):
            assert rel == pytest.approx(float(np.sqrt(0.01 ** 2 + (0.002 / a) ** 2)), rel=1e-15)
        seen.add(lin)
    assert seen == {True, False}
    with pytest.raises(IndexError, match="clone"):
        uc.prior(ekf.clone_p.shape[0], 1.0)


@pytest.mark.parametrize("quiet_sigma, cap", [(2e-6, 16), (2e-6, 3), (0.0, 16)])
def test_the_compiled_after_step_is_the_reference_bit_for_bit(quiet_sigma, cap):
    """A seeded run of updates: chi-square NIS, a disturbance (NIS x 12: the window turns
    inconsistent and the scale grows, then clears), rejected updates (beyond the gate, inf, NaN),
    updates outside the linear region (the monitor not told), magnetometer samples arriving
    between updates (an empty ring first, a ring that wraps) or the quiet term off: the
    consistency term and every attribute of the monitor after each step are the reference's.
    Independent check of the quiet term through numpy. Catches the monitor told of a non-linear
    update, ``add_used`` given the nominal NIS, the quiet term of the oldest sample, the NIS not
    divided by the dimension."""
    ekf, ring, quality, ref_mon, got_mon, uc, w = _pair(quiet_sigma=quiet_sigma, cap=cap)
    rng = np.random.default_rng(11)
    flips, t = 0, 1000
    for i in range(300):
        if i and i % 3 == 0:                     # a magnetometer sample now and then (none before the first)
            t += 10_000
            ring.push(t, *(rng.normal(size=3) * 1e-5 + np.array([2e-5, 0.0, 4e-5])), False, 0)
        nn = float(rng.chisquare(3))
        if 100 <= i < 160:
            nn *= 12.0
        nis = nn * float(rng.uniform(0.3, 1.0))
        if i in (40, 41, 42):
            nis = (30.0, math.inf, math.nan)[i - 40]
            nn = nis
        _fill(rng, ekf, 10.0 ** rng.uniform(-3.5, -0.8))
        lin, _ = window_prior(memoryview(ekf.P.reshape(-1)), 27, memoryview(ekf.p), memoryview(ekf.clone_p), -1,
                              0.2 ** 2, 0.01 ** 2, 0.002, 1.0)
        uc.prior(-1, 1.0)
        assert (w[0] != 0.0) is lin
        was = ref_mon.inconsistent
        x_ref = window_after(quality, 7, ref_mon, nn, nis, lin)
        x_got = uc.after(nn, nis)
        assert x_got == x_ref or (x_got != x_got and x_ref != x_ref), (i, x_got, x_ref)
        for name in _MON_STATE:
            a, b = getattr(ref_mon, name), getattr(got_mon, name)
            assert type(a) is type(b) and (a == b or (a != a and b != b)), (i, name, a, b)
        flips += ref_mon.inconsistent != was
        if quiet_sigma > 0.0 and ring.hc[1] > 0 and math.isfinite(nis):
            bn = float(np.linalg.norm(ring.b[(ring.hc[0] - 1) % cap]))
            q = ((bn - quality.earth) / quiet_sigma) ** 2
            assert x_got == pytest.approx(nis / 3.0 + q, rel=1e-12)
        elif math.isfinite(nis):
            assert x_got == nis / 3.0
    assert flips >= 2 and ref_mon.flagged > 0            # the verdict turned and cleared
    np.testing.assert_array_equal(got_mon._buf, ref_mon._buf)


def test_the_compiled_steps_allocate_nothing_and_bad_bindings_are_refused():
    from coiltrack.firmware import _core

    ekf, ring, _, _, mon, uc, w = _pair()
    ring.push(5, 1e-5, 0.0, 3e-5, False, 0)
    with NumpyAllocationCounter() as n:
        for i in range(200):
            uc.prior(i % 5 - 1, 1.5)
            uc.after(float(i % 7), float(i % 3))
    assert n.count == 0
    args = [ekf.P, 27, POS.start, ekf.p, ekf.clone_p, mon._buf, mon._bound, mon._st, 8, 3, 3.0, 3.0, 50.0, 16.27,
            0.1, 0.04, 1e-4, 0.002, np.zeros(1)]
    bad = list(args)
    bad[1] = 40                                   # P smaller than nP x nP
    with pytest.raises(TypeError, match="P"):
        _core.ScUpdateCore(*bad)
    bad = list(args)
    bad[2] = 26
    with pytest.raises(ValueError, match="pos"):
        _core.ScUpdateCore(*bad)
    bad = list(args)
    bad[5] = np.zeros(8, dtype=np.float32)
    with pytest.raises(TypeError, match="buf"):
        _core.ScUpdateCore(*bad)
    with pytest.raises(RuntimeError, match="already"):
        uc.bind_quiet(ring.hc, ring.b, 5e-5, 2e-6)


def test_the_reference_core_and_a_changed_quality_keep_the_python_steps():
    """No extension, the reference monitor, or a quality whose consistency is not the reference's:
    no compiled core (the tracker runs the reference's steps)."""
    ekf, ring = _Ekf(27, 4), SampleRing(8)
    ch = _Channel(3, ring)
    quality = PoseQuality(_cfg(), 0, [ch])
    assert update_core(None, _Sensor(ekf, nis_monitor(core.PYTHON, **MON), ch), quality, 0.04, 1e-4, 0.002) is None
    assert update_core(COMPILED.ext, _Sensor(ekf, NisMonitor(**MON), ch), quality, 0.04, 1e-4, 0.002) is None

    class Other(PoseQuality):
        def consistency(self, node, cost, nis_per_dim=0.0):
            return 2.0 * nis_per_dim

    other = Other(_cfg(), 0, [ch])
    assert update_core(COMPILED.ext, _Sensor(ekf, nis_monitor(COMPILED, **MON), ch), other, 0.04, 1e-4, 0.002) is None
