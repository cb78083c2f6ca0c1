"""The pulse length as a lever of the adaptive policy (``actuate.pulse_length``,
``CoilChooser.choose_length``), checked against closed forms and the real window extraction."""
import math

import numpy as np
import pytest

from coiltrack.firmware.actuate.coil_choice import CoilChooser, SingleCoilModel, posterior_pose_variances
from coiltrack.firmware.actuate.pulse_length import PulseLengths, window_samples
from coiltrack.firmware.config import ConfigError, config_from_dict
from coiltrack.firmware.measure.pulse import PULSE_TOO_FEW, PulseExtractor, SampleRing
from coiltrack.firmware.model.field import Coil
from coiltrack.tools.scenarios import thesis as scenarios


def _cfg(**kw):
    return scenarios.schepers_adaptive_config(pulse_length="chosen", **kw)


def _extract(cfg, length_us: int, phase_us: float):
    """The firmware's extractor on a constant pulse of ``length_us`` whose samples (100 Hz,
    noise-free) fall at ``start + phase_us + k T``: (flags, n_pulse, n_base, var)."""
    per = 1e6 / cfg.pulse.mag_rate_hz
    ring = SampleRing(64)
    start = 500_000
    ext = PulseExtractor(ring, settle_us=cfg.pulse.settle_us, fall_us=cfg.pulse.fall_us, baseline_us=cfg.pulse.baseline_us,
                         guard_us=cfg.pulse.guard_us, min_pulse_samples=cfg.pulse.min_pulse_samples,
                         min_baseline_samples=cfg.pulse.min_baseline_samples, sigma_t=cfg.pulse.mag_sigma_t)
    for k in range(-8, 20):
        t = int(round(start + phase_us + k * per))
        on = start <= t <= start + length_us
        ring.push(t, 20e-6 + (3e-6 if on else 0.0), -5e-6, 40e-6, False, 0)
    amp, var = np.zeros(3), np.zeros(3)
    flags, n_p, n_b = ext.extract(start, start + length_us, amp, var)
    assert flags & PULSE_TOO_FEW or amp[0] == pytest.approx(3e-6, rel=1e-9)
    return flags, n_p, n_b, float(var[0])


def test_chosen_lengths_keep_m_minus_one_samples_through_the_extraction():
    """``L = settle/2 + m T + guard/2`` with a sample settle/2 after the start edge: the real
    extractor (settle 3 ms, guard 2 ms, first and last in-pulse samples dropped) uses ``m - 1``
    samples and 3 + 3 baseline samples, and its variance is ``sigma^2 (1/(m-1) + 1/6)`` (the
    baselines are symmetric about the used samples' mean time: no slope term), the value the
    chooser weighs. Catches a length the extraction cannot use (fewer than min_pulse_samples),
    a wrong phase, and a variance without the baseline term."""
    cfg = _cfg()
    L = PulseLengths.chosen(cfg, 80_000)
    assert L.lengths_us == (42_500, 52_500, 62_500, 72_500)
    s2 = cfg.pulse.mag_sigma_t ** 2
    for k, length in enumerate(L.lengths_us):
        m = k + 4
        flags, n_p, n_b, var = _extract(cfg, length, L.lead_in_us)
        assert not flags & PULSE_TOO_FEW and n_p == m - 1 >= cfg.pulse.min_pulse_samples and n_b == 6
        assert var == pytest.approx(s2 * (1.0 / (m - 1) + 1.0 / 6.0), rel=1e-9)
        assert L.var_amp[k] == pytest.approx(var, rel=1e-12)
        assert L.mid_us[k] == 1_500 + 5_000 * m             # the used samples' mean time
        assert window_samples(length, L.lead_in_us, 10_000, cfg.pulse.settle_us, cfg.pulse.guard_us, cfg.pulse.fall_us,
                              cfg.pulse.baseline_us) == (n_p, n_b)
    # the same 42.5 ms at another phase loses a sample and is refused: alignment is what makes it usable
    flags, n_p, _, _ = _extract(cfg, 42_500, 6_000)
    assert flags & PULSE_TOO_FEW and n_p == 2
    # the fixed cycle's 60 ms pulses at the bench's phase (2.58 ms): 4 used, 6 baseline samples
    assert window_samples(60_000, 2_584, 10_000, cfg.pulse.settle_us, cfg.pulse.guard_us, cfg.pulse.fall_us, cfg.pulse.baseline_us) == (4, 6)


def test_align_puts_a_sample_half_the_settle_time_after_the_start():
    """``align``: the earliest start at or after the asked one with a sample ``lead_in`` after
    it (closed form on a 10 ms clock); the fixed lengths are never moved."""
    L = PulseLengths.chosen(_cfg(), 80_000)
    for asked in (1_000_000, 1_001_000, 1_002_583, 1_009_999):
        s = L.align(asked, 2_584)
        assert s >= asked and s - asked < 10_000 and (s + 1_500 - 2_584) % 10_000 == 0
    assert PulseLengths.fixed(_cfg(), 60_000).align(1_001_000, 2_584) == 1_001_000


def _case(rel_model: float):
    coils = [Coil((0, 0, 0), a, 0.055, 50) for a in np.eye(3)]
    model = SingleCoilModel(coils)
    p = np.array([0.12, 0.04, -0.03])
    th = 0.4
    R = np.array([[math.cos(th), -math.sin(th), 0.0], [math.sin(th), math.cos(th), 0.0], [0.0, 0.0, 1.0]])
    model.evaluate(p, R)
    P6 = np.diag([4e-6, 3e-6, 5e-6, 2e-5, 3e-5, 2.5e-5])
    P6[0, 3] = P6[3, 0] = 1e-6
    smax = [1.2e-3] * 3 + [3e-3] * 3
    smin = [1.0e-3] * 3 + [2.5e-3] * 3
    ch = CoilChooser(3, np.geomspace(0.01, 2.0, 4000), smax, smin, rel_model, 0.0, trace=True)
    return ch, model, P6


def test_choose_length_minimises_energy_per_information_in_closed_form():
    """Without model error eq 4 depends on ``I^2 / var(L)`` only, so the pair reaching
    ``sigma_min`` at least energy has ``I^2 L`` proportional to ``L (1/n_u + 1/n_b)``: with
    ``n_u = 3..6`` and ``n_b = 6`` the 42.5 ms pulse (21.25 ms against 21.9, 22.9 and 24.2).
    Dropping ``1/n_b`` would pick the longest (``L / n_u``: 14.2, 13.1, 12.5, 12.1). Each
    energy is checked against the closed form (on a fine current ladder) and the choice
    against a brute-force search over every pair."""
    cfg = _cfg()
    L = PulseLengths.chosen(cfg, 80_000)
    ch, model, P6 = _case(0.0)
    lim = np.full(3, 2.0)
    c = ch.choose_length(P6, model, list(L.var_amp), L.lengths_us, lim)
    assert c >= 0 and ch.reached and L.lengths_us[ch.length] == 42_500
    # closed form: the current each length needs scales as sqrt(var), the energy as L var
    i_ref = ch.current / math.sqrt(L.var_amp[ch.length])
    goal = ch._goal()
    out = np.zeros(6)
    best = None
    for k, (length, var) in enumerate(zip(L.lengths_us, L.var_amp)):
        i_need = None
        for i in ch.currents:
            posterior_pose_variances(P6, ch._A[c], ch._M[c], float(ch._hn2[c]), float(i), var, 0.0, out, 0.0)
            if out[ch.target:ch.target + 3].sum() <= goal:
                i_need = float(i)
                break
        assert i_need == pytest.approx(i_ref * math.sqrt(var), rel=2e-3)
        e = i_need * i_need * length
        if best is None or e < best[0]:
            best = (e, k)
    assert best[1] == ch.length


def test_model_error_keeps_the_energy_ratio_of_the_lengths():
    """With the field-model error ``(rel I |h|)^2`` in R (the information saturates with the
    current), eq 4 depends on ``I^2 |h|^2 / (var + rel^2 I^2 |h|^2)``, so the current a goal needs
    obeys ``I^2 = k var / (1 - k rel^2)``: still proportional to ``var(L)``. The shortest length
    is chosen and its energy is ``21.25 / 24.17`` of the longest's, as without model error
    (closed form, within the current ladder's step). Near the source, where the goal needs more
    than saturation allows, none reaches it and the longest length at the largest current is
    kept (the most a pulse can bring)."""
    cfg = _cfg()
    L = PulseLengths.chosen(cfg, 80_000)
    ch, model, P6 = _case(3e-3)
    lim = np.full(3, 2.0)
    ch.choose_length(P6, model, list(L.var_amp), L.lengths_us, lim)
    assert ch.reached and ch.length == 0
    e_short = ch.current ** 2 * L.lengths_us[0]
    ch2, _, _ = _case(3e-3)
    ch2.choose(P6, model, L.var_amp[-1], lim)
    e_long = ch2.current ** 2 * L.lengths_us[-1]
    ratio = (L.lengths_us[0] * L.var_amp[0]) / (L.lengths_us[-1] * L.var_amp[-1])
    assert ratio == pytest.approx(21.25 / 24.1667, rel=1e-4)
    assert e_short / e_long == pytest.approx(ratio, rel=5e-3)
    ch3, _, _ = _case(3e-3)
    f = math.sqrt(0.03)
    ch3.set_bounds(ch3.sigma_max * f, ch3.sigma_min * f)
    ch3.choose_length(P6 * 0.03, model, list(L.var_amp), L.lengths_us, lim)
    assert not ch3.reached and ch3.length == L.n - 1 and ch3.current == float(ch3.currents[-1])


@pytest.mark.parametrize("rel_model", [0.0, 3e-3])
def test_unreached_pulse_takes_the_length_of_least_energy_for_its_share(rel_model):
    """The driver allows 20 mA, too little for ``sigma_min`` at any length: with ``unreached_share``
    0.8 the goal is 80 % of the reduction of the longest length at 20 mA (``unreached_goal``), and the
    42.5 ms pulse reaches it for ``21.25 / 24.17`` of the energy the longest needs (the closed form of
    :func:`test_model_error_keeps_the_energy_ratio_of_the_lengths`: ``I^2`` proportional to ``var(L)``).
    At 10 mA the 52.5 ms pulse at the limit reaches it too: ``52.5 / 72.5`` of the energy at the same
    current. Before, an unreached pulse was always the longest (catches that, and a goal taken from
    a shorter length's largest current)."""
    L = PulseLengths.chosen(_cfg(), 80_000)
    for lim, k_want, ratio in ((0.02, 0, 21.25 / 24.1667), (0.01, 1, 52.5 / 72.5)):
        ch, model, P6 = _case(rel_model)
        ch.unreached_share = 0.8
        c = ch.choose_length(P6, model, list(L.var_amp), L.lengths_us, np.full(3, lim))
        assert c >= 0 and not ch.reached and ch.length == k_want
        ref, _, _ = _case(rel_model)
        ref.unreached_share = 0.8
        assert ref.choose(P6, model, L.var_amp[-1], np.full(3, lim)) == c
        # the same goal: the longest at the limit, 80 % of its reduction
        prior = ch._prior(P6)
        best = ref._target_after(P6, c, L.var_amp[-1], lim)
        goal = prior - 0.8 * (prior - best)
        assert ch._target_after(P6, c, L.var_amp[ch.length], ch.current) <= goal * (1 + 1e-12)
        e = ch.current ** 2 * L.lengths_us[ch.length] / (ref.current ** 2 * L.lengths_us[-1])
        assert e == pytest.approx(ratio, rel=5e-3)


def test_bad_pulse_length_is_refused_naming_the_key():
    with pytest.raises(ConfigError) as e:
        config_from_dict({"adaptive": {"pulse_length": "short"}})
    assert e.value.key == "adaptive.pulse_length"


def test_chosen_lengths_end_to_end_allocate_nothing_and_every_window_is_used():
    """``pulse_length = "chosen"`` with ``unreached_share`` on the bench for 8 s (seed 3): every pulse
    after the acquisition burst and the warm-up is one of ``PulseLengths.chosen``'s lengths (to the
    driver clock's microsecond), their
    windows are extracted (no flagged window, single-coil updates made) and no tick creates a numpy
    array (the length choice included). Catches a length the extraction refuses or a window closed at
    the wrong edge."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools import scenarios as sc_reg
    from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.bench.runner import BenchSetup

    cfg = _cfg(unreached_share=0.8, adaptive_current_step_a=0.001)
    sc = sc_reg.get("schepers-adaptive")
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 3, 8.0, emu_end)
    fw = Firmware(cfg, fw_end)
    counter = NumpyAllocationCounter() if available() else None
    allocating, t = 0, 0
    while t <= 8_000_000:
        bench.emulator.step(t)
        if counter is not None:
            before = counter.count
            with counter:
                fw.tick(t)
            allocating += counter.count != before
        else:
            fw.tick(t)
        t += cfg.timing.tick_us
    s = fw.status()
    assert allocating == 0 and s["windows_flagged"] == 0 and s["adaptive_updates"] > 40
    lengths = set(PulseLengths.chosen(cfg, cfg.timing.pulse_us + 20_000).lengths_us)
    late = [e for e in bench.driver.executed if e["start_us"] > 4_000_000]
    assert len(late) > 20
    # the driver's clock runs on its own: an executed length is within 2 us of a commanded one
    assert all(min(abs(e["end_us"] - e["start_us"] - L) for L in lengths) <= 2 for e in late)
