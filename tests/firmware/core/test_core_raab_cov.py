"""The compiled covariance of Raab's tracker (``firmware_py/core/src/raab_cov.c``) against its
Python reference (``pose.raab_covariance.RaabCovariance``) on seeded sequences of publications,
and against independent references: numpy's inverse of the information ``H^T W H`` written out
here, and (for Raab's co-centred dipoles, where the carry is exact) the inverse at the carried-to
point itself. Skipped where the extension is not built."""
import math

import numpy as np
import pytest

from coiltrack.firmware import core as fcore
from coiltrack.firmware.model.field import orthogonal_source
from coiltrack.firmware.model.signal import SignalModel
from coiltrack.firmware.pose.covariance import MAX_VARIANCE
from coiltrack.firmware.pose.raab_covariance import RaabCovariance
from coiltrack.firmware.pose.raab_update import point, sync_rotation

pytestmark = pytest.mark.skipif(not fcore.available(), reason="the compiled core is not built")

COMPILED = fcore.DEFAULT
N = 3
COILS = orthogonal_source(0.055, 50)
CBAR = (0.0, 0.0, 0.0)


class _Side:
    """One core's RaabCovariance with its own copies of the tracker's buffers."""

    def __init__(self, core, model="exact"):
        self.sig = SignalModel(COILS, model, fcore.PYTHON)
        self.x = memoryview(np.zeros(6))
        self.Rn = np.eye(3)
        self.w = memoryview(np.zeros(3 * N))
        self.cur = memoryview(np.zeros(N))
        self.pm = memoryview(np.zeros(3))
        self.out = np.zeros((6, 6))
        self.cov = RaabCovariance(N, CBAR, self.out, core,
                                  (self.x, self.Rn, self.w, self.cur, self.pm, self.sig.Bv, self.sig.Jv))
        assert self.cov.core == core.name

    def set_pose(self, x6):
        for i in range(6):
            self.x[i] = x6[i]
        sync_rotation(self.x, memoryview(self.Rn))

    def evaluate(self, nan=False, zero=False):
        """The fields at the estimate (the tracker's ``_unit_measure``) and the rows."""
        px, py, pz = point(self.x, CBAR)
        self.sig.fields(px, py, pz, memoryview(np.ones(N)), True)
        if nan or zero:
            for i in range(3 * N):
                self.sig.Bv[i] = math.nan if nan and i == 4 else 0.0
            for i in range(9 * N):
                self.sig.Jv[i] = 0.0
        self.pm[0], self.pm[1], self.pm[2] = px, py, pz
        self.cov.rows(self.sig.Bv, self.sig.Jv)

    def publish(self, w, cur, rel):
        for i in range(3 * N):
            self.w[i] = w[i]
        for j in range(N):
            self.cur[j] = cur[j]
        self.cov.publish(self.x, memoryview(self.Rn), self.w, self.cur, self.pm, rel, point(self.x, CBAR))

    def state(self):
        c = self.cov
        cs_ok = c._cs_ok if c.core == "python" else c._st[0] != 0.0
        return cs_ok, tuple(c._pc), tuple(c._qm), c.sig_p, c.sig_o


def _close(a, b, rel=1e-12):
    """Each element within ``rel`` of sqrt(a_ii a_kk) (the covariance's own scale)."""
    d = np.sqrt(np.abs(np.outer(np.diag(a), np.diag(a))))
    assert np.all(np.abs(a - b) <= rel * d), np.max(np.abs(a - b) / d)


def _pose(rng, rho=None):
    return (rng.uniform(-3, 3), rng.uniform(-1.2, 1.2), rng.uniform(0.15, 0.6) if rho is None else rho,
            rng.uniform(-3, 3), rng.uniform(-1.2, 1.2), rng.uniform(-3, 3))


def _pair_step(sides, action, *args, **kw):
    for s in sides:
        getattr(s, action)(*args, **kw)


@pytest.mark.parametrize("seed", range(6))
def test_publications_equal_to_the_reference(seed):
    """A seeded sequence through every branch of ``publish``: formed at an evaluation, carried to
    small moves (the orientation changed), scaled by a common change of the currents, formed again
    when one coil's current departs from the common scale, formed again after a move past the
    carry's limit, the sensor-frame form of anisotropic weights, and isotropic again. The compiled
    covariance within 1e-12 of sqrt(C_ii C_kk) of the Python's, the sigmas to 1e-12, and the
    decisions (C_s formed or not, where, its weights) exactly. Catches a term of the carry (the
    rho^8 / rho^7 / rho^6 factors, Q or M transposed), a wrong tolerance, a missed reform."""
    rng = np.random.default_rng(seed)
    sides = (_Side(fcore.PYTHON), _Side(COMPILED))
    x = _pose(rng)
    w = np.full(3 * N, 1.0 / 1.2e-7) * rng.uniform(0.8, 1.2, N).repeat(3)
    cur = rng.uniform(1.3, 1.7, N)
    rel = rng.uniform(0.01, 0.3)

    def check():
        p, c = sides
        _close(p.out, c.out)
        sp, sc = p.state(), c.state()
        assert sp[:3] == sc[:3]
        assert sp[3] == pytest.approx(sc[3], rel=1e-12) and sp[4] == pytest.approx(sc[4], rel=1e-12)
        return sp[0]

    _pair_step(sides, "set_pose", x)
    _pair_step(sides, "evaluate")
    _pair_step(sides, "publish", w, cur, rel)
    assert check()
    for k in range(4):                                          # small moves: carried
        x = tuple(v + d for v, d in zip(x, rng.normal(0, 2e-3, 6)))
        _pair_step(sides, "set_pose", x)
        _pair_step(sides, "publish", w, cur * 1.3, rel)         # a common scale of the currents
        assert check()
    cur2 = cur.copy()
    cur2[1] *= 1.05                                             # one coil's current departs: formed again
    _pair_step(sides, "publish", w, cur2, rel)
    assert check()
    x = (x[0] + 0.3, x[1], x[2] * 1.2, x[3], x[4], x[5])        # far from p_c: formed at the newer evaluation
    _pair_step(sides, "set_pose", x)
    _pair_step(sides, "evaluate")
    _pair_step(sides, "publish", w, cur2, rel)
    assert check()
    w2 = w.copy()
    w2[4] *= 1.5                                                # anisotropic: the sensor frame's form
    _pair_step(sides, "publish", w2, cur2, rel)
    assert not check()
    _pair_step(sides, "publish", w, cur2, 0.0)                  # isotropic again (rel 0: the carry's own limit)
    assert check()


def test_sensor_frame_form_equals_numpy_inverse_of_the_information():
    """Independent of the reference: with anisotropic weights the compiled covariance is
    ``(H^T W H)^-1`` (numpy's inverse) with ``H_j = R^T [J_j | [B_j]x] I_j`` built here from the
    exact model's fields and gradients, to 1e-10 of sqrt(C_ii C_kk)."""
    rng = np.random.default_rng(7)
    for _ in range(5):
        s = _Side(COMPILED)
        s.set_pose(_pose(rng))
        s.evaluate()
        w = rng.uniform(0.7e7, 1.3e7, 3 * N)
        cur = rng.uniform(1.3, 1.7, N)
        s.publish(w, cur, 0.1)
        B, J = np.array(s.sig.Bv).reshape(N, 3), np.array(s.sig.Jv).reshape(N, 3, 3)
        R = s.Rn
        rows = []
        for j in range(N):
            bx, by, bz = B[j]
            Bx = np.array([[0.0, -bz, by], [bz, 0.0, -bx], [-by, bx, 0.0]])
            rows.append(R.T @ np.hstack([J[j], Bx]) * cur[j])
        H = np.vstack(rows) * w[:, None]
        _close(np.linalg.inv(H.T @ H), s.out, 1e-10)


def test_carry_equals_the_inverse_at_the_new_pose_for_co_centred_dipoles():
    """Independent of the reference and of the carry's algebra: for Raab's model (co-centred
    orthogonal dipoles, equal currents) the information is covariant under rotations about the
    centre and scales with the range, so the covariance carried 5 % of the range away (another
    orientation too) equals numpy's inverse of the information formed at the new pose, ``D^T A^-1
    D`` with ``D = diag(I, R)`` taking the source-frame orientation error to the sensor's, to 1e-9."""
    rng = np.random.default_rng(11)
    for _ in range(5):
        s = _Side(COMPILED, "dipole")
        x = _pose(rng)
        s.set_pose(x)
        s.evaluate()
        w = np.full(3 * N, 1e7)
        cur = np.full(N, 1.5)
        s.publish(w, cur, 0.0)
        x2 = (x[0] + 0.03, x[1] - 0.02, x[2] * 1.02, x[3] + 0.2, x[4] - 0.1, x[5] + 0.3)
        s.set_pose(x2)
        s.publish(w, cur, 0.0)
        assert s.state()[0] and s.state()[1] != tuple(point(s.x, CBAR))       # carried, not formed
        ref = _Side(COMPILED, "dipole")
        ref.set_pose(x2)
        ref.evaluate()
        B, J = np.array(ref.sig.Bv).reshape(N, 3), np.array(ref.sig.Jv).reshape(N, 3, 3)
        A = np.zeros((6, 6))
        for j in range(N):
            bx, by, bz = B[j]
            K = np.hstack([J[j], [[0.0, -bz, by], [bz, 0.0, -bx], [-by, bx, 0.0]]]) * 1.5e7
            A += K.T @ K
        D = np.eye(6)
        D[3:, 3:] = s.Rn
        _close(D.T @ np.linalg.inv(A) @ D, s.out, 1e-9)


def test_singular_and_non_finite_information_as_the_reference():
    """Edge cases: zero fields (a singular information: the robust inverse's eigenvalue floor,
    which the compiled publication hands to the reference) and a NaN field (``MAX_VARIANCE I``),
    then a regular evaluation again: both cores publish the same covariance and state."""
    rng = np.random.default_rng(5)
    sides = (_Side(fcore.PYTHON), _Side(COMPILED))
    x = _pose(rng)
    w, cur = np.full(3 * N, 1e7), np.full(N, 1.5)
    _pair_step(sides, "set_pose", x)
    fresh = _Side(COMPILED)
    fresh.set_pose(x)
    fresh.evaluate(zero=True)
    for i in range(3 * N):
        fresh.w[i] = w[i]
    for j in range(N):
        fresh.cur[j] = cur[j]
    assert not fresh.cov._ck.publish(0.1)          # the kernel hands the floor to the reference, unchanged
    assert fresh.cov._st[0] == 0.0 and not np.any(fresh.out) and not any(fresh.cov._qm)
    for kw in (dict(zero=True), dict(nan=True), dict()):
        _pair_step(sides, "evaluate", **kw)
        _pair_step(sides, "publish", w, cur, 0.1)
        _close(sides[0].out, sides[1].out)
        assert sides[0].state()[:3] == sides[1].state()[:3]
        if kw.get("nan"):
            assert sides[1].out[0, 0] == pytest.approx(MAX_VARIANCE, rel=1e-12)
        if kw.get("zero"):
            assert np.all(np.isfinite(sides[1].out)) and sides[1].out[0, 0] >= 1e10


def test_compiled_publication_allocates_no_numpy_array():
    """The compiled rows and publications (formed, carried, the sensor frame's form) create no
    numpy array (``tools.bench.alloc.NumpyAllocationCounter``: a single temporary counts 1)."""
    from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available

    if not available():
        pytest.skip("numpy memory handler API not reachable")
    s = _Side(COMPILED)
    s.set_pose(_pose(np.random.default_rng(2)))
    s.evaluate()
    w, cur = np.full(3 * N, 1e7), np.full(N, 1.5)
    for i in range(3 * N):
        s.w[i] = w[i]
    for j in range(N):
        s.cur[j] = cur[j]
    R, pt = memoryview(s.Rn), point(s.x, CBAR)
    counter = NumpyAllocationCounter()
    with counter:
        s.cov.rows(s.sig.Bv, s.sig.Jv)
        for k in range(3):
            s.cov.publish(s.x, R, s.w, s.cur, s.pm, 0.1, pt)
            s.w[0] = 1.2e7 if k == 1 else 1e7
    assert counter.count == 0
    assert s.cov.sig_p > 0.0


def test_tracker_on_either_core_publishes_the_same_poses_and_covariances():
    """Raab's tracker (``pose.raab.RaabTracker``, exact-loop correction) on each core tracking a
    seeded path of the exact model's signals with noise, warm-started from its last solution, a
    coil's axes weighted unequally in some solves: the same status, iterations and evaluations,
    positions and rotations to 1e-12, covariances to 1e-12 of sqrt(C_ii C_kk), every solve."""
    from coiltrack.firmware.pose.raab import RaabTracker

    rng = np.random.default_rng(4)
    trk = {c.name: RaabTracker(COILS, core=c) for c in (fcore.PYTHON, COMPILED)}
    assert trk["compiled"]._covm.core == "compiled" and trk["python"]._covm.core == "python"
    truth = SignalModel(COILS, "exact", fcore.PYTHON)
    cur = np.array([1.5, 1.49, 1.51])
    p = np.array([0.25, 0.1, -0.05])
    rv = np.array([0.3, -0.2, 0.5])
    for k in range(40):
        p = p + rng.normal(0, 0.004, 3)
        rv = rv + rng.normal(0, 0.01, 3)
        th = np.linalg.norm(rv)
        Kx = np.array([[0, -rv[2], rv[1]], [rv[2], 0, -rv[0]], [-rv[1], rv[0], 0]]) / th
        R = np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * Kx @ Kx
        truth.fields(p[0], p[1], p[2], memoryview(cur), False)
        S = R.T @ np.array(truth.B).T + rng.normal(0, 1e-9, (3, 3))
        sigma = np.full((3, 3), 1e-9)
        if k % 7 == 3:
            sigma[1, 2] = 1.5e-9                                # one coil's axes weighted unequally
        res = {}
        for name, t in trk.items():
            warm = k > 0 and t.status & 1 == 0
            st = t.solve(S, cur, sigma, HEMI_X, t.position.copy() if warm else None,
                         t.rotation.copy() if warm else None)
            res[name] = (st, t.iterations, t.solve_evals, t.position.copy(), t.rotation.copy(), t.covariance.copy())
        a, b = res["python"], res["compiled"]
        assert a[:3] == b[:3]
        np.testing.assert_allclose(b[3], a[3], rtol=0, atol=1e-12 * np.linalg.norm(a[3]))
        np.testing.assert_allclose(b[4], a[4], rtol=0, atol=1e-12)
        _close(a[5], b[5])
        assert np.all(np.diag(a[5]) > 0.0)


HEMI_X = np.array([1.0, 0.0, 0.0])
