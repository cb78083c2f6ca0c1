"""A solved burst's report on the compiled core (``core/src/report.c``: ``ReportChain``,
``WarmStart``, ``AheadSame``) against its Python reference, on two firmwares of the same
configuration, one per core, given the same random state:

* ``MagneticTracker._report_pose`` (the solution taken into the tracked pose when it lies in the
  working volume, ``PoseQuality.grade_burst`` with the motion within the burst, the quaternion and
  the reported covariance: the solver's, or with ``SensorInertial.motion_cov``'s motion for the
  fused tracker): the same return, pose, quality, quality rows and POSE arguments to the bit;
* ``BurstFusionTracker.warm_start`` (``PoseHistory.pose_at`` over the fusion filter's live history,
  wrapped around its ring, the range check and the fall-back to the tracked pose): the same start
  to the bit, and the interpolation against ``numpy.interp`` (an independent reference);
* ``_Ahead.same`` (NaN unequal, -0.0 equal to 0.0).

Seeded; skips without the extension."""
from __future__ import annotations

import math
import random

import numpy as np
import pytest

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

from coiltrack.firmware.loop import Firmware  # noqa: E402
from coiltrack.protocol.schema import POSE_VALID  # noqa: E402
from coiltrack.firmware.track.burst_fusion import BurstFusionTracker  # noqa: E402
from coiltrack.firmware.track.magnetic import MagneticTracker, _Ahead  # noqa: E402
from coiltrack.tools import scenarios  # noqa: E402


class _Port:
    def read(self) -> bytes:
        return b""

    def write(self, data: bytes) -> None:
        pass


def _pair(name: str):
    """The trackers of scenario ``name``'s firmware on the Python and the compiled core, each
    POSE's arguments recorded (``sent``)."""
    cfg = scenarios.get(name).firmware_config()
    out = []
    for impl in ("python", "compiled"):
        fw = Firmware(cfg.with_(core={"impl": impl}), _Port())
        assert fw.core == impl
        trk = fw.tracker
        trk.sent = []
        for ch in trk.channels:          # rings near their end: the tests' samples wrap them around
            for i in range(ch.ring.capacity - 3):
                ch.ring.push(1000 * (i + 1), 30e-6, -20e-6, 35e-6, False, 0)

        def rec(node, t_us, p, q, cov, status, quality, sent=trk.sent):
            # the frame the compiled transmitter's pose_cov6 sends (seq 7, source 1)
            sent.append(_core.pose_frame(7, 1, node, t_us, p[0], p[1], p[2], q[0], q[1], q[2], q[3], cov[0, 0],
                                         cov[1, 1], cov[2, 2], cov[3, 3], cov[4, 4], cov[5, 5], status, quality))
        trk.tx.pose_cov6 = rec

        def built(send, node, t_us, status, quality, sent=trk.sent):
            assert send(sent.append, 7, 1, node, t_us, status, quality) == 8        # sent, numbered 7
            return True
        if impl == "compiled":
            trk.tx.pose_built = built    # the report's frame from its chain (ReportChain.send)
        out.append(trk)
    ref, got = out
    assert got._report_pose.__func__ is MagneticTracker._report_pose_compiled
    assert ref._report_pose.__func__ is MagneticTracker._report_pose
    return ref, got


def _rotation(rng):
    q = np.array([rng.gauss(0, 1) for _ in range(4)])
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _state(rng, trk_pair, k: int, t_pose: int):
    """The same random solver results, tracked pose, signals, schedule, quality row and (fused)
    motion inputs into both trackers for channel ``k``."""
    n = trk_pair[0].solver.n
    far = rng.random() < 0.15
    p = np.array([rng.uniform(-0.6, 0.6) for _ in range(3)])
    rm = trk_pair[0].range_m
    p *= (rm * rng.uniform(1.01, 3.0) if far else rm * rng.uniform(0.05, 0.55)) / float(np.linalg.norm(p))
    R = _rotation(rng)
    A = np.array([[rng.gauss(0, 1) for _ in range(6)] for _ in range(6)])
    cov = A @ A.T * 10.0 ** rng.uniform(-10, -4)
    cost = rng.uniform(0.0, 30.0)
    S = np.array([[rng.gauss(0, 1e-6) for _ in range(n)] for _ in range(3)])
    sigma = np.array([[abs(rng.gauss(0, 1e-8)) + 1e-10 for _ in range(n)] for _ in range(3)])
    if rng.random() < 0.1:
        sigma[rng.randrange(3), rng.randrange(n)] = 0.0       # a weight of zero in the motion term
    start = np.array(sorted(rng.randrange(t_pose - 20_000, t_pose + 20_000) for _ in range(n)), dtype=np.int64)
    end = start + rng.randrange(500, 3000)
    prev_have = rng.random() < 0.8
    prev_t = t_pose - rng.choice([rng.randrange(1, 60_000), 0, -5, 10 ** 7])
    prev_p = p + np.array([rng.gauss(0, 0.01) for _ in range(3)])
    prev_R = _rotation(rng) if rng.random() < 0.2 else R @ _rotation_small(rng)
    wl = np.array([rng.gauss(0, 2.0) for _ in range(3)])
    v = np.array([rng.gauss(0, 0.5) for _ in range(3)])
    init = rng.random() < 0.6
    status = rng.choice([0, 1, 0x40])
    # magnetometer samples of the quiet term (PoseQuality.quiet_term: the ring's newest), the ring wrapped
    pushes = [(rng.gauss(0, 40e-6), rng.gauss(0, 40e-6), rng.gauss(0, 40e-6)) for _ in range(rng.choice([0, 1, 7]))]
    for trk in trk_pair:
        ch = trk.channels[k]
        for b in pushes:
            t = ch.ring.latest_t_us + 1000
            ch.ring.push(t, b[0], b[1], b[2], False, 0)
        sv = trk.solver
        np.copyto(sv.position, p)
        np.copyto(sv.rotation, R)
        np.copyto(sv.covariance, cov)
        sv.cost = cost
        np.copyto(ch.S, S)
        np.copyto(ch.sigma, sigma)
        np.copyto(trk.schedule.start, start)
        np.copyto(trk.schedule.end, end)
        row = trk.quality._prev[ch.node]
        row[0] = 1.0 if prev_have else 0.0
        row[1] = float(prev_t)
        row[2], row[3], row[4] = prev_p
        for i in range(9):
            row[5 + i] = prev_R.flat[i]
        trk._status = status
        if isinstance(trk, BurstFusionTracker):
            ins = trk.inertial[ch.node]
            np.copyto(ins.w_last, wl)
            np.copyto(ins.fusion.st.v, v)
            ins.fusion.initialized = init
    return far


def _rotation_small(rng):
    a = np.array([rng.gauss(0, 0.05) for _ in range(3)])
    th = np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]]) / th
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


@pytest.mark.parametrize("name", ["roetenberg-fusion", "multi16", "roetenberg-bench", "raab-ac"])
def test_report_pose_is_the_python_to_the_bit(name):
    """400 random solved bursts (15 % of them beyond the working volume), the fused tracker's
    filter initialized or not, earlier solutions within the motion term's gap or not: the same
    return, tracked pose, quality, motion term, quality rows and POSE frame bytes as the reference
    (the compiled report's frame built by its chain, ``ReportChain.send``, the reference's from
    its ``pose_cov6`` arguments)."""
    rng = random.Random(5)
    ref, got = _pair(name)
    n_ch = len(ref.channels)
    seen_far = seen_motion = 0
    for trial in range(400):
        k = rng.randrange(n_ch)
        t_pose = rng.randrange(10 ** 6, 10 ** 9)
        far = _state(rng, (ref, got), k, t_pose)
        res = []
        for trk in (ref, got):
            ch = trk.channels[k]
            tp = trk.poses[ch.node]
            tp.have_pose = False
            r = trk._report_pose(ch, tp, t_pose)
            q = trk.quality
            res.append((r, tp.have_pose, tp.position.tobytes(), tp.rotation.tobytes(), q.last[ch.node],
                        q.motion_m2, q.chi2_motion, q._prev_rows.tobytes()))
        assert res[0] == res[1], (trial, name)
        assert res[0][0] == (not far)
        seen_far += far
        seen_motion += res[0][0] and res[0][5] > 0.0
    assert ref.sent == got.sent and len(ref.sent) == 400 - seen_far
    # AC blocks (raab-ac): graded without the motion term (PoseQuality._n 0), on the compiled core too
    assert seen_far > 20 and (seen_motion > 50 if ref.quality._n else seen_motion == 0)


def test_reported_covariance_adds_the_motion_within_the_burst():
    """Independent reference of the fused tracker's reported covariance: the solver's plus
    ``|v|^2 t^2 + |p|^2 |w|^2 t^2`` on the position's diagonal (the velocity only with the filter
    initialized) and ``|w|^2 t^2`` on the orientation's, ``t`` the burst's rms time about its
    middle (thesis sec 6.5)."""
    rng = random.Random(9)
    _, got = _pair("roetenberg-fusion")
    ch = got.channels[0]
    ins = got.inertial[ch.node]
    tr2 = ins.burst_rms_s ** 2
    for _ in range(50):
        t_pose = rng.randrange(10 ** 6, 10 ** 9)
        while _state(rng, (got,), 0, t_pose):
            pass
        tp = got.poses[ch.node]
        assert got._report_pose(ch, tp, t_pose)
        cov = got._rep_cov.copy()        # the covariance the POSE is sent with
        p, q = got.poses[ch.node].position, got._q
        assert got.sent[-1] == _core.pose_frame(7, 1, ch.node, t_pose, p[0], p[1], p[2], q[0], q[1], q[2], q[3],
                                                *(cov[i, i] for i in range(6)), got._status | POSE_VALID, got.quality.last[ch.node])
        w2 = float(ins.w_last @ ins.w_last)
        v2 = float(ins.fusion.st.v @ ins.fusion.st.v) if ins.fusion.initialized else 0.0
        p2 = float(got.solver.position @ got.solver.position)
        want = got.solver.covariance.copy()
        want[[0, 1, 2], [0, 1, 2]] += v2 * tr2 + p2 * w2 * tr2
        want[[3, 4, 5], [3, 4, 5]] += w2 * tr2
        assert np.allclose(cov, want, rtol=1e-13, atol=0.0)


def _history(rng, trk, node: int, count: int, head: int, t0: int, dup: bool):
    """A live pose history of ``count`` entries ending before slot ``head`` (wrapped around the ring),
    times increasing from ``t0`` (two equal when ``dup``); its times in order and rows."""
    hist = trk.inertial[node].fusion.history.live
    cap = hist.capacity
    times = []
    t = t0
    for i in range(count):
        t += 0 if (dup and i == count // 2) else rng.randrange(1000, 12000)
        times.append(t)
    rows = [np.array([rng.gauss(0, 0.3) for _ in range(hist.width)]) for _ in range(count)]
    hist.t[:] = -1
    hist.d[:] = np.nan
    for i in range(count):
        s = (head - count + i) % cap
        hist.t[s] = times[i]
        hist.d[s] = rows[i]
    hist.hc[0], hist.hc[1] = head, count
    return times, rows


@pytest.mark.parametrize("name", ["roetenberg-fusion", "raab-ac"])
def test_warm_start_is_the_python_to_the_bit(name):
    """300 random histories (empty, one entry, wrapped around the ring, two equal times), times
    before, at, inside and after them, the filter initialized or not, the tracked pose had or not,
    a range the interpolated pose leaves or not: the same start and answer as the reference
    (``BurstFusionTracker.warm_start``; AC blocks: ``ACFusionTracker.warm_start``, the block's
    ``t_ref`` and no range check); where the pose is interpolated, numpy's interp agrees."""
    from coiltrack.firmware.measure.ac_blocks import _T_REF
    from coiltrack.firmware.track.ac import ACFusionTracker
    rng = random.Random(3)
    ref, got = _pair(name)
    ac = isinstance(got, ACFusionTracker)
    assert got.warm_start.__func__ is (ACFusionTracker if ac else BurstFusionTracker)._warm_start_compiled
    ch = ref.channels[0]
    cap = ref.inertial[ch.node].fusion.history.live.capacity
    interp = 0
    for trial in range(300):
        count = rng.choice([0, 1, 2, rng.randrange(2, cap + 1), cap])
        head = rng.randrange(cap)
        dup = rng.random() < 0.2
        t0 = rng.randrange(10 ** 6, 10 ** 8)
        p = np.array([rng.uniform(-0.5, 0.5) for _ in range(3)])
        R = _rotation(rng)
        have = rng.random() < 0.85
        init = rng.random() < 0.8
        range_m = rng.choice([5.0, 0.3])
        in_times = rng.random() < 0.9
        out = []
        for trk in (ref, got):
            times, rows = _history(random.Random(trial), trk, ch.node, count, head, t0, dup)
            ins = trk.inertial[ch.node]
            if times and in_times:
                pick = random.Random(trial + 1).random()
                t_ref = (times[0] if pick < 0.15 else times[-1] + 5 if pick < 0.25 else times[0] - 5 if pick < 0.3
                         else random.Random(trial + 2).randrange(times[0], times[-1] + 1))
            else:
                t_ref = t0
            ins.t_ref = t_ref
            if ac:
                trk.measure._stv[_T_REF] = t_ref      # the AC block's middle (ACBlockMeasurement.t_ref)
            ins.fusion.initialized = init
            tp = trk.poses[ch.node]
            tp.have_pose = have
            np.copyto(tp.position, p)
            np.copyto(tp.rotation, R)
            tp.warm_p[:] = 7.0
            tp.warm_R[:] = 7.0
            r = trk.warm_start(ch, tp)
            out.append((r, tp.warm_p.tobytes(), tp.warm_R.tobytes()))
        assert out[0] == out[1], trial
        tp = got.poses[ch.node]
        if have and init and len(times) >= 2 and times[0] < t_ref <= times[-1] and not dup \
                and not np.array_equal(tp.warm_p, p):
            tt = np.array(times, dtype=float)
            want = [np.interp(t_ref, tt, [row[c] for row in rows]) for c in range(12)]
            got12 = np.concatenate([tp.warm_p, tp.warm_R.ravel()])
            assert np.allclose(got12, want, rtol=1e-12, atol=1e-15), trial
            interp += 1
    assert interp > 50


def test_ahead_same_is_the_python_comparison():
    """The compiled comparison of a burst's inputs with a solve ahead's (``AheadSame``) against
    ``_Ahead.same`` (memoryviews compared item by item): equal copies (the same), one item a ulp
    off (not), NaN in both (not: NaN is unequal to itself), 0.0 against -0.0 (the same)."""
    from coiltrack.firmware._core import AheadSame
    rng = random.Random(4)
    names = ("S", "sigma", "currents", "hemisphere", "warm_p", "warm_R")
    for trial in range(300):
        ah = _Ahead(3)
        other = []
        for nm in names:
            a = getattr(ah, nm)
            a[...] = np.array([rng.gauss(0, 1) for _ in range(a.size)]).reshape(a.shape)
            other.append(a.copy())
        kind = trial % 4
        j = rng.randrange(len(names))
        mine, theirs = getattr(ah, names[j]).reshape(-1), other[j].reshape(-1)
        i = rng.randrange(mine.size)
        if kind == 1:
            theirs[i] = np.nextafter(theirs[i], math.inf)
        elif kind == 2:
            mine[i] = theirs[i] = math.nan
        elif kind == 3:
            mine[i], theirs[i] = 0.0, -0.0
        views = tuple(memoryview(x) for x in other)
        want = ah.same(views)
        assert want == (kind in (0, 3)), trial
        assert AheadSame(ah._views, views).same() == want, trial
