"""The compiled AC kernels (``firmware_py/core/src/demod.c``, ``src/raab.c``) against their Python
reference (``measure.demod.Demodulator``, ``pose.raab_update`` / ``raab_correction``) on seeded
inputs, bit for bit, and the demodulation against an independent least-squares reference
(``scipy.linalg.lstsq`` of the same model) and the closed form of a pure tone. Skipped where the
extension is not built."""
import math

import numpy as np
import pytest
import scipy.linalg

from coiltrack.firmware import core as fcore
from coiltrack.firmware.measure.demod import Demodulator
from coiltrack.firmware.measure.pulse import PULSE_SATURATED, PULSE_TOO_FEW, SAMPLE_SATURATED, SampleRing

pytestmark = pytest.mark.skipif(not fcore.available(), reason="the compiled core is not built")

COMPILED = fcore.DEFAULT
FREQS = (215.0, 315.0, 465.0)
W_US, HOP_US = 18_000, 9_000
SIGMA = 1.2e-7


def _pair(ring_p=None, ring_c=None, integration_us=500):
    dp = Demodulator(FREQS, W_US, HOP_US, SIGMA, integration_us, ring_p, fcore.PYTHON)
    dc = Demodulator(FREQS, W_US, HOP_US, SIGMA, integration_us, ring_c, COMPILED)
    assert dp.core == "python" and dc.core == "compiled"
    return dp, dc


def _samples(rng, n, t0=1_000_000, sat_every=37):
    """Seeded 1 kHz samples with jitter and a gap: three carriers, an earth field and a ramp, noise."""
    t = t0 + np.arange(n) * 1000 + rng.integers(-40, 41, n)
    t[n // 2:] += 3000                                  # a gap of three samples
    ts = t * 1e-6
    B = np.array([20e-6, -5e-6, 42e-6]) + np.outer(ts - ts[0], [3e-6, -2e-6, 1e-6])
    for k, f in enumerate(FREQS):
        B = B + np.outer(np.cos(2 * np.pi * f * ts + 0.3 * k), rng.normal(0, 1e-6, 3))
    B = B + rng.normal(0, SIGMA, B.shape)
    fl = np.where(np.arange(n) % sat_every == 5, SAMPLE_SATURATED, 0)
    return t, B, fl


def _state(d, stats=True):
    """Everything a finished block publishes (the statistics once a block was solved)."""
    out = (d.S.copy(), d.Q.copy(), d.var.copy(), d.qvar.copy(), d.dc.copy(), d.residual_ratio, d.block_flags,
           d.block_samples, d.block_k, d.next_k)
    return out + (d.signal_chi2(), d.quadrature_chi2(), d.quadrature_ratio()) if stats else out


def _same(a, b):
    for x, y in zip(a, b):
        if isinstance(x, np.ndarray):
            assert np.array_equal(x, y), (x, y)
        else:
            assert x == y, (x, y)


def test_push_and_finish_bit_equal_to_the_reference():
    """Seeded samples (jitter, a gap, saturated samples, samples before t0 and repeated times, which
    are ignored) pushed into both: the same completed blocks and, per block, the same S, Q,
    variances, DC term, residual, flags and statistics, bit for bit: catches a floor division
    rounded towards zero, a phase from the wrong reference, a dropped ramp column or a term
    summed in another order."""
    rng = np.random.default_rng(11)
    t, B, fl = _samples(rng, 400)
    dp, dc = _pair()
    for d in (dp, dc):
        d.start(int(t[0]) + 2500, 1_234_567, (1.5, 1.4, 1.6), (0.3, -2.0, 1.1))
    blocks, flags = 0, 0
    for i in range(len(t)):
        args = (int(t[i]), float(B[i, 0]), float(B[i, 1]), float(B[i, 2]), int(fl[i]))
        kp, kc = dp.push(*args), dc.push(*args)
        assert kp == kc
        assert dp.push(*args) == dc.push(*args) == -1           # not newer than the last: ignored
        if kp >= 0:
            okp, okc = dp.finish(kp), dc.finish(kc)
            assert okp == okc
            _same(_state(dp), _state(dc))
            blocks += okp
            flags |= dp.block_flags
    assert blocks >= 30
    assert flags & PULSE_SATURATED                    # saturated samples flag their blocks


def test_too_few_samples_flag_the_block_in_both():
    """A block that holds fewer than p + 2 samples is not solved, PULSE_TOO_FEW in both."""
    dp, dc = _pair()
    for d in (dp, dc):
        d.start(0, 0, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
        for t in (1000, 2000, 3000, 18_500):
            k = d.push(t, 1e-6, 2e-6, 3e-6, 0)
        assert k == 0
        assert d.finish(k) is False
        assert d.block_flags == PULSE_TOO_FEW and d.block_samples == 3
    _same(_state(dp, False), _state(dc, False))


def test_feed_over_a_wrapping_ring_equals_the_reference():
    """The compiled feed reads the channel's SampleRing in place (a ring of 64 that wraps many
    times, fed 3 new samples per tick, at most 4 per call): the same pending blocks, cursor and
    results as the Python feed: catches a ring slot computed without the wrap or a cursor that
    skips or repeats a sample."""
    rng = np.random.default_rng(5)
    t, B, fl = _samples(rng, 600)
    rp, rc = SampleRing(64), SampleRing(64)
    dp, dc = _pair(rp, rc)
    for d in (dp, dc):
        d.start(int(t[0]) + 1000, 777, (1.5, 1.5, 1.5), (0.1, 0.2, 0.3))
    i, solved = 0, 0
    while i < len(t):
        for _ in range(3):
            if i < len(t):
                for r in (rp, rc):
                    r.push(int(t[i]), float(B[i, 0]), float(B[i, 1]), float(B[i, 2]), bool(fl[i]), 0)
                i += 1
        for _ in range(2):
            assert dp.feed(4) == dc.feed(4)
            assert dp.pending == dc.pending and dp._st[5] == dc._st[5]
            if dp.pending >= 0:
                k = dp.pending
                for d in (dp, dc):
                    d.clear_pending()
                    d.finish(k)
                _same(_state(dp), _state(dc))
                solved += 1
    assert solved >= 50


def test_step_over_a_ring_with_its_gates_equals_the_reference():
    """``Demodulator.step`` (one call per tick: feed, or the pending block solved at the drive's
    phases of now with its signal and distortion gates) compiled against the Python reference:
    the same bits, blocks and results tick by tick while the drive's phases change between
    blocks, the carriers' amplitudes are switched off for a stretch (the signal gate) and the
    ratio gate is set between blocks' quadrature ratios (some blocks distorted, some not):
    catches phases read before the block is taken, a gate compared the wrong way or a flag not
    set on a block without signal."""
    from coiltrack.firmware.measure.demod import STEP_DISTORTED, STEP_FINISHED, STEP_NO_SIGNAL, STEP_SOLVED

    rng = np.random.default_rng(17)
    t, B, fl = _samples(rng, 900, sat_every=1_000_000)
    B[300:420] = B[300:420].mean(axis=0) + rng.normal(0, SIGMA, (120, 3))      # the drive off
    amp, ph = np.array([1.5, 1.4, 1.6]), np.array([0.3, -2.0, 1.1])
    rp, rc = SampleRing(64), SampleRing(64)
    dp = Demodulator(FREQS, W_US, HOP_US, SIGMA, 500, rp, fcore.PYTHON, (amp, ph))
    dc = Demodulator(FREQS, W_US, HOP_US, SIGMA, 500, rc, COMPILED, (amp, ph))
    assert dc.step.__func__ is Demodulator._step_compiled
    for d in (dp, dc):
        d.start(int(t[0]) + 1000, 777, amp, ph)
    ratios = []
    i, seen = 0, 0
    gates = (chi2_gate_9999(), 1.0, 1.0)                 # the blocks' ratios here: 0.3 to 2.1
    while i < len(t):
        for _ in range(2):
            if i < len(t):
                for r in (rp, rc):
                    r.push(int(t[i]), float(B[i, 0]), float(B[i, 1]), float(B[i, 2]), bool(fl[i]), 0)
                i += 1
        rp_ = dp.step(4, *gates)
        rc_ = dc.step(4, *gates)
        assert rp_ == rc_
        assert dp._st.tolist() == dc._st.tolist()
        if rp_ & STEP_SOLVED:
            _same(_state(dp), _state(dc))
            ratios.append(dp.quadrature_ratio())
        if rp_:
            seen |= rp_
            ph += 0.01                               # the drive's measured phases move between blocks
    assert seen & STEP_FINISHED and seen & STEP_NO_SIGNAL and seen & STEP_SOLVED
    assert seen & STEP_DISTORTED and min(ratios) < 1.0 < max(ratios)


def chi2_gate_9999():
    from coiltrack.firmware.estimate.ekf import chi2_gate

    return chi2_gate(9, 0.9999)


def test_demodulation_equals_scipy_least_squares_of_the_same_model():
    """Independent reference: one block's samples fitted by ``scipy.linalg.lstsq`` with the
    module docstring's model (DC, ramp, a cosine and a sine per carrier against t_ref); the
    compiled DC term equals its constant, and ``S + i Q`` its ``(a - i q) g`` with ``g = 1 / (H
    e^{i phi})``, to 1e-9 relative."""
    rng = np.random.default_rng(3)
    t, B, fl = _samples(rng, 60, sat_every=10**9)
    ref, t0 = 4321, int(t[0])
    phase = (0.4, -1.2, 2.5)
    d = Demodulator(FREQS, W_US, HOP_US, SIGMA, 500, None, COMPILED)
    d.start(t0, ref, (1.5, 1.5, 1.5), phase)
    for i in range(len(t)):
        k = d.push(int(t[i]), float(B[i, 0]), float(B[i, 1]), float(B[i, 2]), 0)
        if k == 0:
            break
    assert d.finish(0)
    sel = (t >= t0) & (t < t0 + W_US)
    ts = t[sel]
    cols = [np.ones(ts.size), (ts - t0) / W_US - 0.5]
    for f in FREQS:
        a = 2 * np.pi * f * (ts - ref) * 1e-6
        cols += [np.cos(a), np.sin(a)]
    X, *_ = scipy.linalg.lstsq(np.stack(cols, axis=1), B[sel])
    np.testing.assert_allclose(d.dc, X[0], rtol=1e-9)
    for j, f in enumerate(FREQS):
        u = f * 500e-6
        H = math.sin(math.pi * u) / (math.pi * u) * np.exp(-1j * math.pi * u)
        W = (X[2 + 2 * j] - 1j * X[3 + 2 * j]) / (H * np.exp(1j * phase[j]))
        scale = np.abs(W).max()
        np.testing.assert_allclose(d.S[:, j], W.real, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(d.Q[:, j], W.imag, rtol=0, atol=1e-9 * scale)


def test_a_pure_tone_demodulates_to_its_amplitude_in_closed_form():
    """Closed form: ``b(t) = c A cos(w (t - t_ref) + phi)`` on the sensor's x axis (no averaging),
    exact samples: S[0, k] = c (the coupling at the current amplitude ... times A, here A folded
    in: c A), Q = 0, the other carriers and axes 0, to 1e-9 of c A."""
    cA, phi, ref = 0.8e-6, 0.7, 5000
    d = Demodulator(FREQS, W_US, HOP_US, SIGMA, 0, None, COMPILED)
    d.start(0, ref, (1.0, 1.0, 1.0), (0.0, phi, 0.0))
    for t in range(0, 40_000, 1000):
        b = cA * math.cos(2 * math.pi * FREQS[1] * (t - ref) * 1e-6 + phi)
        k = d.push(t, b, 0.0, 0.0, 0)
        if k == 0:
            break
    assert d.finish(0)
    want = np.zeros((3, 3))
    want[0, 1] = cA
    np.testing.assert_allclose(d.S, want, rtol=0, atol=1e-9 * cA)
    np.testing.assert_allclose(d.Q, 0.0, rtol=0, atol=1e-9 * cA)


# ---------------------------------------------------------------------------------------- Raab's update
from coiltrack.firmware.pose.raab_correction import LoopCorrection, NoCorrection  # noqa: E402
from coiltrack.firmware.pose.raab_update import (ACQUIRED, K_OUT, Update, moment_pseudo_inverse,  # noqa: E402
                                                 sync_rotation)


def _raab_case(seed, core, correction=True, beta=None, theta=None, far=False, zero_signal=False):
    """One tracker's buffers from ``seed`` (the same for both cores) and an ``Update`` on them."""
    rng = np.random.default_rng(seed)
    n = 3
    mpa = memoryview(np.eye(3).reshape(-1) * 0.47 + rng.normal(0, 0.02, 9))
    cur = memoryview(rng.uniform(1.3, 1.7, n))
    mom, mp = memoryview(np.zeros(3 * n)), memoryview(np.zeros(3 * n))
    assert moment_pseudo_inverse(n, mpa, cur, mom, mp)
    x = memoryview(np.array([rng.uniform(-3, 3), rng.uniform(-1.2, 1.2) if beta is None else beta,
                             rng.uniform(0.15, 0.6), rng.uniform(-3, 3),
                             rng.uniform(-1.2, 1.2) if theta is None else theta, rng.uniform(-3, 3)]))
    Rn = np.zeros((3, 3))
    sync_rotation(x, memoryview(Rn))
    S = memoryview(np.zeros(3 * n) if zero_signal else rng.normal(0, 1e-6, 3 * n) * (0.3 / x[2]) ** 3)
    Sc, F = memoryview(np.zeros(3 * n)), memoryview(np.zeros(9))
    cbar = (0.001, -0.002, 0.0005)
    px, py, pz = (cbar[0] + x[2] * math.cos(x[1]) * math.cos(x[0]), cbar[1] + x[2] * math.cos(x[1]) * math.sin(x[0]),
                  cbar[2] - x[2] * math.sin(x[1]))
    off = 0.2 * x[2] if far else 0.01 * x[2]
    pm = memoryview(np.array([px + off, py - 0.5 * off, pz + 0.3 * off]))
    if correction:
        corr = LoopCorrection(n)
        Bv, Jv = rng.normal(0, 1e-6, 3 * n), rng.normal(0, 1e-5, 9 * n)
        corr.refresh(memoryview(Bv), memoryview(Jv), x, mpa, memoryview(np.full(3 * n, 1e7)), cur, (0.0, 0.0, 0.0),
                     False)
        corr.prepare((pm[0], pm[1], pm[2]), x, mp, cur, 2e-7 / x[2] ** 3)
        assert corr.lin and not corr.k_id
    else:
        corr = NoCorrection()
    upd = Update(n, x, Rn, S, Sc, mp, F, pm, cbar, cur, corr, 0.5, 0.01, core)
    assert upd.core == core.name
    return upd


def _raab_state(u):
    return (np.array(u.x), u.Rn.copy(), np.array(u.Sc), np.array(u.F), u.out.copy(), u.corrector.lin)


@pytest.mark.parametrize("case", [dict(), dict(correction=False), dict(far=True), dict(beta=1.45),
                                  dict(theta=-1.5), dict(beta=-1.5, theta=1.47),
                                  dict(zero_signal=True, correction=False)],
                         ids=["tracking", "no-correction", "lin-dropped", "pole-beta", "pole-theta", "both-poles",
                              "no-signal"])
def test_raab_update_bit_equal_to_the_reference(case):
    """Seeded poses and signals, three updates each: the compiled update leaves the same angles,
    rotation, corrected signals, coupling, clipped steps, k and the same linear-term flag as the
    Python, bit for bit, in the cases the reference branches on: the exact-loop correction with
    its preconditioner, none, the estimate beyond the linear term's range (dropped), each pole's
    modified conversion (|cos beta|, |cos theta| below POLE_COS) and a zero signal (k = 0: not
    updated). Catches a sign or an index of the Table II rotations, a clip of the wrong step, the
    preconditioner applied after the linear term was dropped, or a dropped pole branch."""
    for seed in range(6):
        up, uc = _raab_case(seed, fcore.PYTHON, **case), _raab_case(seed, COMPILED, **case)
        for _ in range(3):
            rp, rc = up.run(), uc.run()
            assert rp == rc
            _same(_raab_state(up), _raab_state(uc))
            if not rp:
                assert case.get("zero_signal") and up.out[K_OUT] == 0.0
                break
        else:
            assert not case.get("zero_signal")


@pytest.mark.parametrize("case", [dict(), dict(correction=False), dict(far=True), dict(zero_signal=True)],
                         ids=["tracking", "no-correction", "lin-dropped", "no-signal"])
def test_raab_couple_bit_equal_to_the_reference(case):
    """``Update.couple`` (the tracker's ``_coupling``: the signals corrected at the estimate, ``F =
    S_c M^+`` and ``k``) compiled against the Python, bit for bit, and the correction's linear term
    dropped in both beyond its range. Catches a point of the correction other than the estimate's,
    the linear term kept beyond its range, or ``k`` of the uncorrected signals."""
    for seed in range(6):
        up, uc = _raab_case(seed, fcore.PYTHON, **case), _raab_case(seed, COMPILED, **case)
        kp, kc = up.couple(), uc.couple()
        assert kp == kc and kp == up.out[K_OUT] == uc.out[K_OUT]
        _same(_raab_state(up), _raab_state(uc))
        assert up.corrector.lin == (not case.get("far") and case.get("correction", True))
        if case.get("zero_signal") and case.get("correction", True):
            assert kp > 0.0                         # the correction alone couples
        if case.get("correction") is False:
            assert np.array_equal(np.array(uc.Sc), np.array(uc.S))


@pytest.mark.parametrize("case", ["seeded", "zero-current", "planar", "collinear"])
def test_raab_pseudo_inverse_bit_equal_to_the_reference(case):
    """``Update.pseudo_inverse`` (``moment_pseudo_inverse``: the moments at the currents and ``M^+ =
    M^T (M M^T)^-1``) compiled against the Python, bit for bit, including the moments that do not
    span 3-D (a zero current, coplanar and collinear moments: False in both, ``mp`` untouched);
    and, independently, ``M M^+ = I`` against numpy to 1e-12 where they span. Catches a Gram
    element of the wrong pair, a determinant test of the wrong sign or ``M^+`` transposed."""
    for seed in range(6):
        up, uc = _raab_case(seed, fcore.PYTHON), _raab_case(seed, COMPILED)
        rng = np.random.default_rng(100 + seed)
        mpa = np.eye(3).reshape(-1) * 0.47 + rng.normal(0, 0.02, 9)
        cur = rng.uniform(1.3, 1.7, 3)
        if case == "zero-current":
            cur[:] = 0.0
        elif case == "planar":
            mpa[6:9] = 0.3 * mpa[0:3] - 0.7 * mpa[3:6]
        elif case == "collinear":
            mpa[3:6] = 2.0 * mpa[0:3]
            mpa[6:9] = -mpa[0:3]
        res = []
        for u in (up, uc):
            for j in range(3):
                u.cur[j] = cur[j]
            mom = memoryview(np.zeros(9))
            ok = u.pseudo_inverse(memoryview(mpa.copy()), mom)
            res.append((ok, np.array(mom), np.array(u.mp)))
        assert res[0][0] == res[1][0] == (case == "seeded")
        assert np.array_equal(res[0][1], res[1][1]) and np.array_equal(res[0][2], res[1][2])
        if case == "seeded":
            M = res[1][1].reshape(3, 3).T                   # (3, n): column j the moment of coil j
            Mp = res[1][2].reshape(3, 3)                    # (n, 3)
            np.testing.assert_allclose(M @ Mp, np.eye(3), rtol=0, atol=1e-12)
            np.testing.assert_allclose(Mp, np.linalg.pinv(M), rtol=1e-10, atol=0)


def test_raab_update_converges_on_an_exact_dipole_coupling():
    """Independent of the reference: signals made by Raab's dipole (eq 5, the sensor at a known
    pose, no correction) and the estimate started 0.05 rad and 5 % range off: the compiled
    updates reach the true angles and range to 1e-9 (Raab's detection is exact for the dipole)."""
    from coiltrack.firmware.model.field import dipole_polar
    from coiltrack.firmware.pose.raab_update import dcm

    n = 3
    mpa = memoryview(np.eye(3).reshape(-1) * 0.47)
    cur = memoryview(np.full(n, 1.5))
    mom, mp = memoryview(np.zeros(3 * n)), memoryview(np.zeros(3 * n))
    assert moment_pseudo_inverse(n, mpa, cur, mom, mp)
    truth = (0.6, -0.3, 0.35, 1.1, 0.4, -0.7)
    a = dcm(*truth[3:])
    u = (math.cos(truth[1]) * math.cos(truth[0]), math.cos(truth[1]) * math.sin(truth[0]), -math.sin(truth[1]))
    S = np.zeros(3 * n)
    for j in range(n):
        b = dipole_polar(*u, truth[2], mom[3 * j], mom[3 * j + 1], mom[3 * j + 2], False)
        S[3 * j:3 * j + 3] = np.array(a).reshape(3, 3) @ np.array(b)       # sensor frame: A b
    x = memoryview(np.array(truth) + np.array([0.05, -0.05, 0.0175, 0.05, 0.05, -0.05]))
    Rn = np.zeros((3, 3))
    sync_rotation(x, memoryview(Rn))
    upd = Update(n, x, Rn, memoryview(S), memoryview(np.zeros(3 * n)), mp, memoryview(np.zeros(9)),
                 memoryview(np.zeros(3)), (0.0, 0.0, 0.0), cur, NoCorrection(), 0.5, 0.01, COMPILED)
    for _ in range(12):
        assert upd.run()
    np.testing.assert_allclose(np.array(x), truth, rtol=0, atol=1e-9)
    assert upd.out[ACQUIRED] == 1.0


def _corr_pair(seed):
    """A LoopCorrection on each core and the same seeded fields, moments, weights and pose."""
    rng = np.random.default_rng(seed)
    n = 3
    x = memoryview(np.array([rng.uniform(-3, 3), rng.uniform(-1.4, 1.4), rng.uniform(0.15, 0.6),
                             rng.uniform(-3, 3), rng.uniform(-1.4, 1.4), rng.uniform(-3, 3)]))
    scale = (0.3 / x[2]) ** 3
    Bv = memoryview(rng.normal(0, 1e-6, 3 * n) * scale)
    Jv = memoryview(rng.normal(0, 1e-5, 9 * n) * scale)
    mpa = memoryview(np.eye(3).reshape(-1) * 0.47 + rng.normal(0, 0.02, 9))
    w = memoryview(rng.uniform(0.8e7, 1.2e7, 3 * n))
    cur = memoryview(rng.uniform(1.3, 1.7, n))
    mom, mp = memoryview(np.zeros(3 * n)), memoryview(np.zeros(3 * n))
    assert moment_pseudo_inverse(n, mpa, cur, mom, mp)
    cp, cc = LoopCorrection(n, fcore.PYTHON), LoopCorrection(n, COMPILED)
    assert cp.core == "python" and cc.core == "compiled"
    return cp, cc, x, Bv, Jv, mpa, w, cur, mp, rng


def test_loop_correction_refresh_and_preconditioner_bit_equal_to_the_reference():
    """The correction refreshed twice (the second against the first's linear term moved by a
    seeded shift: the noise-weighted shift of eq. ``refresh``) and ``K = I + G D T`` formed and
    LU-factored: the same b, G, rel, shift, K, permutation and k_ok as the Python, bit for bit
    (catches a dipole gradient element swapped, the weight's max over the wrong axes, a pivot
    chosen otherwise)."""
    for seed in range(8):
        cp, cc, x, Bv, Jv, mpa, w, cur, mp, rng = _corr_pair(seed)
        dd = tuple(rng.normal(0, 0.01, 3))
        for shift_ok in (False, True):
            sp = cp.refresh(Bv, Jv, x, mpa, w, cur, dd, shift_ok)
            sc = cc.refresh(Bv, Jv, x, mpa, w, cur, dd, shift_ok)
            assert sp == sc and cp.rel == cc.rel
            assert np.array_equal(np.array(cp.b), np.array(cc.b)) and np.array_equal(np.array(cp.G), np.array(cc.G))
        assert sp > 0.0
        k = 2e-7 / x[2] ** 3
        cp.precondition(x, mp, cur, k)
        cc.precondition(x, mp, cur, k)
        assert cp.k_ok == cc.k_ok
        _same(cp.kernel_buffers(), cc.kernel_buffers())


def test_preconditioner_of_a_zero_correction_is_the_identity():
    """Edge case, in both: a correction of zero (b = G = 0: the loop equals Raab's dipole) has
    ``K = I + G D T = I`` exactly, factored without a row exchange (catches a missing identity or
    a column written into the wrong row)."""
    cp, cc, x, Bv, Jv, mpa, w, cur, mp, rng = _corr_pair(3)
    for c in (cp, cc):
        for i in range(len(c.b)):
            c.b[i] = 0.0
        for i in range(len(c.G)):
            c.G[i] = 0.0
        c.precondition(x, mp, cur, 2e-7 / x[2] ** 3)
        assert c.k_ok
        b, G, K, perm = c.kernel_buffers()
        np.testing.assert_array_equal(np.array(K).reshape(6, 6), np.eye(6))
        assert list(perm) == list(range(6))
