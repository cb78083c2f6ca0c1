"""One IMU sample of a fused tracker's sensor in one call of the compiled core
(``core/src/fusimu.c`` ``ct_ori_sample``, ``ct_ring_push``/``ct_ring_pop``; ``py_fusimu.c``
``OriStep``, ``ImuSample``, ``FusOutput.pose_frame`` / ``pose_next``) against the Python reference
(``track.burst_fusion.SensorInertial.process`` with ``_Ori.step``, ``FlipOffset``,
``orientation_updates.Inclination``, ``FusionFilter.push_imu``, ``SensorInertial.send_fused``).

Three sensors see the same seeded stream: ``ref`` on the Python core, ``sep`` on the compiled core
with its kernels called one by one (``_Ori.step_python`` through the compiled ``predict``,
``update_acc``, ``update_mag``; ``FusionFilter.push_imu``'s ``FusLive``) and ``got`` on the
one-call path. ``got`` equals ``sep`` bit for bit (the same kernels in the same order); both equal
``ref`` to 1e-9 (its updates' products go through BLAS), with the same discrete decisions (the
updates' flags and counts, the compass samples chosen, the flips seen) at every step. The stream
covers the compass's learning, flips of the set/reset state, saturated samples and samples in
the pulses, a free-fall sample, a magnetic disturbance (gated compass updates), a break in the
IMU stream (the orientation lost and found again), the periodic orthonormalisation and
symmetrisations, snapshots and a full output queue; and the POSE frames sent from the queued
poses are the same bytes.
"""
from __future__ import annotations

import math
import types

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware import core
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.estimate.fusion_rings import KernelRing
from coiltrack.firmware.measure.pulse import SampleRing
from coiltrack.firmware.ring import Ring
from coiltrack.firmware.track.burst_fusion import _FUSED_VALID, FixedSource, PulseGate, SensorInertial, _OneCall
from coiltrack.firmware.transmit import Transmitter
from coiltrack.protocol.schema import ACC_LSB, GYR_LSB

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

G = np.array([0.0, 0.0, 9.81])
H = np.array([0.2e-4, 0.0, -0.45e-4])       # earth field, global frame (north, west, up), T


class _Port:
    def __init__(self):
        self.frames = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


class _Drained:
    """Counts the samples ``ext.ImuSample.drain`` ran (``n``) and those it handed back (``back``)."""

    def __init__(self, one):
        self.n = self.back = 0
        self._drain = one._drain
        one._drain = self

    def __call__(self, max_steps: int) -> int:
        r = self._drain(max_steps)
        self.n += r >> 2
        self.back += (r & 3) != 0
        return r


def _matmul_is_fma_chain() -> bool:
    """numpy's 3x3 ``matmul`` (the reference ``OrientationFilter._orthonormalize``'s product) computes each
    element as ``fma(a2, b2, fma(a1, b1, a0 b0))`` here (OpenBLAS's dgemm kernels on FMA machines), the
    operations ``ct_ori_orthonormalize`` makes; exact rational arithmetic gives the correctly rounded fma."""
    from fractions import Fraction as F

    def fma(a, b, c):
        return float(F(a) * F(b) + F(c))

    rng = np.random.default_rng(2)
    for _ in range(20):
        a, b = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        c = np.matmul(a, b)
        for i in range(3):
            for j in range(3):
                if c[i, j] != fma(a[i, 2], b[2, j], fma(a[i, 1], b[1, j], a[i, 0] * b[0, j])):
                    return False
    return True


# where the BLAS sums a 3x3 product otherwise, R after an orthonormalisation differs in its last bits
# and the one-call path is compared with the kernels one by one to 1e-9 (as with the Python reference)
_R_EXACT = _matmul_is_fma_chain()


def _rel(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b))) / max(float(np.max(np.abs(a))), 1e-300)


def _sensors(adapt: float, heading_only: bool):
    cfg = FirmwareConfig().with_(orientation={"mag_learn_samples": 12, "ori_update_every": 3},
                                 body={"acc_adapt_gain": adapt, "acc_adapt_tau_s": 0.3,
                                       "compass_heading_only": heading_only},
                                 fusion={"pose_output_capacity": 8})
    starts = np.array([1_300_000, 2_100_000, 2_900_000], np.int64)
    ends = starts + 60_000
    gate = PulseGate(starts, ends, 600, 200)
    c = core.load("compiled")
    out = {}
    for name, k in (("ref", core.PYTHON), ("sep", c), ("got", c)):
        ins = SensorInertial(16, cfg, gate, FixedSource(cfg), core=k)
        tx = Transmitter(_Port(), 1, 1_000_000, None, core=k)
        out[name] = (ins, tx)
    ins, tx = out["sep"]
    assert ins.process.__func__ is _OneCall.run
    ins.process = types.MethodType(SensorInertial.process, ins)     # the kernels one by one
    ins.ori.step = ins.ori.step_python
    own = tx.pose
    tx.pose = lambda r: own(r)                                          # (every POSE through pose)
    assert out["ref"][0].process.__func__ is SensorInertial.process
    return cfg, out


def _start_fusion(ins, t0: int) -> None:
    """The same running fusion state in each sensor (a full covariance, offsets)."""
    rng = np.random.default_rng(3)
    ff = ins.fusion
    ff.push_imu(t0, *G, 0.0, 0.0, 0.0, *(-G), ins.source.phi)
    st = ff.st
    n = st.P.shape[0]
    M = rng.normal(size=(n, n))
    st.p[:] = (0.1, -0.2, 0.3)
    st.v[:] = (0.01, 0.02, -0.01)
    st.Th[:] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    st.P[:] = 1e-6 * (M @ M.T) + 1e-6 * np.eye(n)
    st.t_us = t0
    ff.initialized = True
    ff.last_update_t = t0                 # (as if a magnetic update were accepted now)


def _imu_msg(t, acc, gyr):
    a = np.rint(acc / ACC_LSB).astype(int)
    g = np.rint(gyr / GYR_LSB).astype(int)
    return types.SimpleNamespace(t_us=int(t), ax=int(a[0]), ay=int(a[1]), az=int(a[2]), gx=int(g[0]),
                                 gy=int(g[1]), gz=int(g[2]), node=16)


def _compare_ori(a, b, exact: bool, where) -> None:
    exact = exact and _R_EXACT
    fa, fb = a.ori.f, b.ori.f
    for name in ("R", "P", "bias", "dist", "acc", "sums"):
        x, y = getattr(fa, name), getattr(fb, name)
        if exact:
            np.testing.assert_array_equal(x, y, err_msg=f"{name} {where}")
        else:
            assert _rel(x, y) < 1e-9 or np.array_equal(x, y), (name, where)
    for name in ("initialized", "t_us", "steps", "last_acc_flags", "last_mag_flags", "reacquired"):
        assert getattr(fa, name) == getattr(fb, name), (name, where)
    for u, v in ((fa.incl.upd, fb.incl.upd), (fa.compass.upd, fb.compass.upd)):
        assert (u.count, u.rejected) == (v.count, v.rejected), where
        assert u.nis == v.nis if exact else abs(u.nis - v.nis) <= 1e-7 * max(abs(u.nis), 1.0), where
    assert fa.pred.count == fb.pred.count, where
    assert (a.ori.n, a.ori.compass_used, a.ori.compass_t, a.ori.lost) == \
        (b.ori.n, b.ori.compass_used, b.ori.compass_t, b.ori.lost), where
    np.testing.assert_array_equal(a.ori.flip.si, b.ori.flip.si, err_msg=str(where))
    for x, y in ((a.ori.flip.s, b.ori.flip.s), (fa.compass.state, fb.compass.state), (fa.incl.st, fb.incl.st),
                 (a.w_last, b.w_last)):
        if exact:
            np.testing.assert_array_equal(x, y, err_msg=str(where))
        else:
            assert _rel(x, y) < 1e-9 or np.array_equal(x, y), where


def _compare_fusion(a, b, exact: bool, where) -> None:
    exact = exact and _R_EXACT
    fa, fb = a.fusion, b.fusion
    for name in ("p", "v", "Th", "ba", "bg", "P"):
        x, y = getattr(fa.st, name), getattr(fb.st, name)
        if exact:
            np.testing.assert_array_equal(x, y, err_msg=f"{name} {where}")
        else:
            assert _rel(x, y) < 1e-9, (name, where)
    assert (fa.st.t_us, fa.steps, fa.st.pred.count, fa.out_dropped, len(fa.hist)) == \
        (fb.st.t_us, fb.steps, fb.st.pred.count, fb.out_dropped, len(fb.hist)), where
    for ra, rb in ((fa.prediction.imu, fb.prediction.imu), (fa.hist, fb.hist), (fa.output.out, fb.output.out),
                   (a.imu, b.imu)):
        assert (len(ra), ra.slot(0) if len(ra) else -1) == (len(rb), rb.slot(0) if len(rb) else -1), where
        np.testing.assert_array_equal(ra.t, rb.t, err_msg=str(where))
        if exact:
            np.testing.assert_array_equal(ra.d, rb.d, err_msg=str(where))
        else:
            assert _rel(ra.d, rb.d) < 1e-9 or np.array_equal(ra.d, rb.d), where


@pytest.mark.parametrize("adapt, heading_only", [(0.0, False), (0.5, True)])
def test_one_call_sensor_sample_matches_the_reference(adapt, heading_only):
    rng = np.random.default_rng(11 + int(heading_only))
    cfg, sens = _sensors(adapt, heading_only)
    mag = SampleRing(64)
    R = Rotation.from_rotvec([0.1, -0.2, 0.3])
    w_true = np.array([0.4, -0.3, 0.8])
    t0 = 1_000_000
    for ins, _ in sens.values():
        _start_fusion(ins, t0)
    sent = []
    gtx = sens["got"][1]
    fused_pose = gtx.fused_pose
    gtx.fused_pose = lambda *a: (sent.append(fused_pose(*a)), sent[-1])[1]
    calls = []
    drained = None
    live = sens["got"][0].fusion.live_sample
    sens["got"][0].fusion.live_sample = lambda *a: (calls.append(a[0].__name__), live(*a))[1]
    tm = t0
    t = t0
    for i in range(900):
        t += 8333 + (i % 3 == 0)
        if i == 500:
            t += 400_000                              # the IMU stream breaks off: orientation lost
        R = R * Rotation.from_rotvec(w_true * 0.008333)
        Rm = R.as_matrix()
        while tm + 10_000 <= t + 4000:                # the magnetometer at 100 Hz, a little ahead
            tm += 10_000
            dist = 0.15e-4 * np.array([1.0, 0.5, 0.0]) if 600 < i < 660 else 0.0
            flip = (tm // 250_000) % 2                # the set/reset state flips every 0.25 s
            b = Rm.T @ (H + dist) + 3e-8 * rng.normal(size=3) + (1 if flip else -1) * 2e-7
            mag.push(tm, *b, rng.random() < 0.05, int(flip))
        acc = Rm.T @ G + 0.2 * rng.normal(size=3)
        if i == 300:
            acc = acc * 0.1                           # free fall
        gyr = w_true + 0.01 * rng.normal(size=3) + 0.02
        msg = _imu_msg(t, acc, gyr)
        for ins, _ in sens.values():
            ins.imu.push(msg)
        if i == 520:
            for ins, _ in sens.values():
                _start_fusion(ins, t + 1)             # (the fusion filter restarted after the break)
        if i % 60 == 30:
            for ins, _ in sens.values():
                ins.schedule(t + 20_000)              # a snapshot inside a later step
        if i % 2:
            continue                                  # two samples a tick
        for ins, tx in sens.values():
            ins.process(mag, t + 1000, 0, 4)
            if ins is sens["got"][0] and drained is None and getattr(ins._one, "_drain", None) is not None:
                drained = _Drained(ins._one)                # (bound at the first sample both filters take)
            if i % 50 < 40:                           # (the queue fills and drops at times)
                ins.send_fused(tx, 16, 1.0, 200)
        where = i
        _compare_ori(sens["sep"][0], sens["got"][0], True, where)
        _compare_fusion(sens["sep"][0], sens["got"][0], True, where)
        _compare_ori(sens["ref"][0], sens["got"][0], False, where)
        _compare_fusion(sens["ref"][0], sens["got"][0], False, where)
    got, sep, ref = sens["got"][0], sens["sep"][0], sens["ref"][0]
    f = got.ori.f
    assert f.reacquired == 1 and f.incl.upd.count > 100 and f.compass.upd.count > 50
    assert f.compass.upd.rejected > 0 or heading_only       # the disturbance gated
    assert got.ori.flip.si[2] >= 2                           # flips seen
    assert got.fusion.out_dropped > 0 and got.fusion.snap.valid
    # one call each: most in the compiled loop (ext.ImuSample.drain), the rest handed back one by one
    assert got._one.kernel is not None and sep._one.kernel is None and drained.n + len(calls) > 400
    assert drained.n > 300 and drained.back > 10
    # the samples whose prediction orthonormalised R (steps 64, 128, ...) ran in the compiled loop too
    # (ct_ori_sample_ortho), R the same bits as the reference's np.matmul (compared with sep above)
    assert f.steps > 5 * 64 and calls.count("finish") == 0
    # the per-sample state lives in the owners' arrays, read through the reference's names
    for ins in (got, ref):
        fo, fu = ins.ori.f, ins.fusion
        assert list(fo.state) == [int(fo.initialized), fo.t_us, fo.steps, fo.last_acc_flags, fo.last_mag_flags]
        assert list(fo.incl.upd.kst) == [fo.incl.upd.count, fo.incl.upd.rejected] and fo.pred.cst[0] == fo.pred.count
        assert list(ins.ori.ns) == [ins.ori.n, ins.ori.compass_used] and fo.compass.learn_state[0] == 0
        assert (fu.st.ts[0], fu.prediction.ps[0], fu.fs[1], fu.fs[2]) == (fu.st.t_us, fu.steps, fu.last_update_t,
                                                                      fu.last_flags)
    # the POSE frames: the same bytes on the one-call path as through PoseReport and pose
    fa, fb, fr = sens["got"][1].port.frames, sens["sep"][1].port.frames, sens["ref"][1].port.frames
    assert len(fa) == len(fb) == len(fr) > 300
    assert fa == fb
    assert sent.count(0) > 50 and sent.count(-1) > 10      # sent from the rows (all queued), and through the reference
    assert sens["got"][1].fused_poses == sens["sep"][1].fused_poses == sens["ref"][1].fused_poses


def test_one_call_path_is_taken_and_left():
    """The one-call path runs for the samples of an initialised filter that has learned its
    compass and whose fusion filter runs, those whose prediction orthonormalises R included; a
    sample before the compass learned takes the reference path."""
    cfg, sens = _sensors(0.0, False)
    ins = sens["got"][0]
    calls = []
    live = ins.fusion.live_sample
    ins.fusion.live_sample = lambda *a: (calls.append(a[0].__name__), live(*a))[1]
    mag = SampleRing(64)
    _start_fusion(ins, 1_000_000)
    t = 1_000_000
    drained = None
    for i in range(400):
        t += 8333
        mag.push(t - 2000, *(H + 1e-9 * i), False, 0)
        ins.imu.push(_imu_msg(t, G, np.array([0.1, 0.0, 0.0])))
        learning = ins.ori.f.learning
        ins.process(mag, t, 0, 8)
        if drained is None and getattr(ins._one, "_drain", None) is not None:
            drained = _Drained(ins._one)
        if learning:                                  # (the hand-backs up to the compass's last learning sample)
            back_learning = drained.back if drained is not None else 0
        ins.send_fused(sens["got"][1], 16, 1.0, 200)
    f = ins.ori.f
    assert not f.learning and f.steps == 399 and f.upd_mag.count > 50     # (the first sample initialises)
    # all but the samples before the compass learned (2 x 12 compass samples): in the compiled loop
    # (drain), the steps 64, 128, ... 384 (each orthonormalises R) too, none handed back after it learned
    assert 350 < drained.n + len(calls) <= 400 - 24 and calls.count("finish") == 0
    assert drained.back == back_learning and len(calls) <= 2


def test_kernel_ring_is_a_ring():
    """KernelRing: every Ring operation the same (push, pop, peek, slot, search, rewind, copy, clear,
    advance), head and count in its array; the kernel's push and pop on it (ImuSample) agree."""
    rng = np.random.default_rng(5)
    a, b = Ring(7, (("X", 2),)), KernelRing(7, (("X", 2),))
    t = 0
    for i in range(200):
        op = rng.integers(0, 6)
        if op < 3:
            t += int(rng.integers(1, 5))
            assert a.push(t) == b.push(t)
        elif op == 3:
            assert a.pop() == b.pop()
        elif op == 4 and len(a):
            x = int(rng.integers(a.tv[a.slot(0)], t + 1))
            a.drop_newer_than(x)
            b.drop_newer_than(x)
        else:
            a.advance(2)
            b.advance(2)
        assert len(a) == len(b) == b.hc[1] and a.full == b.full and a.last_pushed_slot() == b.last_pushed_slot()
        assert [a.peek(k) for k in range(8)] == [b.peek(k) for k in range(8)]
        assert a.index_at_or_after(t - 3) == b.index_at_or_after(t - 3)
    c = KernelRing(7, (("X", 2),))
    c.copy_from(b)
    assert (len(c), c.slot(0) if len(c) else -1) == (len(b), b.slot(0) if len(b) else -1)
    c.clear()
    assert len(c) == 0 and list(c.hc) == [0, 0]


def test_pose_frame_refuses_what_the_reference_sends_differently():
    """``FusOutput.pose_frame`` sends a row with no OUT_* bit and in range only (None otherwise,
    for the reference path); its bytes are ``Transmitter.pose``'s."""
    cfg, sens = _sensors(0.0, False)
    ins, tx = sens["got"]
    _start_fusion(ins, 1_000_000)
    po = ins.fusion.output
    ins.fusion.push_imu(1_008_333, *G, 0.0, 0.0, 0.0, *(-G), ins.source.phi)
    k = po.out.slot(0)
    kern = po._ck
    frame = kern.pose_frame(k, po.out.tv[k], 5, 1, 16, _FUSED_VALID, 200, 1.0)
    assert frame is not None
    ref = sens["sep"][1]
    r = types.SimpleNamespace(node=16, t_us=po.out.tv[k], status=_FUSED_VALID, quality=200, p=[0.0] * 3, q=[0.0] * 4,
                              var=[0.0] * 6)
    kern.report(k, r.p, r.q, r.var)
    ref._seq = 5
    ref.pose(r)
    assert ref.port.frames[-1] == frame
    assert kern.pose_frame(k, po.out.tv[k], 5, 1, 16, _FUSED_VALID, 200, 0.1) is None         # beyond the range
    assert kern.pose_frame(k, -1, 5, 1, 16, _FUSED_VALID, 200, 1.0) is None                   # a time the wire refuses
    assert kern.pose_next(5, 1, 16, _FUSED_VALID, 200, 0.1) is None and len(po.out) == 1   # left queued
    assert kern.pose_next(5, 1, 16, _FUSED_VALID, 200, 1.0) == frame and len(po.out) == 0  # sent: off the queue
    assert kern.pose_next(5, 1, 16, _FUSED_VALID, 200, 1.0) == 0                          # none queued
    po.out.d[k, 13] = 4.0
    assert kern.pose_frame(k, po.out.tv[k], 5, 1, 16, _FUSED_VALID, 200, 1.0) is None         # an OUT_* bit
    assert math.isfinite(r.p[0])


def test_drain_hands_back_what_the_reference_tests_refuse():
    """``ext.ImuSample.drain`` (``ct_sample_route``) runs a sample only where ``_Ori.settled`` and
    ``FusionFilter.live_ready`` hold (or only a pending snapshot falls inside the step, while no replay
    runs) and the output queue has room: a recorder attached, a pending snapshot inside the step
    during a replay, the fusion filter not initialised, the compass learning or a full queue each hand
    the sample back (nothing run, the state unchanged); the sample then runs as the reference runs it."""
    cfg, sens = _sensors(0.0, False)
    ins, tx = sens["got"]
    mag = SampleRing(64)
    _start_fusion(ins, 1_000_000)
    t = 1_000_000
    for i in range(80):                               # the compass learns; the drain is bound
        t += 8333
        mag.push(t - 2000, *(H + 1e-9 * i), False, 0)
        ins.imu.push(_imu_msg(t, G, np.array([0.1, 0.0, 0.0])))
        if i % 2:
            ins.process(mag)                          # (track.ac's call: the defaults)
        else:
            ins.process(mag, t, 0, 8)
        ins.send_fused(tx, 16, 1.0, 200)
    assert ins.samples == 80
    one, fus = ins._one, ins.fusion
    assert one._drain is not None and not ins.ori.f.learning
    if ((ins.ori.f.steps + 1) & 63) == 0:             # (keep clear of an orthonormalising step)
        t += 8333
        ins.imu.push(_imu_msg(t, G, np.array([0.1, 0.0, 0.0])))
        ins.process(mag, t, 0, 8)

    def refused(arrange, undo) -> None:
        nonlocal t
        t += 8333
        ins.imu.push(_imu_msg(t, G, np.array([0.1, 0.0, 0.0])))
        arrange()
        before = (ins.ori.f.state.copy(), fus.fs.copy(), fus.st.ts.copy(), fus.prediction.ps.copy(), len(ins.imu))
        assert one._drain(8) == 1                     # none run, handed back as the steps one by one
        after = (ins.ori.f.state, fus.fs, fus.st.ts, fus.prediction.ps, len(ins.imu))
        assert all(np.array_equal(a, b) for a, b in zip(before, after))
        undo()
        assert one._drain(8) == 4                     # then run whole
        assert fus.st.t_us == t and ins.ori.f.t_us == t
        ins.send_fused(tx, 16, 1.0, 200)

    saved = fus.fs.copy()
    refused(lambda: fus.fs.__setitem__(3, 1), lambda: fus.fs.__setitem__(3, saved[3]))       # a recorder
    refused(lambda: (fus.snap.schedule(t - 10), fus.fs.__setitem__(4, 1)),                    # a snapshot in the step
            lambda: (fus.snap.__setattr__("pending", False), fus.fs.__setitem__(4, 0)))       # during a replay
    refused(lambda: fus.fs.__setitem__(0, 0), lambda: fus.fs.__setitem__(0, 1))               # not initialised
    refused(lambda: ins.ori.f.compass.__setattr__("learning", True),
            lambda: ins.ori.f.compass.__setattr__("learning", False))                         # the compass learning
    out = fus.output.out
    for _ in range(out.capacity - len(out)):
        out.push(0)
    refused(lambda: None, lambda: [out.pop() for _ in range(len(out))])                       # a full output queue


@pytest.mark.parametrize("ortho", [False, True])
def test_drain_takes_a_snapshot_inside_the_step_as_the_kernels_one_by_one(ortho):
    """A sample whose step a pending snapshot splits runs in the compiled loop (``CT_SR_SNAP``:
    ``_Ori.step``, ``InertialPrediction.push``, ``CompiledReplay.split_take`` with the ch. 2 filter's
    propagation, ``Snapshot.taken``, ``PoseOutput.queue``), the same bits as the kernels one by one
    (``sep``) and to 1e-9 as the Python reference, the snapshot taken at its instant with ``Phi`` and
    ``Xi``; also when its prediction orthonormalises R (``ortho``)."""
    cfg, sens = _sensors(0.0, False)
    mag = SampleRing(64)
    for ins, _ in sens.values():
        _start_fusion(ins, 1_000_000)
    got = sens["got"][0]
    t = 1_000_000
    taken = 0
    for i in range(300):
        t += 8333
        mag.push(t - 2000, *(H + 1e-9 * i), False, 0)
        w = np.array([0.1, 0.05 * math.sin(i / 9.0), -0.02])
        msg = _imu_msg(t, G + 0.05 * np.array([math.cos(i / 7.0), 0.0, 0.0]), w)
        for ins, _ in sens.values():
            ins.imu.push(msg)
        steps_next = (got.ori.f.steps + 1) & 63 == 0
        if i > 60 and (steps_next if ortho else i % 23 == 0):
            for ins, _ in sens.values():
                ins.schedule(t - 3000)                 # the snapshot falls inside this sample's step
        for ins, tx in sens.values():
            pend = ins.fusion.snap.pending
            ins.process(mag, t, 0, 8)
            if ins is got and pend and not ins.fusion.snap.pending:
                taken += 1
            ins.send_fused(tx, 16, 1.0, 200)
        if i == 60:
            drained = _Drained(got._one)              # (the compass has learned: none handed back from here)
        _compare_ori(sens["sep"][0], got, True, i)
        _compare_fusion(sens["sep"][0], got, True, i)
        _compare_ori(sens["ref"][0], got, False, i)
        _compare_fusion(sens["ref"][0], got, False, i)
        for name in ("p", "v", "Th", "ba", "bg", "P"):
            x, y = getattr(sens["sep"][0].fusion.snap.st, name), getattr(got.fusion.snap.st, name)
            np.testing.assert_array_equal(x, y) if _R_EXACT else np.testing.assert_allclose(x, y, rtol=1e-9)
        sa, sg = sens["sep"][0].fusion.snap, got.fusion.snap
        for name in ("Phi", "Xi", "XiP", "XiB"):
            np.testing.assert_array_equal(getattr(sa, name), getattr(sg, name)) if _R_EXACT else \
                np.testing.assert_allclose(getattr(sa, name), getattr(sg, name), rtol=1e-9, atol=1e-300)
        assert (sa.t, sa.pending, sa.valid, sa.initialized, sa.xi, sa.st.t_us) == \
            (sg.t, sg.pending, sg.valid, sg.initialized, sg.xi, sg.st.t_us), i
    assert taken >= 3 and drained.back == 0 and drained.n == 300 - 61
    assert got.fusion.snap.valid and got.fusion.snap.st.t_us == got.fusion.snap.t
