"""Raab's tracker's inputs (``pose.raab_io.RaabIO``): the compiled ``ct_raab_io``
against the Python reference, bit for bit, on seeded inputs and the edge cases the reference
handles; the warm start's angles against their definition (the point and ``A = R^T`` they give
back)."""
from __future__ import annotations

import numpy as np
import pytest

from coiltrack.firmware import core as fcore
from coiltrack.firmware.pose import raab_io as rio
from coiltrack.firmware.pose.raab import RaabTracker
from coiltrack.firmware.pose.raab_update import dcm, point
from coiltrack.hil.physics import thesis_source

pytestmark = pytest.mark.skipif(not fcore.available(), reason="the compiled core is not built")


def _pair():
    coils = thesis_source().coils
    tp = RaabTracker(coils, core=fcore.PYTHON)
    tc = RaabTracker(coils, core=fcore.DEFAULT)
    assert tp._in.core == "python" and tc._in.core == "compiled"
    return tp, tc


def _buffers(t):
    """Everything the inputs write (the tracker's buffers and the component's flags)."""
    i = t._in
    return (np.array(t._Sv), np.array(t._wv), np.array(t._curv), np.array(i.hemi), t._Rn.copy(), np.array(t._x),
            np.array(t._mom), np.array(t._mp), i.check_hemi, i.warm, i._sigma_rms)


def _same(tp, tc, args):
    rp, rc = tp._in.load(*args), tc._in.load(*args)
    assert rp == rc, (rp, rc)
    for a, b in zip(_buffers(tp), _buffers(tc)):
        assert np.array_equal(a, b, equal_nan=True), (a, b)
    return rp


def _rotation(rng):
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _case(rng, n=3):
    S = rng.normal(0, 1e-6, (3, n))
    sigma = rng.uniform(1e-9, 1e-8, (3, n))
    cur = rng.uniform(0.5, 2.0, n)
    return S, cur, sigma


def test_random_inputs_bit_equal_to_the_reference():
    """Seeded signals, currents, hemispheres and warm starts (rotations, some transposed views and
    Fortran-ordered signals): the same result code and the same buffers, bit for bit: catches a
    weight not inverted, a signal read at the wrong stride, an angle from the wrong element of
    ``A = R^T`` or the moments at the nominal instead of the measured currents."""
    rng = np.random.default_rng(3)
    tp, tc = _pair()
    codes = set()
    for k in range(200):
        S, cur, sigma = _case(rng)
        if k % 3 == 1:
            S, sigma = np.asfortranarray(S), np.asfortranarray(sigma)
        hemi = rng.normal(size=3) if k % 2 else None
        if k % 4 == 0:
            args = (S, cur, sigma, hemi, None, None)
        else:
            R = _rotation(rng)
            R = R.T.copy().T if k % 5 == 0 else R
            args = (S, cur, sigma, hemi, rng.uniform(-0.5, 0.5, 3), R)
        codes.add(_same(tp, tc, args))
    assert codes == {rio.OK}


def test_edge_cases_give_the_reference_code_and_buffers():
    """The checks in their order: a NaN signal, a zero sigma, a NaN current (BAD_LOAD), a NaN or a
    zero hemisphere (BAD_HEMI), one of the warm start's two arguments, a NaN in the rotation or
    the position, a start at the coils' centre (BAD_X0), zero currents (NO_START), a warm start's
    matrix that is no rotation (projected by the Python's nearest_rotation) and inputs that are no
    float64 arrays (the reference takes them): each the same in both."""
    rng = np.random.default_rng(8)
    tp, tc = _pair()
    R = _rotation(rng)
    p = np.array([0.2, -0.1, 0.15])
    cases = []
    S, cur, sigma = _case(rng)
    cases.append(((S, cur, sigma, None, p, R), rio.OK))
    bad = S.copy(); bad[1, 2] = np.nan
    cases.append(((bad, cur, sigma, None, p, R), rio.BAD_LOAD))
    bad = sigma.copy(); bad[2, 0] = 0.0
    cases.append(((S, cur, bad, None, p, R), rio.BAD_LOAD))
    cases.append(((S, np.array([1.0, np.nan, 1.0]), sigma, None, p, R), rio.BAD_LOAD))
    cases.append(((S, cur, sigma, np.array([np.nan, 0.0, 1.0]), p, R), rio.BAD_HEMI))
    cases.append(((S, cur, sigma, np.zeros(3), p, R), rio.BAD_HEMI))
    cases.append(((S, cur, sigma, None, p, None), rio.BAD_X0))
    cases.append(((S, cur, sigma, None, None, R), rio.BAD_X0))
    badR = R.copy(); badR[1, 1] = np.inf
    cases.append(((S, cur, sigma, None, p, badR), rio.BAD_X0))
    cases.append(((S, cur, sigma, None, np.array([0.1, np.nan, 0.0]), R), rio.BAD_X0))
    centre = np.array(tp._cbar)
    cases.append(((S, cur, sigma, None, centre, R), rio.BAD_X0))
    cases.append(((S, np.zeros(3), sigma, None, p, R), rio.NO_START))
    skew = R + 1e-6 * rng.normal(size=(3, 3))
    cases.append(((S, cur, sigma, np.array([1.0, 0.0, 0.0]), p, skew), rio.OK))
    cases.append(((S.tolist(), list(cur), sigma, (1.0, 0.0, 0.0), tuple(p), R), rio.BAD_LOAD))    # no shape
    cases.append(((S, list(cur), sigma, (0.0, 1.0, 0.0), tuple(p), R), rio.OK))
    cases.append(((S.astype(np.float32), cur, sigma.astype(np.float32), None, p, R), rio.OK))
    for args, want in cases:
        assert _same(tp, tc, args) == want
    # the projection: the skewed matrix's nearest rotation, not the matrix itself
    _same(tp, tc, (S, cur, sigma, None, p, skew))
    assert np.allclose(tc._Rn.T @ tc._Rn, np.eye(3), atol=1e-14) and not np.array_equal(tc._Rn, skew)


def test_warm_start_angles_give_back_the_pose():
    """Raab's angles of a warm start give back its point (``raab_update.point``) and ``A = R^T``
    (``dcm``, Table II) to rounding: an independent check of the angles' definition."""
    rng = np.random.default_rng(21)
    _, tc = _pair()
    for _ in range(50):
        S, cur, sigma = _case(rng)
        R, p = _rotation(rng), rng.uniform(-0.5, 0.5, 3)
        assert tc._in.load(S, cur, sigma, None, p, R) == rio.OK
        x = tc._x
        assert np.allclose(point(x, tc._cbar), p, rtol=0, atol=1e-14)
        assert np.allclose(np.array(dcm(x[3], x[4], x[5])).reshape(3, 3), R.T, rtol=0, atol=1e-13)


def test_residual_cost_and_finish_pose_bit_equal_to_the_reference():
    """At seeded estimates (angles, range, corrected signals, weights, moments; one estimate with a
    NaN range): ``residual_cost`` and the published pose (position, rotation, angles, the finite
    flag) the same in both, bit for bit; the residual also against numpy's dipole field of
    ``model.field.dipole_point`` summed independently (1e-12 relative): catches ``R`` applied
    untransposed, a weight squared twice or the dipole's range cubed wrong."""
    from coiltrack.firmware.model.field import dipole_point

    rng = np.random.default_rng(13)
    tp, tc = _pair()
    for k in range(60):
        x = np.array([rng.uniform(-3, 3), rng.uniform(-1.4, 1.4), rng.uniform(0.1, 0.6),
                      rng.uniform(-3, 3), rng.uniform(-1.4, 1.4), rng.uniform(-3, 3)])
        if k == 59:
            x[2] = np.nan
        Sc, w, mom = rng.normal(0, 1e-6, 9), rng.uniform(1e7, 1e9, 9), rng.normal(0, 0.5, 9)
        for t in (tp, tc):
            for i in range(6):
                t._x[i] = x[i]
            for i in range(9):
                t._Sc[i], t._wv[i], t._mom[i] = Sc[i], w[i], mom[i]
            sync = np.array(dcm(x[3], x[4], x[5])).reshape(3, 3).T
            t._Rn[:] = sync
        cp, cc = tp._in.residual_cost(), tc._in.residual_cost()
        assert cp == cc or (np.isnan(cp) and np.isnan(cc))
        okp, okc = tp._in.finish_pose(), tc._in.finish_pose()
        assert okp == okc == (k != 59)
        for a, b in ((tp.position, tc.position), (tp.rotation, tc.rotation), (np.array(tp.angles),
                                                                               np.array(tc.angles))):
            assert np.array_equal(a, b, equal_nan=True)
        if k == 59:
            continue
        u = np.array([np.cos(x[1]) * np.cos(x[0]), np.cos(x[1]) * np.sin(x[0]), -np.sin(x[1])])
        ref = 0.0
        for j in range(3):
            b = np.array(dipole_point(*(x[2] * u), *mom[3 * j:3 * j + 3], False)[:3])
            ref += np.sum(((Sc[3 * j:3 * j + 3] - sync.T @ b) * w[3 * j:3 * j + 3]) ** 2)
        assert cc == pytest.approx(ref, rel=1e-12)
        assert np.allclose(tc.position, point(x, tc._cbar), rtol=0, atol=0)


def test_moved_and_behind_decide_as_the_reference():
    """The refresh test (``moved``) and the hemisphere test (``behind``, acquiring or not) at seeded
    estimates around their thresholds (the last evaluation's point at about ``refresh`` x range,
    directions near the hemisphere's margin): the same decisions in both, and each decision
    against its definition in numpy: catches a range not squared or the acquisition's hemisphere
    taken while tracking."""
    rng = np.random.default_rng(29)
    tp, tc = _pair()
    hemi = np.array([0.3, -0.8, 0.5])
    seen = set()
    for k in range(400):
        x = np.array([rng.uniform(-3, 3), rng.uniform(-1.5, 1.5), rng.uniform(0.1, 0.6), 0.0, 0.0, 0.0])
        p = np.array(point(x, tp._cbar))
        d = rng.normal(size=3)
        pm = p + d / np.linalg.norm(d) * 0.02 * x[2] * rng.uniform(0.98, 1.02)
        S, cur, sigma = _case(rng)
        for t in (tp, tc):
            assert t._in.load(S, cur, sigma, hemi, None, None) == rio.OK
            for i in range(6):
                t._x[i] = x[i]
            for i in range(3):
                t._pm[i] = pm[i]
        m = tp._in.moved(0.02)
        assert m == tc._in.moved(0.02) == (np.sum((p - pm) ** 2) > (0.02 * x[2]) ** 2)
        u = (p - np.array(tp._cbar)) / x[2]
        for acq in (False, True):
            h = np.array(tp._in._acq) if acq else hemi
            b = tp._in.behind(acq)
            assert b == tc._in.behind(acq)
            assert b == (u @ h < -0.1 * np.linalg.norm(h)) or abs(u @ h + 0.1 * np.linalg.norm(h)) < 1e-12
            seen.add((m, b))
    assert seen == {(False, False), (False, True), (True, False), (True, True)}


def test_gated_warm_solves_equal_the_reference():
    """Whole solves with the residual gate on (0.99): warm starts near a seeded pose (the gate
    passes) and far from it with a distorted signal (the gate fails: a reacquisition), each on both
    cores: the same status, iterations, cost, pose and covariance, bit for bit (the gate's decision
    sees the same cost)."""
    from coiltrack.firmware.pose.solver import SOLVE_REACQUIRED

    coils = thesis_source().coils
    tp = RaabTracker(coils, gate_probability=0.99, core=fcore.PYTHON)
    tc = RaabTracker(coils, gate_probability=0.99, core=fcore.DEFAULT)
    rng = np.random.default_rng(31)
    flags = passed = 0
    for k in range(12):
        R, p = _rotation(rng), np.array([0.25, 0.1, 0.05]) + rng.uniform(-0.05, 0.05, 3)
        cur = np.array([1.0, 1.1, 0.9])
        S = np.zeros((3, 3))
        tp.predict_signals(p, R, cur, S)
        sigma = np.full((3, 3), 2e-9)
        S += rng.normal(0, 2e-9, (3, 3))
        if k % 3 == 2:
            S[:, 1] *= 1.3                          # a distorted coil: the residual fails the gate
        dR = _rotation(rng) if k % 4 == 3 else np.eye(3)
        x0p, x0R = p + rng.normal(0, 0.003, 3), R @ dR
        sp = tp.solve(S, cur, sigma, None, x0p, x0R)
        sc = tc.solve(S, cur, sigma, None, x0p, x0R)
        assert sp == sc
        flags |= sp
        assert (tp.iterations, tp.cost, tp.converged) == (tc.iterations, tc.cost, tc.converged)
        for a, b in ((tp.position, tc.position), (tp.rotation, tc.rotation), (tp.covariance, tc.covariance)):
            assert np.allclose(a, b, rtol=1e-12, atol=0)
        assert np.array_equal(tp.position, tc.position) and np.array_equal(tp.rotation, tc.rotation)
        passed += not sp & SOLVE_REACQUIRED and tp.cost > 0.0
    assert flags & SOLVE_REACQUIRED and passed
