"""The fusion filter's delayed magnetic update and its replay on the compiled core
(firmware_py/core/src/fusion.c: ct_fusion_evaluate, ct_fusion_rotvec_from_matrix,
ct_fusion_correct, ct_fusion_copy, ct_fusion_replay) against their Python reference
(estimate/fusion_measurement.py, fusion_state.InsState.correct / copy_from, and
magnetic_inertial.FusionFilter.step with fusion_prediction), and against independent
references: scipy's rotation vector and numpy's congruences for the measurement, filterpy's
Kalman update for one whole update. The 3x3 products the reference takes from BLAS are summed in
order in C, so states are compared to 1e-12 relative; discrete outcomes (flags, step counts,
ring positions, the time) exactly. Seeded; skips where the extension is not built."""
import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.estimate.ekf import EKF_OK
from coiltrack.firmware.estimate.layout import ORI, POSE_ORI, POSE_POS, PSI, QM, XI
from coiltrack.firmware.estimate.magnetic_inertial import FUS_REPLAY_LOST, FusionFilter, FusionParams
from coiltrack.firmware.estimate.orientation import OrientationFilter, OrientationParams
from coiltrack.hil.motion import HandMovedBench

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
COMPILED = core.load("compiled")


def _pair(model, fixed=True, imu_capacity=128):
    """The same filter on the Python core (reference) and on the compiled one; each with its own
    ch. 2 filter on the Python core (so the snapshots' Xi are the same to the bit)."""
    prm = FusionParams.from_config(None, measurement_model=model)
    out = []
    for c in (core.PYTHON, COMPILED):
        of = OrientationFilter(OrientationParams.from_config(None), core.PYTHON)
        out.append(FusionFilter(prm, of, imu_capacity=imu_capacity, fixed_source=fixed, core=c))
    ref, got = out
    assert ref._replay_ck is None and got._replay_ck is not None
    assert ref.sh.cs is None and got.sh.cs is not None and got.sn.cs is not None
    return ref, got


def _close(a, b, rel=1e-12, what=""):
    """``b`` equal to ``a`` within ``rel`` of ``a``'s largest element (or of 1)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape, what
    if a.size == 0:
        return
    tol = rel * max(float(np.abs(a).max()), 1.0)
    d = float(np.abs(b - a).max())
    assert d <= tol, f"{what}: differs by {d:.3g} (tolerance {tol:.3g})"


def _random_rotation(rng, angle=None):
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    return Rotation.from_rotvec(u * (rng.uniform(0, math.pi) if angle is None else angle)).as_matrix()


def _spd(rng, n, scale):
    M = rng.normal(size=(n, n))
    return scale * (M @ M.T + n * np.eye(n))


def _fill(ff, rng, Th, Phi, Xi):
    """One random shadow state and snapshot (the same in both filters: call with equal rng)."""
    sh, snap = ff.sh, ff.snap
    sh.p[:] = rng.normal(size=3) * 0.2
    sh.Th[:] = Th
    sh.P[:] = _spd(rng, ff.n, 1e-4)
    snap.Phi[:] = Phi
    snap.Xi[:] = Xi
    snap.XiP[:] = _spd(rng, 3, 1e-5)


@pytest.mark.parametrize("model", [1, 2, 3])
def test_evaluate_matches_the_reference_and_scipy(model):
    """ct_fusion_evaluate against the models' evaluate over 80 random states, snapshots and
    solutions, with orientation errors from tiny (the series branch of the rotation vector) to
    near pi (the axis from the symmetric part): y and every element of P equal to 1e-12. The
    innovation's orientation rows are scipy's rotation vector of Psi Theta^T and Xi Theta^T, its
    position rows Phi q - p, the white blocks Phi C_pp Phi^T s, Psi C_tt Psi^T s, Phi C_pt Psi^T s
    (numpy), so a transposed Phi, a dropped scale or a wrong sign near pi fails."""
    rng = np.random.default_rng(40 + model)
    ref, got = _pair(model)
    prm = ref.prm
    zl = ref.zlayout
    names = zl.names()
    for it in range(80):
        Phi = _random_rotation(rng)
        Th = _random_rotation(rng)
        kind = it % 4
        err = (1e-9, 0.3, math.pi - 1e-7, math.pi - 0.2)[kind]
        Rerr = _random_rotation(rng, err)
        R_ms = Phi.T @ Rerr @ Th            # Psi = Phi R_ms = Rerr Theta: log(Psi Theta^T) = log(Rerr)
        Xi = _random_rotation(rng, (1e-9, 0.1, math.pi - 1e-6, 2.0)[kind]) @ Th
        q = rng.normal(size=3) * 0.3
        C = _spd(rng, 6, 1e-6)
        seed = int(rng.integers(1 << 30))
        for ff in (ref, got):
            _fill(ff, np.random.default_rng(seed), Th, Phi, Xi)
        ref.meas.evaluate(ref.sh, ref.snap, q, R_ms, C, memoryview(ref.upd.y))
        got._evaluate(q, R_ms, C)
        _close(ref.upd.y, got.upd.y, what="y")
        _close(ref.sh.P, got.sh.P, what="P")
        # the independent references
        y, P, s = got.upd.y, got.sh.P, prm.mag_var_scale
        np.testing.assert_allclose(y[zl.ZP], Phi @ q - got.sh.p, rtol=0, atol=1e-14)
        Psi = Phi @ R_ms
        for row, Z in (("ZPSI", Psi), ("ZXI", Xi)):
            if row in names:
                rv = Rotation.from_matrix(Z @ Th.T).as_rotvec()
                if np.linalg.norm(rv) > math.pi - 1e-6:      # the same rotation either way round
                    rv = rv if np.dot(rv, y[getattr(zl, row)]) > 0 else -rv
                np.testing.assert_allclose(y[getattr(zl, row)], rv, rtol=0, atol=1e-7, err_msg=row)
        Cpp, Cpt, Ctt = C[POSE_POS, POSE_POS], C[POSE_POS, POSE_ORI], C[POSE_ORI, POSE_ORI]
        # models 2-3 with the magnetic orientation: the realized rotation margin (pose.covariance
        # RotationMargin.realized_into) in numpy, |theta|^2 the innovation's, capped at 1 rad^2
        M = np.zeros((3, 3))
        if "ZPSI" in names and got.meas.xi_model:
            t2, tr = min(float(y[zl.ZPSI] @ y[zl.ZPSI]), 1.0), float(np.trace(Ctt))
            if t2 > tr:
                M = 0.25 * (t2 - tr) * (Cpt @ np.linalg.inv(Ctt) @ Cpt.T + 2.0 / tr * Cpt @ Cpt.T)
        np.testing.assert_allclose(P[QM, QM], Phi @ (Cpp + M) @ Phi.T * s, rtol=1e-12, atol=1e-20)
        if "ZPSI" in names:
            np.testing.assert_allclose(P[PSI, PSI], Psi @ Ctt @ Psi.T * s, rtol=1e-12, atol=1e-20)
            np.testing.assert_allclose(P[QM, PSI], Phi @ Cpt @ Psi.T * s, rtol=1e-12, atol=1e-20)
            np.testing.assert_allclose(P[PSI, QM], (Phi @ Cpt @ Psi.T * s).T, rtol=1e-12, atol=1e-20)
        else:
            np.testing.assert_array_equal(P[PSI, PSI], np.eye(3) * prm.psi_sigma ** 2)
            np.testing.assert_array_equal(P[QM, PSI], 0.0)
        if "ZXI" in names:
            floor = np.diag([prm.xi_sigma_floor ** 2, prm.xi_sigma_floor ** 2, prm.xi_heading_sigma_floor ** 2])
            np.testing.assert_allclose(P[XI, XI], got.snap.XiP * prm.xi_var_scale + floor, rtol=1e-14)


def test_evaluate_takes_arrays_lists_and_transposed_views():
    """The solution may come as any float64 array (a transposed view too), an integer array or
    nested lists: the same result; a wrong size is refused with a message naming the argument."""
    rng = np.random.default_rng(47)
    _, got = _pair(3)
    Th, Phi = _random_rotation(rng), _random_rotation(rng)
    _fill(got, rng, Th, Phi, Th)
    q, R, C = rng.normal(size=3), _random_rotation(rng), _spd(rng, 6, 1e-6)
    got._evaluate(q, R, C)
    y0, P0 = got.upd.y.copy(), got.sh.P.copy()
    for args in ((list(q), R.tolist(), C.tolist()), (q, np.asfortranarray(R), C.T.T), (q, R.T.copy().T, C)):
        got._evaluate(*args)
        np.testing.assert_array_equal(got.upd.y, y0)
        np.testing.assert_array_equal(got.sh.P, P0)
    qi = np.array([1, -2, 3])                           # an integer array is read as numbers
    got._evaluate(qi, R, C)
    yi = got.upd.y.copy()
    got._evaluate(qi.astype(float), R, C)
    np.testing.assert_array_equal(got.upd.y, yi)
    with pytest.raises(TypeError, match="R_ms"):
        got._evaluate(q, np.eye(2), C)
    with pytest.raises(TypeError, match="C"):
        got._evaluate(q, R, np.eye(5))


def test_correct_and_copy_match_the_reference():
    """ct_fusion_correct against InsState.correct (random corrections, rotations from 1e-9 rad
    to near pi, 300 chained): p, v, offsets, Theta to 1e-12; ct_fusion_copy gives the other
    state's arrays and time to the bit."""
    rng = np.random.default_rng(48)
    ref, got = _pair(3)
    Th = _random_rotation(rng)
    for ff in (ref, got):
        _fill(ff, np.random.default_rng(1), Th, np.eye(3), np.eye(3))
        ff.sh.v[:] = (0.1, 0.2, -0.3)
        ff.sh.ba[:] = (0.01, 0.0, -0.02)
        ff.sh.bg[:] = (0.001, -0.002, 0.0)
    dx = np.zeros(ref.n)
    for i in range(300):
        dx[:] = rng.normal(size=ref.n) * 1e-3
        u = rng.normal(size=3)
        dx[ORI] = u / np.linalg.norm(u) * (1e-9, 1e-3, 1.0, math.pi - 1e-6)[i % 4]
        ref.sh.correct(dx)
        got.sh.correct(memoryview(dx))
    for name in ("p", "v", "Th", "ba", "bg", "P"):
        _close(getattr(ref.sh, name), getattr(got.sh, name), what=name)
    np.testing.assert_allclose(got.sh.Th @ got.sh.Th.T, np.eye(3), atol=1e-12)
    got.sh.t_us = 123_456
    got.st.copy_from(got.sh)
    for name in ("p", "v", "Th", "ba", "bg", "P"):
        np.testing.assert_array_equal(getattr(got.st, name), getattr(got.sh, name))
    assert got.st.t_us == 123_456


def test_one_update_matches_filterpy():
    """prepare and apply of one delayed update on the compiled core against filterpy's
    KalmanFilter.update (Joseph form) on the same H, R, innovation and prior: the correction
    applied to the shadow and its posterior covariance to 1e-10 relative."""
    rng = np.random.default_rng(49)
    _, got = _pair(3)
    Th, Phi = _random_rotation(rng), _random_rotation(rng)
    _fill(got, rng, Th, Phi, _random_rotation(rng, 0.01) @ Th)
    got.sh.P.fill(0.0)                      # the white states carry no cross-covariance (A's zero rows)
    got.sh.P[:15, :15] = _spd(rng, 15, 1e-5)
    q = Phi.T @ got.sh.p + rng.normal(size=3) * 1e-3
    R_ms = Phi.T @ _random_rotation(rng, 0.01) @ Th
    C = _spd(rng, 6, 1e-7)
    got._evaluate(q, R_ms, C)
    kf = KalmanFilter(dim_x=got.n, dim_z=got.m)
    kf.x = np.zeros(got.n)
    kf.P = got.sh.P.copy()
    kf.H = got.upd.H.copy()
    kf.R = got.upd.R.copy()
    p0 = got.sh.p.copy()
    kf.update(got.upd.y.copy())
    assert got.upd.update(got.sh.P, math.inf) == EKF_OK
    got.sh.correct(got.upd.dx)
    np.testing.assert_allclose(got.upd.dx, kf.x, rtol=0, atol=1e-10 * np.abs(kf.x).max())
    np.testing.assert_allclose(got.sh.P, kf.P, rtol=0, atol=1e-10 * np.abs(kf.P).max())
    np.testing.assert_allclose(got.sh.p, p0 + kf.x[:3], rtol=0, atol=1e-15)


# ------------------------------------------------------------------ the replay

_TRAJ = HandMovedBench(seed=3, duration_s=10, v_max=0.12, w_max_deg=40.0)
_G = np.array([0.0, 0.0, -9.81])
_EARTH = np.array([20e-6, 0.0, -45e-6])


class _Run:
    """Both filters fed the same IMU samples (irregular steps, so the step-dependent blocks are
    rewritten), the same Phi (a turning source unless fixed) and the same magnetic solutions
    (the truth moved by a fixed error), each stage compared."""

    def __init__(self, model, fixed, imu_capacity=128, seed=50, rel=1e-12):
        rng = np.random.default_rng(seed)
        self.ref, self.got = _pair(model, fixed, imu_capacity)
        self.rel = rel
        self.lost = 0
        self.i = 0
        t = 1000 + np.cumsum(rng.integers(700, 1400, size=4000))
        k = _TRAJ.kinematics(t)
        ang = 0.0 if fixed else 0.3 * np.sin(t * 1e-6)
        Phi = Rotation.from_rotvec(np.outer(ang * np.ones(t.size), [0.0, 0.0, 1.0])).as_matrix()
        Rg = Phi @ k.R                                           # sensor orientation in G
        a = np.einsum("nij,nj->ni", Phi, k.acceleration) - _G
        self.t_us = t
        self.f = np.einsum("nji,nj->ni", Rg, a) + rng.normal(0, 0.01, (t.size, 3))
        self.w = k.angular_velocity + 0.005 + rng.normal(0, 0.005, (t.size, 3))
        self.m = np.einsum("nji,j->ni", Rg, _EARTH)
        self.Phi = Phi
        self.rsrc = (0.0, 0.0, 9.81)              # the source's specific force in G (it does not accelerate)

    @property
    def t(self):
        return int(self.t_us[self.i - 1]) if self.i else 0

    def push(self):
        i = self.i
        self.i += 1
        t = int(self.t_us[i])
        f, w, m, Phi = self.f[i], self.w[i], self.m[i], self.Phi[i]
        for ff in (self.ref, self.got):
            of = ff.snap.xi_filter
            if not of.initialized:
                of.initialize(t, *f, *m)
            else:
                of.predict(t, *w)
                of.update_acc(*f)
                of.update_mag(*m)
            ff.push_imu(t, *f, *w, *self.rsrc, Phi)
        return t

    def solution(self, t_ref):
        k = _TRAJ.kinematics(np.array([t_ref]))
        C = np.diag([4e-6, 3e-6, 5e-6, 1e-4, 1.2e-4, 0.8e-4])
        C[0, 4] = C[4, 0] = 2e-6
        R = k.R[0] @ Rotation.from_rotvec([0.004, -0.006, 0.003]).as_matrix()
        return t_ref, k.position[0] + [0.002, -0.001, 0.0015], R, C

    def check_step(self, what):
        """The cheap part of :meth:`check`, after every replay step: the shadow and the counters."""
        a, b = self.ref, self.got
        assert (a.sh.t_us, a.steps, a.sh.pred.count, a.replaying, a.last_flags, len(a.history.shadow)) == \
               (b.sh.t_us, b.steps, b.sh.pred.count, b.replaying, b.last_flags, len(b.history.shadow)), what
        _close(a.sh.P, b.sh.P, rel=self.rel, what=f"{what}: sh.P")
        _close(a.sh.p, b.sh.p, rel=self.rel, what=f"{what}: sh.p")

    def check(self, what):
        a, b = self.ref, self.got
        for name in ("p", "v", "Th", "ba", "bg", "P"):
            for st in ("st", "sh", "sn"):
                _close(getattr(getattr(a, st), name), getattr(getattr(b, st), name), rel=self.rel, what=f"{what}: {st}.{name}")
        for st in ("st", "sh", "sn"):
            assert getattr(a, st).t_us == getattr(b, st).t_us, (what, st)
        assert (a.sh.dt_last, a.sh.ka, a.sh.kg) == (b.sh.dt_last, b.sh.ka, b.sh.kg), what
        assert a.sh.pred.count == b.sh.pred.count and a.st.pred.count == b.st.pred.count, what
        assert (a.steps, a.updates, a.rejected, a.replays_lost, a.last_flags, a.replaying, a.initialized) == \
               (b.steps, b.updates, b.rejected, b.replays_lost, b.last_flags, b.replaying, b.initialized), what
        assert (a.snap.pending, a.snap.valid, a.snap.t, a.snap.xi) == (b.snap.pending, b.snap.valid, b.snap.t, b.snap.xi)
        for name in ("Phi", "Xi", "XiP", "XiB"):
            _close(getattr(a.snap, name), getattr(b.snap, name), rel=self.rel, what=f"{what}: snap.{name}")
        for h in ("live", "shadow"):
            ra, rb = getattr(a.history, h), getattr(b.history, h)
            assert len(ra) == len(rb) and ra.slot(0) == rb.slot(0), (what, h)
            used = [ra.slot(i) for i in range(len(ra))]
            np.testing.assert_array_equal(ra.t[used], rb.t[used], err_msg=f"{what}: history {h}")
            _close(ra.d[used], rb.d[used], rel=self.rel, what=f"{what}: history {h}")

    def run(self, t_end, budget, period_us=300_000, delay_us=90_000, every=1):
        """Bursts every ``period_us``: the snapshot scheduled ahead of the stream (while a replay
        runs, so the shadow takes it), the solution ``delay_us`` after t_ref, then ``budget``
        replay steps every ``every`` samples."""
        pending = []
        next_burst = 250_000
        n = 0
        while self.t < t_end:
            t = self.push()
            n += 1
            if t >= next_burst - 40_000 and next_burst not in [p for p, _ in pending]:
                t_ref = next_burst + 333                    # off the sample grid: a split step
                for ff in (self.ref, self.got):
                    ff.schedule_snapshot(t_ref)
                pending.append((next_burst, t_ref))
                next_burst += period_us
            for burst, t_ref in list(pending):
                if t >= t_ref + delay_us:
                    pending.remove((burst, t_ref))
                    sol = self.solution(t_ref)
                    for ff in (self.ref, self.got):
                        ff.finish()
                    fa = self.ref.begin_magnetic_update(*sol)
                    fb = self.got.begin_magnetic_update(*sol)
                    assert fa == fb, (t, fa, fb)
                    self.check(f"update at {t}")
            if (self.ref.replaying or self.got.replaying) and n % every == 0:
                da, db = self.ref.step(budget), self.got.step(budget)
                assert (da, self.ref.last_step_units) == (db, self.got.last_step_units), t
                self.check(f"replay end at {t}") if da else self.check_step(f"replay step at {t}")
        self.lost = self.got.replays_lost


@pytest.mark.parametrize("model, fixed, budget", [(1, True, 8), (3, False, 3), (2, True, 1), (3, True, 50)])
def test_replay_matches_the_reference(model, fixed, budget):
    """FusionFilter.step on the compiled core (one ct_fusion_replay call, resumed once after a
    snapshot taken inside the replay) against the Python loop, from the first solution over
    1.5 s of irregular IMU steps: after every update and every replay step the live, shadow and
    snapshot states agree to 1e-12, and the times, step counts, the replay's units, the flags, the
    step-dependent blocks and both pose histories (slots, times, rows) are the same."""
    r = _Run(model, fixed)
    r.run(1_500_000, budget)
    assert r.got.updates >= 3 and r.got.steps > 1000
    assert r.got.initialized


def test_replay_through_a_snapshot_inside_it():
    """A snapshot scheduled while a slow replay (1 step per sample) runs is taken by the shadow
    when it crosses t_ref (``REPLAY_SNAPSHOT``: the sample split there), on both cores alike."""
    r = _Run(3, False)
    taken = []
    ck = r.got._replay_ck
    run0 = ck.run

    def run(budget):
        before = r.got.snap.pending
        rc = run0(budget)
        taken.append(before and not r.got.snap.pending)
        return rc

    ck.run = run
    r.run(1_300_000, 1)
    assert any(taken)


def test_a_replay_that_loses_its_samples_ends_alike():
    """An IMU ring too short for a slow replay: the sample before the next one leaves the ring
    and the replay ends with FUS_REPLAY_LOST, on both cores at the same step."""
    r = _Run(3, True, imu_capacity=40)
    flags = []
    step0 = r.got.step

    def step(budget):
        done = step0(budget)
        flags.append(r.got.last_flags)
        return done

    r.got.step = step
    r.run(1_000_000, 1, delay_us=20_000, every=3)
    assert r.got.replays_lost > 0 and r.ref.replays_lost == r.got.replays_lost
    assert any(f & FUS_REPLAY_LOST for f in flags)


def test_the_recorder_keeps_the_python_replay():
    """The offline recorder's per-step hook runs in the Python loop: attaching one unbinds the
    compiled replay (chosen once then)."""
    _, got = _pair(3)
    got.attach_recorder(object())
    assert got._replay_ck is None


@pytest.mark.parametrize("budget", [1, 2])
def test_the_live_split_step_is_the_python_split_bit_for_bit(budget):
    """The live state's step split at a pending snapshot (``FusionFilter._advance`` through the
    replay kernel bound to the live state, ``_live_ck``: ``split_take`` with the snapshot taken
    inside the call, ``run`` where the shadow is the one to take it) against the same compiled filter taking
    the Python split (``_propagate``, ``history``, ``Snapshot.take`` one by one): every state, the
    snapshot (Phi, Xi, its covariance and offset) and both histories equal to the bit after every
    update and replay step, while the live state takes the snapshot (a replay of 2 steps a sample
    catches up before the next burst) and while the shadow does (1 step a sample: the replay
    runs when the live state crosses t_ref, which only splits its step there)."""
    r = _Run(3, False, rel=0.0)
    ref = FusionFilter(r.got.prm, OrientationFilter(OrientationParams.from_config(None), core.PYTHON),
                       fixed_source=False, core=COMPILED)
    ref._live_ck = None
    r.ref = ref
    split = []
    ck = r.got._live_ck
    run0 = ck.run

    def run(budget, take=True):
        split.append(take)
        return run0(budget, take)

    ck.run = run
    take0 = ck.split_take

    def split_take():
        split.append(True)
        take0()

    ck.split_take = split_take
    r.run(1_300_000, budget)
    assert split and all(take == (budget == 2) for take in split)
    assert r.got.updates >= 3


def _history(rng, cap, n, head):
    """A pose history (the live ring) of ``n`` entries ending before slot ``head`` (wrapped), random
    poses, times 900-1100 us apart."""
    from coiltrack.firmware.estimate.fusion_output import PoseHistory
    h = PoseHistory(cap, core.PYTHON)
    live = h.live
    t = 5000
    for _ in range(cap + head - n if n < cap else head):
        live.push(t)
        t += 1000
    live.clear()
    for _ in range(cap):                 # fill, then trim to n entries ending at head
        live.push(0)
    live.clear()
    live._head = (head - n) % cap
    for _ in range(n):
        k = live.push(t)
        live.d[k] = rng.normal(size=live.width)
        t += int(rng.integers(900, 1100))
    assert live.slot(len(live)) % cap == head % cap or len(live) == cap
    return h


def test_pose_at_matches_the_reference():
    """ct_fusion_pose_at (``PoseHistory.pose_at`` on the compiled core, bound to the live ring)
    against the reference over wrapped and unwrapped rings of 0 to full entries: the same answer
    for instants before, at and after every entry, between entries and at the ends, and the
    interpolated pose equal to the bit; the interpolation itself checked against numpy's."""
    from coiltrack.firmware.estimate.fusion_output import PoseHistory
    rng = np.random.default_rng(71)
    cap = 16
    for n, head in ((0, 0), (1, 5), (2, 0), (7, 3), (16, 9), (16, 0), (12, 14)):
        ref = _history(rng, cap, n, head)
        got = PoseHistory(cap, COMPILED)
        np.copyto(got.live.t, ref.live.t)
        np.copyto(got.live.d, ref.live.d)
        got.live._head, got.live._count = ref.live._head, ref.live._count
        times = [int(ref.live.tv[ref.live.slot(i)]) for i in range(n)]
        queries = [0, 10**9] + [t + d for t in times for d in (-1, 0, 1, 357)]
        for t in queries:
            pa, Ra = np.full(3, 7.0), np.full((3, 3), 7.0)
            pb, Rb = np.full(3, 7.0), np.full((3, 3), 7.0)
            oa = ref.pose_at(t, pa, memoryview(Ra))
            ob = got.pose_at(t, pb, Rb)
            assert oa == ob, (n, head, t)
            np.testing.assert_array_equal(pa, pb)
            np.testing.assert_array_equal(Ra, Rb)
            if ob:
                i = next(i for i, ti in enumerate(times) if ti >= t)
                i = max(i, 1)
                t0, t1 = times[i - 1], times[i]
                a = (t - t0) / (t1 - t0)
                d0, d1 = ref.live.d[ref.live.slot(i - 1)], ref.live.d[ref.live.slot(i)]
                np.testing.assert_allclose(pb, (1 - a) * d0[0:3] + a * d1[0:3], rtol=1e-14, atol=1e-15)
                np.testing.assert_allclose(Rb.ravel(), (1 - a) * d0[3:12] + a * d1[3:12], rtol=1e-14, atol=1e-15)
    assert not got.pose_at(0, np.zeros(3), np.zeros((3, 3)))


@pytest.mark.parametrize("fixed", [True, False])
def test_snapshot_aux_matches_the_reference(fixed):
    """ct_fusion_snap_aux (``Snapshot.take_aux`` on the compiled core) against the reference on
    random ch. 2 filter states and IMU rows: Phi (the ring row's, or the identity for a fixed
    source), Xi, its global covariance ``R P_tt R^T`` and the offset equal to the bit, and the
    covariance against numpy's product; an uninitialised filter leaves Xi alone in both."""
    from coiltrack.firmware.estimate.fusion_snapshot import Snapshot
    from coiltrack.firmware.estimate.fusion_state import FixedSource, MovingSource
    from coiltrack.firmware.estimate.layout import THETA
    rng = np.random.default_rng(72)
    frame = FixedSource() if fixed else MovingSource()
    imu_d = rng.normal(size=(8, _core.IMU_WIDTH))
    for trial in range(30):
        xi = OrientationFilter(OrientationParams.from_config(None), core.PYTHON)
        if trial % 5:
            xi.initialize(1000, 0.1, 0.2, 9.8, 20.0, 1.0, -40.0)
            xi.R[:] = _random_rotation(rng, math.pi * (1 - 1e-9) if trial == 1 else None)
            xi.P[:] = _spd(rng, xi.P.shape[0], 1e-3)
            xi.bias[:] = rng.normal(size=3) * 1e-3
        a, b = Snapshot(24, frame, xi), Snapshot(24, frame, xi)
        b.bind(imu_d, COMPILED)
        assert b.take_aux != a.take_aux
        k = int(rng.integers(0, 8))
        a.take_aux(memoryview(imu_d), k, trial % 2 == 0)
        b.take_aux(memoryview(imu_d), k, trial % 2 == 0)
        for name in ("Phi", "Xi", "XiP", "XiB"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert (a.xi, a.pending, a.valid, a.initialized) == (b.xi, b.pending, b.valid, b.initialized)
        assert b.xi == bool(trial % 5)
        if b.xi:
            t0 = THETA.start
            np.testing.assert_allclose(b.XiP, xi.R @ xi.P[t0:t0 + 3, t0:t0 + 3] @ xi.R.T, rtol=1e-13, atol=1e-18)
        np.testing.assert_array_equal(b.Phi, np.eye(3) if fixed else imu_d[k, 9:18].reshape(3, 3))


def test_motion_cov_matches_the_reference():
    """ct_fusion_motion_cov (``SensorInertial.motion_cov`` on the compiled core) against the
    reference, compensated or not, the filter initialised or not, a NaN covariance too: every
    element equal to the bit; the added diagonal against the closed form of its docstring."""
    from coiltrack.firmware.config import FirmwareConfig
    from coiltrack.firmware.track.burst_fusion import FixedSource as FixedSrc
    from coiltrack.firmware.track.burst_fusion import PulseGate, SensorInertial
    cfg = FirmwareConfig()
    gate = PulseGate(np.zeros(3, dtype=np.int64), np.zeros(3, dtype=np.int64), 0, 0)
    ref = SensorInertial(1, cfg, gate, FixedSrc(cfg), core=core.PYTHON)
    got = SensorInertial(1, cfg, gate, FixedSrc(cfg), core=COMPILED)
    assert got.motion_cov != got.__class__.motion_cov.__get__(got)
    rng = np.random.default_rng(73)
    for trial in range(40):
        P = _spd(rng, ref.fusion.n, 1e-3)
        v, w = rng.normal(size=3), rng.normal(size=3)
        if trial == 7:
            P[3, 3] = float("nan")
        for ins in (ref, got):
            np.copyto(ins.fusion.st.P, P)
            np.copyto(ins.fusion.st.v, v)
            np.copyto(ins.w_last, w)
            ins.fusion.initialized = trial % 3 != 0
        C = _spd(rng, 6, 1e-5)
        p = rng.normal(size=3) * 0.3
        for comp in (False, True):
            oa, ob = np.zeros((6, 6)), np.zeros((6, 6))
            ref.motion_cov(C, comp, oa, p)
            got.motion_cov(C, comp, ob, p)
            np.testing.assert_array_equal(oa, ob)
            tr2 = ref.burst_rms_s ** 2
            if comp:
                ap, ao = np.trace(P[3:6, 3:6]) / 3.0 * tr2, 0.0
            else:
                ao = float(w @ w) * tr2
                ap = (float(v @ v) * tr2 if trial % 3 else 0.0) + float(p @ p) * ao
            if trial != 7 or not comp:
                np.testing.assert_allclose(np.diag(ob - C), [ap] * 3 + [ao] * 3, rtol=1e-12, atol=1e-30)


class _Signals:
    """A stand-in for the re-solve's solver: ``predict_signals`` a smooth function of the pose (the
    compensation only needs the same numbers in both cores), evaluations counted."""

    def __init__(self, n):
        self.n = n
        self.calls = 0

    def predict_signals(self, p, R, currents, out):
        self.calls += 1
        p, R = np.asarray(p), np.asarray(R)
        for j in range(self.n):
            out[:, j] = R.T @ (p * (j + 1.0) + currents[j]) + 1e-3 * np.sin(p.sum() * (j + 2))


def test_compensation_matches_the_reference():
    """``SensorInertial.compensate_begin`` / ``compensate_step`` on the compiled core
    (ct_fusion_comp_begin: the copy, the velocity check and the pose at t_ref; ct_fusion_pose_at
    per pulse; ct_fusion_comp_add) against the reference over random histories and bursts: the
    same answers (compensated, not initialised, a velocity too uncertain, t_ref or a pulse outside
    the history: -1 and the signals as measured) at every budget, and the compensated signals
    equal to the bit; with a still history the compensation changes nothing."""
    from coiltrack.firmware.config import FirmwareConfig
    from coiltrack.firmware.track.burst_fusion import FixedSource as FixedSrc
    from coiltrack.firmware.track.burst_fusion import PulseGate, SensorInertial
    cfg = FirmwareConfig()
    gate = PulseGate(np.zeros(3, dtype=np.int64), np.zeros(3, dtype=np.int64), 0, 0)
    ref = SensorInertial(1, cfg, gate, FixedSrc(cfg), core=core.PYTHON)
    got = SensorInertial(1, cfg, gate, FixedSrc(cfg), core=COMPILED)
    assert got.compensate_step != got.__class__.compensate_step.__get__(got)
    n = ref.S_comp.shape[1]
    rng = np.random.default_rng(74)
    outcomes = set()
    for trial in range(60):
        still = trial == 5
        P = _spd(rng, ref.fusion.n, 1e-5 if trial % 7 else 1e-1)        # every 7th: velocity too uncertain
        t = np.cumsum(rng.integers(900, 1100, size=40)) + 10_000
        rows = rng.normal(size=(40, 12)) * (0.0 if still else 0.01)
        rows[:, 0:3] += [0.1, 0.2, 0.3]
        for ins in (ref, got):
            np.copyto(ins.fusion.st.P, P)
            ins.fusion.initialized = trial % 11 != 3
            live = ins.fusion.history.live
            live.clear()
            for k in range(40):
                live.d[live.push(int(t[k]))] = rows[k]
        S = rng.normal(size=(3, n))
        currents = rng.normal(size=n)
        t_ref = int(t[20]) + 17 if trial % 13 != 4 else int(t[-1]) + 5     # every 13th: beyond the history
        pulse_t = np.array([int(t[5]) + 3, int(t[20]), int(t[33]) + 400 if trial % 9 != 2 else int(t[0]) - 50],
                           dtype=np.int64)
        budget = int(rng.integers(1, 3 * n + 1))
        res = []
        for ins in (ref, got):
            sig = _Signals(n)
            ins.t_ref = t_ref
            r = [ins.compensate_begin(sig, S, currents)]
            if r[0]:
                r.append(0)
                while r[-1] == 0:
                    r.append(ins.compensate_step(sig, S, currents, memoryview(pulse_t), budget))
            res.append((r, ins.S_comp.copy(), ins.compensated, sig.calls))
        (ra, Sa, ca, na), (rb, Sb, cb, nb) = res
        assert ra == rb and ca == cb and na == nb, (trial, ra, rb)
        np.testing.assert_array_equal(Sa, Sb)
        outcomes.add(ra[-1] if ra[0] else "no")
        if not ra[0] or ra[-1] == -1:
            np.testing.assert_array_equal(Sb, S)
        elif still:
            np.testing.assert_allclose(Sb, S, rtol=0, atol=1e-15)
    assert outcomes == {"no", -1, 1}


def test_history_rewind_and_commit_match_the_reference():
    """ct_fusion_hist_copy (``PoseHistory.rewind_shadow`` and ``commit`` on the compiled core) against
    the reference's ``Ring.copy_from`` and ``drop_newer_than`` over wrapped and unwrapped histories and
    rewinds before, at, between and after the entries: the same arrays, heads and counts."""
    from coiltrack.firmware.estimate.fusion_output import PoseHistory
    rng = np.random.default_rng(75)
    cap = 16
    for n, head in ((0, 0), (1, 5), (7, 3), (16, 9), (12, 14)):
        ref = _history(rng, cap, n, head)
        got = PoseHistory(cap, COMPILED)
        assert got.rewind_shadow != PoseHistory.rewind_shadow.__get__(got)
        times = [int(ref.live.tv[ref.live.slot(i)]) for i in range(n)]
        t0, d0, hc0 = ref.live.t.copy(), ref.live.d.copy(), (ref.live._head, ref.live._count)
        for t in [0, 10**9] + [x + d for x in times for d in (-1, 0, 1)]:
            for h in (ref, got):
                np.copyto(h.live.t, t0)
                np.copyto(h.live.d, d0)
                h.live._head, h.live._count = hc0
                h.shadow.clear()
                h.rewind_shadow(t)
            for name in ("t", "d"):
                np.testing.assert_array_equal(getattr(ref.shadow, name), getattr(got.shadow, name))
            assert (ref.shadow._head, ref.shadow._count) == (got.shadow._head, got.shadow._count), (n, head, t)
            assert len(got.shadow) == sum(1 for x in times if x <= t)
            for h in (ref, got):                 # a replay pushes onto the shadow, then commits it
                h.shadow.d[h.shadow.push(t + 5)] = 0.5
                h.commit()
            for name in ("t", "d"):
                np.testing.assert_array_equal(getattr(ref.live, name), getattr(got.live, name))
            assert (ref.live._head, ref.live._count) == (got.live._head, got.live._count)


@pytest.mark.parametrize("gap", [0, 8, 16, 504, 512, 520, 2048, 4080])
def test_history_copy_is_exact_at_every_distance_modulo_4k(gap):
    """ct_fusion_hist_copy copies backwards where the destination lies just above the source modulo
    4 KiB (against 4K aliasing) and with memcpy elsewhere: both ways the shadow is the live ring's
    copy, byte for byte, with the reference's head and count (``Ring.copy_from``,
    ``drop_newer_than``); then ``commit`` the other way round. The arrays are carved out of one
    buffer so that the shadow's lie ``gap`` bytes (modulo 4096) above the live ones."""
    rng = np.random.default_rng(76)
    cap, w = 64, 12
    nt, nd = cap * 8, cap * w * 8
    buf = np.zeros(8 * 4096 + nd, dtype=np.uint8)
    base = (-buf.ctypes.data) % 4096            # live_t at a 4 KiB boundary

    def carve(off, nbytes, dtype):
        return buf[base + off:base + off + nbytes].view(dtype)
    lt, ld = carve(0, nt, np.int64), carve(4096, nd, np.float64).reshape(cap, w)
    st, sd = carve(3 * 4096 + gap, nt, np.int64), carve(5 * 4096 + gap, nd, np.float64).reshape(cap, w)
    assert ((st.ctypes.data - lt.ctypes.data) % 4096, (sd.ctypes.data - ld.ctypes.data) % 4096) == (gap, gap)
    lhc, shc = np.array([37, 50], dtype=np.int64), np.zeros(2, dtype=np.int64)
    lt[:] = np.arange(cap) * 1000
    lt[:] = np.roll(lt, 37 - 50 + cap)           # oldest at slot 37 - 50 (mod cap)
    ld[:] = rng.normal(size=(cap, w))
    hc = _core.HistCopy(lt, ld, lhc, st, sd, shc)
    first = (37 - 50) % cap
    t_ref = int(lt[(first + 20) % cap])
    hc.rewind(t_ref)
    np.testing.assert_array_equal(st, lt)
    np.testing.assert_array_equal(sd, ld)
    assert list(shc) == [(first + 21) % cap, 21]
    sd[:] = rng.normal(size=(cap, w))
    st[:] = rng.integers(0, 10**6, size=cap)
    hc.commit()
    np.testing.assert_array_equal(lt, st)
    np.testing.assert_array_equal(ld, sd)
    assert list(lhc) == list(shc)


@pytest.mark.parametrize("model", [1, 2, 3])
def test_one_call_update_is_the_three_calls_bit_for_bit(model):
    """``ext.FusionUpdate`` (``fusion_replay.CompiledUpdate``: ``FusionFilter._restore`` and
    ``_update_shadow`` in one call each) against the filter's own methods run as the reference
    composes them (``InsState.copy_from``, ``PoseHistory.rewind_shadow``, the model's evaluate,
    ``KalmanUpdate.update``, ``InsState.correct``) on a copy of the same filter: the shadow, its
    history, ``y``, ``dx``, the NIS, the flags and the counts the same to the bit, over 40 updates
    (the symmetrisation of every 16th accepted one included, a gated one among them)."""
    from coiltrack.firmware.estimate.fusion_replay import CompiledUpdate
    rng = np.random.default_rng(77 + model)
    _, got = _pair(model)
    assert CompiledUpdate.fits(got) and got._restore.__self__.__class__ is CompiledUpdate
    ring = got.history.live
    for i in range(ring.capacity + 5):                 # a full, wrapped live history
        ring.d[ring.push(1000 * i)] = rng.normal(size=ring.width)
    ref = FusionFilter(got.prm, OrientationFilter(OrientationParams.from_config(None), core.PYTHON),
                       fixed_source=True, core=COMPILED)
    arrays = [(ref.sh, got.sh, ("p", "v", "Th", "ba", "bg", "P")), (ref.snap.st, got.snap.st, ("p", "v", "Th", "ba", "bg", "P")),
              (ref.snap, got.snap, ("Phi", "Xi", "XiP")), (ref.history.live, got.history.live, ("t", "d", "hc")),
              (ref.history.shadow, got.history.shadow, ("t", "d", "hc")), (ref.upd, got.upd, ("H", "R"))]
    for a, b, names in arrays:
        for name in names:
            np.copyto(getattr(a, name), getattr(b, name))
    gated = 0
    for k in range(40):
        Th = _random_rotation(rng)
        _fill(got, rng, Th, _random_rotation(rng, 0.01), _random_rotation(rng, 0.02) @ Th)
        P = _spd(rng, got.n, 1e-3)
        for w in [sl for name, sl in ((nm, getattr(got.layout, nm)) for nm in got.layout.names())
                  if name in ("QM", "PSI", "XI")]:
            keep = P[w, w].copy()
            P[w, :] = 0.0                        # white states: no cross-covariance (A's zero rows)
            P[:, w] = 0.0
            P[w, w] = keep
        got.snap.st.P[:] = P
        got.snap.st.Th[:] = Th
        got.snap.st.p[:] = rng.normal(size=3) * 0.2
        got.snap.st.t_us = 5000 + 1000 * k
        for a, b, names in arrays[:3]:
            for name in names:
                np.copyto(getattr(a, name), getattr(b, name))
        ref.snap.st.t_us = got.snap.st.t_us
        q = got.snap.Phi.T @ (got.snap.st.p + rng.normal(size=3) * (0.01 if k != 7 else 5.0))   # (k 7: gated)
        R = got.snap.Phi.T @ _random_rotation(rng, 0.02) @ Th
        C = _spd(rng, 6, 1e-6)
        t_ref = int(got.history.live.t[got.history.live.slot(rng.integers(0, 100))])
        FusionFilter._restore(ref, t_ref, q, R, C)
        got._restore(t_ref, q, R, C)
        fa = FusionFilter._update_shadow(ref)
        fb = got._update_shadow()
        gated += fa != EKF_OK
        assert fa == fb and ref.upd.nis == got.upd.nis and ref.upd.count == got.upd.count, k
        assert ref.upd.rejected == got.upd.rejected and ref.sh.t_us == got.sh.t_us == got.snap.st.t_us, k
        for a, b, names in arrays[:2] + [(ref.upd, got.upd, ("y", "dx"))] + arrays[3:5]:
            for name in names:
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"{k} {name}")
    assert got.upd.count >= 32 and gated >= 1
