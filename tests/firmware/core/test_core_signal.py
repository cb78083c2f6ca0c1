"""The compiled core's coil field and signal model (firmware_py/core/src/field.c, signal.c) against
their Python reference (model/field.py loop_point / dipole_point, model/signal.py SignalModel).

The C does the same floating-point operations in the same order as the Python, compiled with
-ffp-contract=off, so the results are compared bit for bit (``assert_array_equal``); the stated
fallback tolerance of the kernels' contract is 1e-12 relative, which these tests do not need.
All inputs are seeded. The whole module skips where the extension is not built."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.calibration import calibrated_coils
from coiltrack.firmware.linalg import flat
from coiltrack.firmware.model.distortion import DistortionMap
from coiltrack.firmware.model.field import Coil, dipole_point, loop_point, orthogonal_source
from coiltrack.firmware.model.signal import SignalModel
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

SKEWED = [Coil([0.01, 0, 0], [1, 0.2, 0], 0.05, 40), Coil([0, 0.012, 0], [0, 1, 0.3], 0.06, 50),
          Coil([0, 0, 0.01], [0.1, 0, 1], 0.055, 45), Coil([-0.01, 0, 0], [1, 1, 1], 0.04, 30)]
ORTHO = orthogonal_source(0.055, 50)
# a signed permutation that is not the identity (the axes kernel's index and sign bookkeeping)
FLIPPED = [Coil([0.002, 0, 0], [0, 0, -1], 0.05, 40), Coil([0, 0, 0.003], [-1, 0, 0], 0.05, 40),
           Coil([0, 0, 0], [0, 1, 0], 0.05, 40)]


def _points(rng, radius):
    """Seeded points in the coil frame, with the reference's edge cases: on the axis (rho = 0
    exactly), 1e-9 a off it, 1e-9 a from the wire, exactly on the wire, at the centre, far away
    (1e4 a), and a spread of ordinary ones."""
    a = radius
    pts = [(0.0, 0.0, 0.3), (0.0, 0.0, -0.02), (1e-9 * a, 0.0, 0.5 * a), (0.0, 1e-9 * a, 3 * a),
           (a * (1 + 1e-9), 0.0, 0.0), (0.0, a, 1e-9 * a), (a, 0.0, 0.0), (0.0, 0.0, 0.0),
           (1e4 * a, -3e3 * a, 2e3 * a), (0.3 * a, 0.4 * a, 0.0)]
    for _ in range(400):
        u = rng.normal(size=3)
        pts.append(tuple(u / np.linalg.norm(u) * a * 10 ** rng.uniform(-2, 2.5)))
    return pts


@pytest.mark.parametrize("jac", [False, True])
def test_loop_point_is_bit_identical_to_the_reference(jac):
    """ct_loop_point against field.loop_point on 410 points including the axis, the wire and far
    away: a dropped derivative term, a swapped Jxy/Jxz slot or an AGM stopping one step early
    changes the last bits (or more) of some entry."""
    rng = np.random.default_rng(3)
    for radius in (0.055, 0.02):
        for x, y, z in _points(rng, radius):
            scale = rng.uniform(-2e-4, 2e-4)
            ref = loop_point(x, y, z, radius, scale, jac)
            got = _core.loop_point(x, y, z, radius, scale, jac)
            assert got == ref or all((g == r) or (math.isnan(g) and math.isnan(r)) for g, r in zip(got, ref)), \
                (x, y, z, got, ref)


@pytest.mark.parametrize("jac", [False, True])
def test_dipole_point_is_bit_identical_to_the_reference(jac):
    """ct_dipole_point against field.dipole_point on seeded points (the moment along and across
    the point's direction, a point on the moment's axis): a wrong r power or sign shows."""
    rng = np.random.default_rng(4)
    cases = [((0.0, 0.0, 0.4), (0.0, 0.0, 0.5)), ((0.3, 0.0, 0.0), (0.0, 0.0, 0.5))]
    for _ in range(500):
        cases.append((tuple(rng.normal(size=3) * 10 ** rng.uniform(-2, 1)), tuple(rng.normal(size=3))))
    for p, m in cases:
        assert _core.dipole_point(*p, *m, jac) == dipole_point(*p, *m, jac), (p, m)


def _pair(coils, model, monkeypatch):
    """The same model built on the Python core and on the compiled core."""
    ref = SignalModel(coils, model, core.PYTHON)
    got = SignalModel(coils, model, core.load("compiled"))
    assert (ref.core, got.core) == ("python", "compiled")
    return ref, got


def _pose(rng):
    u = rng.normal(size=3)
    return u / np.linalg.norm(u) * rng.uniform(0.1, 0.7), Rotation.from_rotvec(rng.normal(size=3)).as_matrix()


@pytest.mark.parametrize("coils", [ORTHO, SKEWED, FLIPPED], ids=["orthogonal", "skewed-offset", "flipped-axes"])
@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_signal_model_fields_predict_measure_bit_identical(coils, model, monkeypatch):
    """fields / predict / measure of the compiled SignalModel against the Python one at 60 seeded
    poses (and a sensor on coil 0's axis), currents of both signs, R as an array, a 2-D
    memoryview and a transposed (strided) view; B, J, h and H compared bit for bit, and the
    evaluation count the same."""
    rng = np.random.default_rng(5)
    ref, got = _pair(coils, model, monkeypatch)
    n = len(coils)
    poses = [_pose(rng) for _ in range(60)]
    ax = np.asarray(coils[0].axis) * 0.4 + np.asarray(coils[0].center)
    poses.append((ax, np.eye(3)))
    for k, (p, R) in enumerate(poses):
        cur = rng.uniform(0.2, 2.0, n) * rng.choice([-1.0, 1.0], n)
        Rv = (R, memoryview(np.ascontiguousarray(R)), np.ascontiguousarray(R.T).T)[k % 3]
        for sm in (ref, got):
            sm.fields(*p, memoryview(cur), True)
        np.testing.assert_array_equal(got.B, ref.B)
        np.testing.assert_array_equal(got.J, ref.J)
        hs = [np.zeros(3 * n) for _ in range(4)]
        Hs = [np.zeros(18 * n) for _ in range(2)]
        ref.predict(*p, Rv, memoryview(cur), flat(hs[0]))
        got.predict(*p, Rv, memoryview(cur), flat(hs[1]))
        ref.measure(*p, Rv, list(cur), hs[2], Hs[0])
        got.measure(*p, Rv, list(cur), hs[3], Hs[1])
        np.testing.assert_array_equal(hs[1], hs[0])
        np.testing.assert_array_equal(hs[3], hs[2])
        np.testing.assert_array_equal(Hs[1], Hs[0])
    assert got.evals == ref.evals == 3 * n * len(poses)


def test_calibrated_source_and_distortion_map_bit_identical(monkeypatch):
    """A calibrated source (tilted axes, gains, offsets: the general loop kernel with a gain in its
    scale) with the room's distortion map added between the compiled fields and the compiled
    projection: the same h and H as the Python core, bit for bit."""
    from coiltrack.firmware.calibration import SourceCalibration

    rng = np.random.default_rng(6)
    src = SourceCalibration(np.diag([1.01, 0.98, 1.03]) + 0.02 * rng.normal(size=(3, 3)),
                            0.002 * rng.normal(size=(3, 3)))
    coils = calibrated_coils(orthogonal_source(0.055, 50), src)
    ref, got = _pair(coils, "exact", monkeypatch)
    dm = DistortionMap([[[0.05, 0.02, -1.1]], [[0.1, 0.0, -1.2]], [[-0.2, 0.3, -1.0]]],
                       [[[-0.08, 0.01, -0.005]], [[0.0, -0.1, -0.004]], [[0.0, -0.04, 0.18]]])
    ref.set_distortion(dm)
    got.set_distortion(dm)
    for _ in range(30):
        p, R = _pose(rng)
        cur = [1.5, -0.8, 1.1]
        h0, h1, H0, H1 = np.zeros(9), np.zeros(9), np.zeros(54), np.zeros(54)
        ref.measure(*p, R, cur, h0, H0)
        got.measure(*p, R, cur, h1, H1)
        np.testing.assert_array_equal(h1, h0)
        np.testing.assert_array_equal(H1, H0)
        ref.predict(*p, R, cur, h0)
        got.predict(*p, R, cur, h1)
        np.testing.assert_array_equal(h1, h0)
    assert np.any(H0 != 0.0)


@pytest.mark.skipif(not available(), reason="needs numpy's allocation hook")
def test_compiled_measure_allocates_no_array(monkeypatch):
    """The compiled measure and predict, called as the solver calls them (memoryviews made at
    start-up), allocate no numpy array."""
    _, sm = _pair(ORTHO, "exact", monkeypatch)
    h, H = np.zeros(9), np.zeros(54)
    hv, Hv, R = flat(h), flat(H), memoryview(np.eye(3))
    cur = memoryview(np.ones(3))
    sm.measure(0.2, 0.1, 0.3, R, cur, hv, Hv)
    with NumpyAllocationCounter() as c:
        for i in range(50):
            sm.measure(0.2 + 1e-3 * i, 0.1, 0.3, R, cur, hv, Hv)
            sm.predict(0.2, 0.1 + 1e-3 * i, 0.3, R, cur, hv)
    assert c.count == 0


def test_bad_buffers_are_refused_with_their_name(monkeypatch):
    """A float32 or too short output buffer, or an R of the wrong shape, is refused with a
    TypeError naming the argument (never a write past the end)."""
    _, sm = _pair(ORTHO, "exact", monkeypatch)
    R = np.eye(3)
    with pytest.raises(TypeError, match="h"):
        sm.predict(0.2, 0.1, 0.3, R, [1.0, 1.0, 1.0], np.zeros(9, dtype=np.float32))
    with pytest.raises(TypeError, match="H"):
        sm.measure(0.2, 0.1, 0.3, R, [1.0, 1.0, 1.0], np.zeros(9), np.zeros(53))
    with pytest.raises(TypeError, match="R"):
        sm.predict(0.2, 0.1, 0.3, np.eye(2), [1.0, 1.0, 1.0], np.zeros(9))
    with pytest.raises(ValueError, match="cur"):
        sm.fields(0.2, 0.1, 0.3, [1.0, 1.0], False)
