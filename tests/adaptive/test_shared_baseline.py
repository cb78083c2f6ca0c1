"""Amplitudes of back-to-back pulses share baseline samples (``estimate.shared_baseline``):
their errors are correlated, and counting the shared part twice in each bounds them.

The reference is the firmware's own window extraction taken apart: it is linear in the
samples, so feeding it one unit sample at a time gives its exact weights ``W`` and the exact
covariance ``sigma^2 W W^T`` of a chain of amplitudes (no Monte Carlo), against which the
variances the filter is given are checked in the Loewner order."""
import numpy as np
import pytest

from coiltrack.firmware.config import ConfigError, config_from_dict
from coiltrack.firmware.estimate.shared_baseline import SharedBaselines, next_start, span_overlap
from coiltrack.firmware.measure.pulse import PulseExtractor, SampleRing

SETTLE, FALL, GUARD, BASE = 3_000, 3_000, 2_000, 35_000
SIGMA = 3e-8
PER = 10_000                       # 100 Hz
LENGTH = 60_000
GAP = FALL + BASE + GUARD          # the single-coil mode's back-to-back spacing (PulseBook gap_us)


def _times(edges, phase_us: int):
    return list(range(edges[0][0] - 60_000 + phase_us, edges[-1][1] + 60_000 + 60_000, PER))


def _chain(n_pulses: int, gap_us: int, phase_us: int):
    """Pulse edges and the extraction's weights ``W`` (n_pulses, n_samples) on the x axis, its
    variances and baseline counts, for ``n_pulses`` pulses ``gap_us`` apart."""
    t0 = 200_000
    edges = []
    s = t0
    for _ in range(n_pulses):
        edges.append((s, s + LENGTH))
        s += LENGTH + gap_us
    times = _times(edges, phase_us)
    W = np.zeros((n_pulses, len(times)))
    var = np.zeros(n_pulses)
    info = np.zeros((n_pulses, 4), dtype=np.int64)
    for j in range(-1, len(times)):
        ring = SampleRing(256)
        ext = PulseExtractor(ring, settle_us=SETTLE, fall_us=FALL, baseline_us=BASE, guard_us=GUARD,
                             min_pulse_samples=3, min_baseline_samples=2, sigma_t=SIGMA)
        for i, t in enumerate(times):
            ring.push(t, 1e-6 if i == j else 0.0, 0.0, 0.0, False, 0)
        amp, v = np.zeros(3), np.zeros(3)
        for k, (a, b) in enumerate(edges):
            _, n_u, n_b = ext.extract(a, b, amp, v)
            if j >= 0:
                W[k, j] = amp[0] / 1e-6
            else:
                var[k] = v[0]
                first, last = ext.last_used_span()
                info[k] = (n_u, n_b, first, last)
    return edges, W, var, info


def _used(edges, var, info, enabled=True, earliest_after_last=-1):
    """The variances a filter takes the chain with (``SharedBaselines``, windows closed in
    order, each with the next pulse already commanded but the last)."""
    sh = SharedBaselines(FALL, BASE, GUARD, SIGMA, PER, enabled)
    out = np.zeros(len(edges))
    for k, (a, b) in enumerate(edges):
        nxt = edges[k + 1][0] if k + 1 < len(edges) else -1
        sh.close(a, b, nxt, earliest_after_last)
        out[k] = sh.variance(np.full(3, var[k]), info[k])[0]
    return out


@pytest.mark.parametrize("phase_us", [0, 2_500, 5_000, 7_500])
def test_back_to_back_amplitudes_are_correlated_and_the_counted_variances_bound_them(phase_us):
    """Four 60 ms pulses 40 ms apart (fall + baseline + guard): the extraction's own variance is
    exact for each amplitude alone (``diag(sigma^2 W W^T)``), but neighbours correlate (0.1-0.3,
    the closed form ``(1/(2 n_b)) / (1/n_u + 1/n_b)`` = 0.22 for 5.5 and 7 samples), and taken as
    independent they understate the chain (``diag(var) - C`` has a negative eigenvalue). The
    variances of ``SharedBaselines`` bound it: ``diag(used) - C`` is positive semi-definite.
    Catches the shared side left out, counted once only, or counted in one pulse of a pair."""
    edges, W, var, info = _chain(4, GAP, phase_us)
    C = SIGMA ** 2 * W @ W.T
    assert np.allclose(np.diag(C), var, rtol=1e-9)           # the extraction's variance, alone
    rho = C[0, 1] / np.sqrt(C[0, 0] * C[1, 1])
    assert 0.1 < rho < 0.35
    assert C[0, 2] == pytest.approx(0.0, abs=1e-30)           # one pulse apart: nothing shared
    assert np.linalg.eigvalsh(np.diag(var) - C).min() < -0.05 * var.min()
    used = _used(edges, var, info)
    assert np.linalg.eigvalsh(np.diag(used) - C).min() >= -1e-12 * var.min()
    # the shared samples' part is exact: the sum of the extraction's own squared weights over them
    for k in range(4):
        a, b = edges[k]
        shared = np.zeros(W.shape[1], dtype=bool)
        for j, t in enumerate(_times(edges, phase_us)):
            if k > 0 and b - LENGTH - BASE <= t <= a - GUARD and edges[k - 1][1] + FALL <= t:
                shared[j] = True
            if k < 3 and b + FALL <= t <= b + FALL + BASE and edges[k + 1][0] - BASE <= t:
                shared[j] = True
        assert used[k] - var[k] == pytest.approx(SIGMA ** 2 * np.sum(W[k, shared] ** 2), rel=1e-9)
    # the middle pulses, sides even, share both: sigma^2 (1/n_u + 2/n_b), the chain's variance
    if phase_us == 5_000:
        assert used[1] == pytest.approx(var[1] + SIGMA ** 2 / info[1, 1], rel=1e-12)
    # ignored: the amplitudes' own variances
    assert np.array_equal(_used(edges, var, info, enabled=False), var)


def test_the_filter_on_the_bound_is_never_overconfident_and_on_the_raw_variances_it_is():
    """A scalar Kalman filter (state ``x``, prior variance ``p0``) taking the chain ``z_k = x + e_k``
    one at a time, as the single-coil EKF does (Schepers eq 4 in one dimension): its final variance
    against the actual error variance of the estimate it forms, computed exactly from ``W``
    (``x_hat - x = sum g_k e_k - (1 - sum g_k) x0_err``). With the counted variances the filter's
    variance is at least the actual one; with the raw ones it is below (the overconfidence)."""
    edges, W, var, info = _chain(8, GAP, 5_000)
    C = SIGMA ** 2 * W @ W.T
    p0 = 1e-12

    def run(r):
        p, coeff = p0, np.zeros(len(r))      # x_hat error = a0 * prior error + coeff . e
        a0 = 1.0
        for k, rk in enumerate(r):
            g = p / (p + rk)
            a0 *= 1.0 - g
            coeff *= 1.0 - g
            coeff[k] += g
            p = (1.0 - g) * p
        actual = a0 * a0 * p0 + coeff @ C @ coeff
        return p, actual

    p_raw, act_raw = run(var)
    p_used, act_used = run(_used(edges, var, info))
    assert p_raw < 0.9 * act_raw
    assert p_used >= act_used


def test_spaced_pulses_share_nothing_and_the_fixed_cycle_keeps_its_variances():
    """The fixed cycle's spacing (60 ms pulses 140 ms apart: 80 ms gaps) leaves the baselines
    disjoint: no correlation, and nothing is added (its figures do not change)."""
    edges, W, var, info = _chain(3, 80_000, 5_000)
    C = SIGMA ** 2 * W @ W.T
    assert np.allclose(C, np.diag(var), rtol=1e-9, atol=1e-30)
    assert np.array_equal(_used(edges, var, info), var)


def test_the_after_side_counts_when_a_pulse_not_yet_commanded_could_still_share_it():
    """The last window of a chain is closed before the next pulse is decided: its after side is
    counted when the earliest start a new pulse may have would put that pulse's before span on it
    (by the overlap's fraction), and not when the earliest start is two baselines away."""
    sh = SharedBaselines(FALL, BASE, GUARD, SIGMA, PER)
    assert sh.close(100_000, 160_000, -1, 160_000 + GAP) == pytest.approx(33_000 / 35_000)
    sh = SharedBaselines(FALL, BASE, GUARD, SIGMA, PER)
    assert sh.close(100_000, 160_000, -1, 160_000 + FALL + 2 * BASE + GUARD) == 0.0
    assert sh.close(400_000, 460_000, -1, -1) == 0.0         # none may follow (the fixed cycle's close)
    # a commanded next pulse decides; the previous pulse's after span decides the before side
    sh = SharedBaselines(FALL, BASE, GUARD, SIGMA, PER)
    sh.close(100_000, 160_000, 200_000, 200_000)
    assert sh.before_after(200_000, 260_000, 160_000, -1) == (pytest.approx(33_000 / 33_000), 0.0)
    assert sh.close(200_000, 260_000, 300_000, -1) == pytest.approx(1.0 + 33_000 / 35_000)


def test_overlap_and_next_start_closed_forms():
    assert span_overlap(0, 10, 5, 20) == 0.5
    assert span_overlap(0, 10, -5, 20) == 1.0
    assert span_overlap(0, 10, 10, 20) == 0.0
    assert span_overlap(5, 5, 0, 10) == 0.0

    class Slot:
        def __init__(self, active, start):
            self.active, self.start = active, start
    a, b, c, d = Slot(True, 100), Slot(True, 300), Slot(True, 200), Slot(False, 150)
    assert next_start((a, b, c, d), a) == 200
    assert next_start((a, b, c, d), b) == -1


def test_the_prediction_of_a_decision_uses_the_chain_variance():
    """A decision predicts ``sigma^2 (1/n_u + 2/n_b)`` for a pulse back to back with the previous one
    (nominal ``n_b = 2 baseline / T`` = 6 here), ``1/n_u + 1.5/n_b`` after a quiet gap (its after side
    may still be shared), and the raw variance with the bound off."""
    sh = SharedBaselines(FALL, BASE, GUARD, SIGMA, PER)
    v = SIGMA ** 2 * (1 / 5 + 1 / 6)
    assert sh.n_base == 6
    assert sh.predicted(v, 200_000, 200_000 - GAP) == pytest.approx(SIGMA ** 2 * (1 / 5 + 2 / 6), rel=1e-12)
    assert sh.predicted(v, 200_000, 0) == pytest.approx(SIGMA ** 2 * (1 / 5 + 1.5 / 6), rel=1e-12)
    assert sh.chained(v) == pytest.approx(SIGMA ** 2 * (1 / 5 + 2 / 6), rel=1e-12)
    off = SharedBaselines(FALL, BASE, GUARD, SIGMA, PER, enabled=False)
    assert off.predicted(v, 200_000, 200_000 - GAP) == v and off.chained(v) == v


def test_a_bad_baseline_sharing_is_refused_naming_the_key():
    with pytest.raises(ConfigError) as e:
        config_from_dict({"adaptive": {"baseline_sharing": "twice"}})
    assert e.value.key == "adaptive.baseline_sharing"
    assert config_from_dict({"adaptive": {"baseline_sharing": "ignore"}}).adaptive.baseline_sharing == "ignore"


def test_apart_keeps_the_next_before_baseline_off_this_after_baseline():
    """``pulse_gap_us``: back to back (``bound``) the next pulse's before span lies on this one's
    after span (33 of its 35 ms); ``apart`` starts it one baseline and guard later, where the two
    spans are disjoint and the extraction's weights show no correlation; the bound then adds
    nothing, and a decision predicts nothing either."""
    from coiltrack.firmware.estimate.shared_baseline import pulse_gap_us
    from coiltrack.tools.scenarios import thesis as scenarios

    cfg = scenarios.schepers_adaptive_config()
    assert pulse_gap_us(cfg) == FALL + BASE + GUARD
    apart = cfg.with_keys(baseline_sharing="apart")
    gap = pulse_gap_us(apart)
    assert gap == FALL + 2 * BASE + 2 * GUARD
    sh = SharedBaselines(FALL, BASE, GUARD, SIGMA, PER)
    assert sh.before_after(200_000, 260_000, 200_000 - GAP, -1)[0] == pytest.approx(33_000 / 33_000)
    assert sh.before_after(200_000, 260_000, 200_000 - gap, 260_000 + gap) == (0.0, 0.0)
    for phase in (0, 5_000):
        edges, W, var, info = _chain(3, gap, phase)
        C = SIGMA ** 2 * W @ W.T
        assert np.allclose(C, np.diag(var), rtol=1e-9, atol=1e-30)
        assert np.array_equal(_used(edges, var, info, earliest_after_last=edges[-1][1] + gap), var)
    ap = SharedBaselines(FALL, BASE, GUARD, SIGMA, PER, apart=True)
    v = SIGMA ** 2 * (1 / 5 + 1 / 6)
    assert ap.predicted(v, 200_000, 200_000 - gap) == v and ap.chained(v) == v


@pytest.mark.parametrize("mode", ["bound", "apart"])
def test_live_ticks_allocate_nothing_and_back_to_back_pulses_are_counted(mode):
    """A live 8 s ``schepers-adaptive`` run with the bound (and with the pulses apart): no tick
    creates a numpy array; with ``bound`` the windows closed after the warm-up were mostly shared
    on both sides (pulses back to back), with ``apart`` none was shared and the pulses are at
    least ``pulse + fall + 2 baseline + 2 guard`` apart."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available
    from coiltrack.tools.bench.runner import BenchSetup
    from coiltrack.tools.scenarios import get

    if not available():
        pytest.skip("numpy memory handler API not reachable")
    from coiltrack.tools.scenarios.thesis import schepers_adaptive_config

    sc = get("schepers-adaptive")
    # the scenario's filter with 60 ms pulses (LENGTH) and the other policy keys at their defaults
    cfg = schepers_adaptive_config(field_model_rel_sigma=3e-3, baseline_sharing=mode, adaptive_current_step_a=0.001)
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 3, 8.0, emu_end)
    fw = Firmware(cfg, fw_end)
    sh = fw.tracker.sharing
    counter = NumpyAllocationCounter()
    allocating = 0
    shared = []
    for t in range(0, 8_000_001, cfg.timing.tick_us):
        bench.emulator.step(t)
        before = counter.count
        n0 = sh.prev_end
        with counter:
            fw.tick(t)
        allocating += counter.count != before
        if sh.prev_end != n0 and t > 4_000_000:
            shared.append(sh.shared)
    assert fw.status()["adaptive_updates"] > 30 and len(shared) > 10
    assert allocating == 0
    if mode == "bound":
        assert np.mean(np.array(shared) > 1.5) > 0.5
    else:
        assert max(shared) == 0.0
        ex = sorted(e["start_us"] for e in bench.driver.executed if e["start_us"] > 4_000_000)
        assert min(np.diff(ex)) >= LENGTH + FALL + 2 * BASE + 2 * GUARD - 1_000
