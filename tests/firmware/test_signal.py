"""The firmware's one measurement model, model/signal.py: signals, pose
Jacobian, current scaling, evaluation count, no allocation. All inputs seeded."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware.linalg import flat
from coiltrack.firmware.model.field import Coil, orthogonal_source
from coiltrack.firmware.model.signal import SignalModel
from coiltrack.firmware.pose.reference import measurement_model
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

SKEWED = [Coil([0.01, 0, 0], [1, 0.2, 0], 0.05, 40), Coil([0, 0.012, 0], [0, 1, 0.3], 0.06, 50),
          Coil([0, 0, 0.01], [0.1, 0, 1], 0.055, 45), Coil([-0.01, 0, 0], [1, 1, 1], 0.04, 30)]
ORTHO = orthogonal_source(0.055, 50)


def rot(w):
    """exp([w]x) from scipy, independent of the firmware's Rodrigues."""
    return Rotation.from_rotvec(w).as_matrix()


def poses(rng, k):
    out = []
    for _ in range(k):
        u = rng.normal(size=3)
        out.append((u / np.linalg.norm(u) * rng.uniform(0.12, 0.6), rot(rng.normal(size=3))))
    return out


def signals(sm, p, R, cur):
    h = np.zeros((sm.n, 3))
    sm.predict(*p, R, memoryview(cur), flat(h))
    return h


def measured(sm, p, R, cur):
    h = np.zeros((sm.n, 3))
    H = np.zeros((sm.n, 3, 6))
    sm.measure(*p, R, memoryview(cur), flat(h), flat(H))
    return h, H


@pytest.mark.parametrize("coils", [ORTHO, SKEWED], ids=["orthogonal", "skewed-offset"])
@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_jacobian_matches_central_differences_of_the_signals(coils, model):
    """H = [R^T J, [h]x] against central differences of h with
    R_true = R exp([dtheta]x) (scipy's exp): a sign error or a transposed
    skew matrix in the orientation columns, or R instead of R^T in the
    position block, is off by O(|H|)."""
    rng = np.random.default_rng(11)
    sm = SignalModel(coils, model)
    cur = rng.uniform(0.5, 2.0, len(coils)) * rng.choice([-1.0, 1.0], len(coils))
    eps = 1e-6
    for p, R in poses(rng, 4):
        h, H = measured(sm, p, R, cur)
        np.testing.assert_array_equal(h, signals(sm, p, R, cur))
        for k in range(6):
            d = np.zeros(6)
            d[k] = eps
            fd = (signals(sm, p + d[:3], R @ rot(d[3:]), cur) - signals(sm, p - d[:3], R @ rot(-d[3:]), cur)) / (2 * eps)
            # central differences at 1e-6: truncation and rounding below 1e-7 |H|
            assert np.abs(H[:, :, k] - fd).max() < 1e-7 * np.abs(H).max(), (k, model)


def test_loop_fields_of_axis_and_general_coils_match_magpylib():
    """Source-frame fields of the exact loop against magpylib's ``Circle`` (placed and turned
    by the coil's own centre and axis, scipy's rotation), to 1e-9 of the largest, for the
    orthogonal source (whose coil frames are signed permutations of the source axes: the
    kernel without the frame rotations' zero terms) and the skewed, offset one (the general
    kernel); the gradient against central differences of magpylib to 1e-6. Catches a
    component written to the wrong axis or with the wrong sign in either kernel."""
    import magpylib
    import scipy.constants

    scale = (4e-7 * np.pi) / scipy.constants.mu_0
    rng = np.random.default_rng(21)
    for coils in (ORTHO, SKEWED):
        sm = SignalModel(coils, "exact")
        cur = rng.uniform(0.5, 2.0, len(coils))
        srcs = []
        for c, i in zip(coils, cur):
            z = np.array([0.0, 0.0, 1.0])
            turn = Rotation.align_vectors([c.axis], [z])[0]
            srcs.append(magpylib.current.Circle(current=i * c.turns, diameter=2 * c.radius,
                                                position=c.center, orientation=turn))
        for p, _ in poses(rng, 6):
            sm.fields(*p, memoryview(cur), True)
            ref = np.array([s.getB(p) for s in srcs]) * scale
            assert np.abs(sm.B - ref).max() < 1e-9 * np.abs(ref).max()
            eps = 1e-6
            for k in range(3):
                d = np.zeros(3)
                d[k] = eps
                fd = np.array([(s.getB(p + d) - s.getB(p - d)) / (2 * eps) for s in srcs]) * scale
                assert np.abs(sm.J[:, :, k] - fd).max() < 1e-6 * np.abs(sm.J).max()


@pytest.mark.parametrize("model", ["exact", "dipole"])
def test_signals_scale_with_each_coils_own_current(model):
    """h_j = I_j R^T B_j(p) against the numpy reference (CoilSet path) with
    a different current per coil: catches a dropped current, a current taken
    from the wrong coil, or the dipole moment without the current."""
    rng = np.random.default_rng(12)
    sm = SignalModel(SKEWED, model)
    cur = np.array([1.5, -0.7, 2.2, 0.3])
    for p, R in poses(rng, 3):
        ref = measurement_model(p, R, SKEWED, cur, model)         # (3, n)
        np.testing.assert_allclose(signals(sm, p, R, cur), ref.T, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
        h1, H1 = measured(sm, p, R, np.ones(4))
        h, H = measured(sm, p, R, cur)
        np.testing.assert_allclose(h, cur[:, None] * h1, rtol=1e-13, atol=1e-13 * np.abs(h).max())
        np.testing.assert_allclose(H, cur[:, None, None] * H1, rtol=1e-13, atol=1e-13 * np.abs(H).max())


def test_every_coil_at_every_point_counts_one_evaluation():
    sm = SignalModel(SKEWED, "exact")
    cur = np.ones(4)
    p, R = np.array([0.2, 0.1, 0.0]), np.eye(3)
    measured(sm, p, R, cur)
    signals(sm, p, R, cur)
    sm.fields(0.3, 0.0, 0.0, memoryview(cur), False)
    assert sm.evals == 12
    sm.reset_evals()
    assert sm.evals == 0


@pytest.mark.skipif(not available(), reason="numpy memory handler API not reachable")
def test_measure_and_predict_allocate_no_numpy_array():
    for model in ("exact", "dipole"):
        sm = SignalModel(SKEWED, model)
        cur = memoryview(np.array([1.0, 2.0, 0.5, 1.5]))
        h = memoryview(np.zeros(12))
        H = memoryview(np.zeros(72))
        R = np.eye(3)
        Rm = memoryview(R)
        sm.measure(0.2, 0.1, 0.05, R, cur, h, H)
        counter = NumpyAllocationCounter()
        with counter:
            for k in range(5):
                sm.measure(0.2 + 0.01 * k, 0.1, 0.05, R, cur, h, H)
                sm.measure(0.2, 0.1 + 0.01 * k, 0.05, Rm, cur, h, H)
                sm.predict(0.2, 0.1, 0.05 + 0.01 * k, R, cur, h)
        assert counter.count == 0
