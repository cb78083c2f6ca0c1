"""The single-coil window close in few compiled calls, against its Python reference.

* ``WindowCloser.close_one`` on the compiled core (``_close_one_compiled``: ``ct_window_run`` on the
  one channel) against the reference ``close_one`` on the compiled channel and on the Python core:
  windows on the sampling grid, cut short (the ring ends inside the span), longer than the
  extractor's record of used sample times (``_n_rec`` capped at ``max_samples``), with no used
  sample, off the compiled range (the reference takes them), clipped (saturated) samples, flips
  and gaps. The extractor's counts of used samples (``_n_used``, ``_n_rec``) live in its ``ires``
  array, so the compiled close leaves them as the Python extraction does.
* ``Health.suspect_either`` (``ext.SuspectSpan``, ``core/src/sc_close.c``) against the reference's
  ``suspect(node) or suspect(other)`` on the supervisor's arrays: intervals opened by off-grid
  stamps, closed by sync replies, reopened within 2 s, shown only by the replies, every edge of an
  interval, nodes outside the table.
* The whole window update (``ext.ScWindowUpdate``, ``core/py_sc_close.c``:
  ``SingleCoilTracker._update``'s prior, the shared baselines' variance, ``SchepersEKF.update_pulse``
  with the one-call run's bookkeeping, the after-steps) against those steps one call each
  (``_update_steps``), on replayed runs of schepers-adaptive and schepers-ferro (the monitor judges
  the updates inconsistent, inflates ``R`` and lifts the gate): every POSE to the bit, the
  filters' state, counts and NISs, the monitors', the shared baselines', the field evaluations.
  Then, from the same state, the edge cases a replay seldom reaches: a NaN amplitude (the update
  fails: not applied, no after-steps), an amplitude far off (gated: the after-steps still run), a
  clone the IMU stream has not reached (the kernel does nothing and hands it to the reference),
  the state's own pose (no clone).

Independent reference of the suspect test: the interval overlap written out with numpy over the
intervals the test itself opened. Seeded; skips where the extension is not built."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")

from coiltrack.firmware import core  # noqa: E402
from coiltrack.firmware.config import FirmwareConfig  # noqa: E402
from coiltrack.firmware.loop import Firmware  # noqa: E402
from coiltrack.firmware.measure.windows import SensorChannel, WindowCloser  # noqa: E402
from coiltrack.firmware.supervise.health import Health  # noqa: E402
from coiltrack.firmware.track import single_coil_tracker as sct  # noqa: E402
from coiltrack.firmware.transmit import Transmitter  # noqa: E402
from coiltrack.protocol.schema import POSE_INCONSISTENT  # noqa: E402
from coiltrack.tools import scenarios  # noqa: E402
from coiltrack.tools.bench.framelog import replay  # noqa: E402

COMPILED = core.load("compiled")


# ------------------------------------------------------------------ the window close
class _Capture:
    def __init__(self):
        self.frames = []

    def write(self, data):
        self.frames.append(bytes(data))


class _Decoder:
    frames_bad = 0


class _Sample:
    def __init__(self, t, x, y, z, flip):
        self.t_us, self.x, self.y, self.z, self.flip = t, x, y, z, flip


def _closer(kernels, cfg, k: int = 3):
    port = _Capture()
    tx = Transmitter(port, 1, 1_000_000, _Decoder(), core=kernels)
    chans = [SensorChannel(16 + j, cfg, kernels) for j in range(k)]
    return port, chans, WindowCloser(chans, cfg.pulse.fall_us, cfg.pulse.baseline_us, 100_000, tx)


def _same_channel(a, b, case):
    for name in ("S", "var", "flags", "done", "pulse_mid", "amp", "amp_var", "info", "cnt"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"{name} {case}")
    xa, xb = a.extractor, b.extractor
    assert (xa._n_used, xa._n_rec) == (xb._n_used, xb._n_rec), case
    assert xa.last_used_span() == xb.last_used_span(), case
    ua, ub = np.zeros(xa.max_samples + 8, dtype=np.int64), np.zeros(xb.max_samples + 8, dtype=np.int64)
    assert xa.last_used_times(ua) == xb.last_used_times(ub), case
    np.testing.assert_array_equal(ua, ub)
    ea, eb = np.zeros(3), np.zeros(3)
    assert xa.last_empirical_var(ea) == xb.last_empirical_var(eb), case
    np.testing.assert_array_equal(ea, eb)


def test_the_compiled_close_one_is_the_reference_on_every_kind_of_window():
    """1500 sample steps of three channels (jitter, gaps, flips, clipped samples); every 3rd step one
    channel's window closes: on the grid, cut short, longer than the record of used times, with no
    used sample, far off the compiled range. The compiled close, the reference on the compiled
    channel and the Python core leave the same channel, extractor counts, closer counts and frames.
    Catches a channel's place in the run taken from another channel, the used-sample counts left
    stale (the reference reads them from its attributes), the changes not counted, a frame sent with
    the flags of another window."""
    cfg = FirmwareConfig().with_(link={"sensor_ids": (16, 17, 18)}).validate()
    port_c, chs_c, cc = _closer(COMPILED, cfg)
    port_r, chs_r, cr = _closer(COMPILED, cfg)
    port_p, chs_p, cp = _closer(core.PYTHON, cfg)
    assert cc.close_one.__func__ is WindowCloser._close_one_compiled
    assert cp.close_one.__func__ is WindowCloser.close_one
    rng = np.random.default_rng(33)
    n = chs_c[0].S.shape[1]
    cap = chs_c[0].extractor.max_samples
    t = [0, 3_000, 5_500]
    flip = [0, 0, 0]
    kinds, flags_seen, capped = set(), 0, 0
    for step in range(1500):
        for k in range(3):
            t[k] += int(rng.integers(15_000, 30_000)) if rng.random() < 0.03 else int(rng.integers(8_000, 8_600))
            if rng.random() < 0.01:
                flip[k] ^= 1
            counts = rng.integers(-3000, 3000, size=3)
            sat = 2 if rng.random() < 0.02 else 0
            for chs in (chs_c, chs_r, chs_p):
                chs[k].push(_Sample(t[k], int(counts[0]), int(counts[1]), int(counts[2]), sat | flip[k]), 1e-8)
        if step % 3 or step < 300:
            continue
        k = int(rng.integers(0, 3))
        kind = int(rng.integers(0, 5))
        if kind == 0:                                      # on the grid, complete
            start = t[k] - int(rng.integers(150_000, 250_000))
            end = start + int(rng.integers(20_000, 90_000))
        elif kind == 1:                                    # cut short: the ring ends inside the span
            start = t[k] - int(rng.integers(10_000, 60_000))
            end = start + int(rng.integers(20_000, 90_000))
        elif kind == 2:                                    # more used samples than the record holds
            start = t[k] - int(rng.integers(2_200_000, 2_600_000))
            end = start + 8_500 * (cap + 40)
        elif kind == 3:                                    # no used sample
            start = t[k] - int(rng.integers(150_000, 250_000))
            end = start + int(rng.integers(0, 3_000))
        else:                                              # beyond the compiled range: the reference
            start = (1 << 62) + int(rng.integers(0, 1000))
            end = start + 50_000
        kinds.add(kind)
        coil, pid = int(rng.integers(0, n)), step & 0xFFFF
        fc = cc.close_one(chs_c[k], coil, pid, start, end)
        fr = WindowCloser.close_one(cr, chs_r[k], coil, pid, start, end)
        fp = cp.close_one(chs_p[k], coil, pid, start, end)
        assert fc == fr == fp, (step, kind)
        flags_seen |= fc
        capped += chs_p[k].extractor._n_used > chs_p[k].extractor._n_rec
        for j in range(3):
            _same_channel(chs_c[j], chs_r[j], (step, kind, j))
            _same_channel(chs_c[j], chs_p[j], (step, kind, j))
        assert (cc.closed, cc.flagged) == (cr.closed, cr.flagged) == (cp.closed, cp.flagged)
    assert port_c.frames == port_r.frames == port_p.frames
    assert kinds == {0, 1, 2, 3, 4} and capped > 0 and flags_seen == 31, (kinds, capped, flags_seen)


def test_the_compiled_readiness_is_the_reference():
    """``WindowCloser.ready`` on the compiled core (``ext.ReadyUpto``) against the reference on the
    same channels and the Python core's, before any sample, as the channels' samples come in one by
    one (each channel its own latest time), on the exact edge (a sample at ``end + fall + baseline``
    is not after it) and past the timeout. Catches a channel skipped, the edge taken as ready, the
    timeout's sum short of a term."""
    cfg = FirmwareConfig().with_(link={"sensor_ids": (16, 17, 18)}).validate()
    _, chs_c, cc = _closer(COMPILED, cfg)
    _, chs_p, cp = _closer(core.PYTHON, cfg)
    assert cc.ready.__func__ is WindowCloser._ready_compiled
    after = cfg.pulse.fall_us + cfg.pulse.baseline_us
    rng = np.random.default_rng(36)
    seen = set()
    for step in range(600):
        end = int(rng.integers(0, 400_000))
        for now in (end, end + after + 100_000, end + after + 100_001, end + int(rng.integers(0, 300_000))):
            got = cc.ready(end - 30_000, end, now)
            assert got == WindowCloser.ready(cc, end - 30_000, end, now) == cp.ready(end - 30_000, end, now)
            seen.add(got)
        k = int(rng.integers(0, 3))
        t = max(int(chs_c[k].ring.latest_t_us) + 1, end + after + int(rng.integers(-2, 2)), 0)
        for chs in (chs_c, chs_p):
            chs[k].push(_Sample(t, 1, 2, 3, 0), 1e-8)
    assert seen == {True, False}
    assert cc.ready(0, 1 << 62, 0) == WindowCloser.ready(cc, 0, 1 << 62, 0)      # the reference's range


# ------------------------------------------------------------------ the suspect span
def _firmware(name: str = "schepers-adaptive"):
    sc = scenarios.get(name)
    return Firmware(sc.firmware_config().with_(core={"impl": "compiled"}), _Capture())


def test_suspect_either_is_the_reference_on_the_supervisor_arrays():
    """Suspect intervals made the ways the health makes them (a stamp off the grid opens one, a sync
    reply with a step closes it or shows one of its own, a step within 2 s reopens the last), for
    every node of the firmware: the compiled ``suspect_either`` of random nodes (the table's, and
    ones it does not hold) and spans equals the reference, and both equal the overlap of the
    intervals the test recorded, computed with numpy. Catches an interval's edge taken strictly, a
    node's row read from another slot, an open interval not seen, the other node not asked."""
    fw = _firmware()
    h = fw.supervisor.health
    assert h.suspect_either.__func__ is Health._suspect_either_compiled
    rng = np.random.default_rng(34)
    ids = list(h.ids)
    asked = ids + [0, 200, 255, 256, 1000, -1]
    hits = 0
    for step in range(400):
        i = int(rng.integers(0, len(ids)))
        t = 1_000_000 * step + int(rng.integers(0, 900_000))
        what = rng.random()
        if what < 0.25 and not h.suspect_open[i]:
            h._open_suspect(i, t, 1 << 8)
        elif what < 0.45 and h.suspect_open[i]:
            h._close_suspect(i, t + int(rng.integers(0, 3_000_000)))
        elif what < 0.55:
            h.on_sync_reply(ids[i], True, t - 20_000, t)
        for _ in range(20):
            node, other = (int(x) for x in rng.choice(asked, 2))
            t0 = int(rng.integers(0, 1_000_000 * (step + 1)))
            t1 = t0 + int(rng.integers(-10_000, 400_000))
            if rng.random() < 0.2:             # a span ending or starting on an interval's edge
                s = int(rng.integers(0, len(ids)))
                k = int(rng.integers(0, 4))
                t0 = t1 = int(h.susp_t0[s][k] if rng.random() < 0.5 else h.susp_t1[s][k])
            got = h.suspect_either(node, other, t0, t1)
            want = Health.suspect_either(h, node, other, t0, t1)
            assert got is want, (step, node, other, t0, t1)
            assert want == (_overlap(h, node, t0, t1) or _overlap(h, other, t0, t1))
            hits += want
    assert 100 < hits < 7000, hits


def _overlap(h, node: int, t0: int, t1: int) -> bool:
    """Node ``node``'s clock suspect anywhere in ``[t0, t1]``, from its intervals (numpy)."""
    if node not in h.ids:
        return False
    i = h.ids.index(node)
    if h.suspect_open[i]:
        return True
    a, b = np.array(h.susp_t0[i]), np.array(h.susp_t1[i])
    return bool(np.any((a != -(1 << 62)) & (a <= t1) & (b >= t0)))


def test_suspect_span_refuses_bad_arrays():
    """The kernel's binding checks: an array too short for its nodes, the wrong item type."""
    fw = _firmware()
    si, sd = fw.supervisor._si, fw.supervisor._sd
    with pytest.raises(ValueError, match="si"):
        COMPILED.ext.SuspectSpan(si[:40], sd)
    with pytest.raises((ValueError, TypeError)):
        COMPILED.ext.SuspectSpan(si, si)
    k = COMPILED.ext.SuspectSpan(si, sd)
    with pytest.raises(OverflowError):
        k.either(1 << 70, 0, 0, 1)


# ------------------------------------------------------------------ the window update
def _record(name: str, duration: float):
    from coiltrack.tools.bench.runner import record_log
    sc = scenarios.get(name)
    return record_log(sc, 1, duration, sc.firmware_config().with_(core={"impl": "compiled"}))


def _run(header, reads, fused: bool, monkeypatch):
    """The firmware after the replay (compiled core; ``fused``: the window update in one call, else
    its steps one call each) and every POSE it sent."""
    rows = []
    if not fused:
        monkeypatch.setattr(sct, "window_update", lambda *a: None)

    def factory(cfg, port):
        fw = Firmware(cfg, port)
        send = fw.tx.pose

        def pose(r):
            rows.append((r.node, r.t_us, r.status, r.quality, *r.p, *r.q, *r.var))
            send(r)
        fw.tx.pose = pose
        return fw

    fw = replay(factory, header, reads)
    monkeypatch.undo()
    tr = fw.tracker
    assert all((w is not None) == fused for w in tr._wu.values())
    return fw, np.array(rows, dtype=float)


def _state(fw) -> dict:
    tr = fw.tracker
    out = {"counters": tr.counters(), "q_x": dict(tr.q_x), "evals": tr.model.signal.evals,
           "sharing": (tr.sharing._si.copy(), tr.sharing._sf.copy(), tr.sharing.var.copy())}
    for s in tr._sens:
        e, u = s.ekf, s.ekf._coil_update.upd
        out[s.index] = (e.P.copy(), e.p.copy(), e.v.copy(), e.R.copy(), e.ba.copy(), e.bg.copy(), e.clone_p.copy(),
                        e.clone_R.copy(), e.ust.copy(), e.ucnt.copy(), u.kst.copy(), u._nis.copy(),
                        s.monitor._st.copy(), s.monitor._buf.copy(), s.bits, s.gated, s.gated_in_row, s.updates,
                        s.distorted, s.mon_t)
    return out


def _same_state(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        va, vb = a[key], b[key]
        if isinstance(va, tuple):
            for x, y in zip(va, vb):
                np.testing.assert_array_equal(x, y, err_msg=str(key))
        else:
            assert va == vb, key


@pytest.mark.parametrize("name, duration, updates", [("schepers-adaptive", 4.0, 10), ("schepers-ferro", 6.0, 10)])
def test_the_one_call_window_update_is_the_steps_bit_for_bit(name, duration, updates, monkeypatch):
    """A recorded run replayed with the window update in one call and with its steps: every POSE
    to the bit, and the filters', monitors', shared baselines' and tracker's state and counts, the
    field evaluations. Catches the prior's flag or relative error not the update's, the variance of
    another channel, the monitor's scale or gate not applied, a count or an NIS left stale, the
    injection skipped or made on a gated update, the after-steps fed the wrong NIS, the evaluations
    not charged."""
    header, reads = _record(name, duration)
    fa, pa = _run(header, reads, True, monkeypatch)
    fb, pb = _run(header, reads, False, monkeypatch)
    assert pa.shape == pb.shape and len(pa) > 100
    np.testing.assert_array_equal(pa, pb)
    _same_state(_state(fa), _state(fb))
    assert fa.tracker.updates >= updates, fa.tracker.updates
    if name == "schepers-ferro":
        assert sum(s.monitor.flagged for s in fa.tracker._sens) > 0 or fa.tracker.gated > 0


class _Slot:
    def __init__(self, clone: int, coil: int):
        self.clone, self.coil = clone, coil


def test_the_edge_cases_from_one_state(monkeypatch):
    """From one replayed state, the same updates through the one call and through its steps: the
    state's own pose (clone -1), a NaN amplitude (not applied: no injection, no after-steps, counted
    unusable), an amplitude far off (gated: rejected, the after-steps run, POSE_INCONSISTENT), a
    clone not taken yet (the kernel returns -1 and changes nothing; the reference takes the clone),
    a monitor that judged the updates inconsistent (the gate lifted, R scaled). Each pair to the
    bit."""
    header, reads = _record("schepers-adaptive", 3.0)
    fa, _ = _run(header, reads, True, monkeypatch)
    fb, _ = _run(header, reads, False, monkeypatch)
    ta, tb = fa.tracker, fb.tracker
    sa, sb = ta._sens[0], tb._sens[0]
    assert sa.ekf.initialized
    now = 3_000_000
    amp0 = sa.track.amp.copy()
    np.testing.assert_array_equal(amp0, sb.track.amp)
    cases = {}
    for case in ("state", "nan", "far", "inconsistent", "untaken"):
        clone = -1
        if case == "untaken":
            clone = 0
            for tr in (ta, tb):
                s = tr._sens[0]
                s.ekf.clones.taken[0] = False
                s.ekf.clones.due[0] = True
                s.ekf.clones.t[0] = s.ekf.t_us
            assert ta._wu[0][0].run(0, 1, 0.5) == -1
        for tr in (ta, tb):
            s = tr._sens[0]
            amp = s.track.amp
            amp[:] = amp0
            if case == "nan":
                amp[1] = np.nan
            elif case == "far":
                amp *= 50.0
                s.monitor.inconsistent = False
                s.monitor.r_scale = 1.0
            elif case == "inconsistent":
                s.monitor.inconsistent = True
                s.monitor.r_scale = 7.5
            tr._update(s, _Slot(clone, 1), 0.62, 0, now)
        cases[case] = (sa.ekf.ucnt.copy(), ta.unusable, ta.gated, sa.bits)
        _same_state(_state(fa), _state(fb))
        assert ta.unusable == tb.unusable and sa.bits == sb.bits, case
        now += 100_000
    # what each case did (the reference's bookkeeping, the same on both)
    c0, u0, g0, _ = cases["state"]
    c1, u1, g1, _ = cases["nan"]
    c2, u2, g2, b2 = cases["far"]
    c3, u3, g3, _ = cases["inconsistent"]
    c4, u4, g4, _ = cases["untaken"]
    assert c0[1] >= 1 and u0 == 0 or c0[0] >= 1
    assert (u1, c1[0], c1[1], g1) == (u0 + 1, c0[0] + 1, c0[1], g0)        # NaN: rejected, unusable
    assert (u2, c2[0], g2) == (u1, c1[0] + 1, g1 + 1) and b2 & POSE_INCONSISTENT   # far: gated
    assert (c3[1], g3, u3) == (c2[1] + 1, g2, u2)                          # inconsistent: not gated, applied
    assert c4[0] + c4[1] == c3[0] + c3[1] + 1 and u4 == u3                 # untaken: the reference's update


# ------------------------------------------------------------------ the periodic symmetrisation
def test_the_compiled_symmetrize_is_the_reference_and_refuses_what_it_cannot_take():
    """``ext.symmetrize`` (``KalmanUpdate``'s every 16th update on the compiled core) against
    ``estimate.ekf.symmetrize`` on seeded matrices of 1..30 rows with infinities and NaNs: P and the
    scratch to the bit, and equal to numpy's ``(A + A.T) / 2`` (the independent reference). Arrays it
    cannot take (not square, not of one size, not contiguous, not float64, one array twice) are
    left alone and refused with False, so the caller runs the reference. Catches a transposed
    index, the scratch not a copy, a row stride taken from the wrong array."""
    from coiltrack.firmware.estimate.ekf import KalmanUpdate, symmetrize
    sym = COMPILED.ext.symmetrize
    rng = np.random.default_rng(35)
    for n in list(range(1, 31)) + [24] * 5:
        A = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-8, 8, size=(n, n))
        if n > 3:
            A[1, 2], A[2, 1], A[0, n - 1] = np.inf, np.nan, -np.inf
        B, C = A.copy(), A.copy()
        T, T2 = np.zeros((n, n)), np.zeros((n, n))
        assert sym(B, T) is True
        symmetrize(C, T2, T2.T, np.full((), 0.5))
        np.testing.assert_array_equal(B, C)
        np.testing.assert_array_equal(T, T2)
        np.testing.assert_array_equal(B, (A + A.T) / 2)
    P = np.arange(16.0).reshape(4, 4)
    for args in ((P, np.zeros((4, 5))), (np.zeros((3, 4)), np.zeros((3, 4))), (np.zeros((8, 8))[::2, ::2], P),
                 (P, P), (P.astype(np.float32), np.zeros((4, 4), np.float32)), (P, np.zeros(16))):
        before = [a.copy() for a in args]
        assert sym(*args) is False
        for a, b in zip(args, before):
            np.testing.assert_array_equal(a, b)
    ku = KalmanUpdate(6, 3, 0.99, COMPILED)
    assert ku._sym is sym
