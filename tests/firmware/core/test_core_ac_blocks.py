"""The AC measure stage's tick in one compiled call (``firmware_py/core/src/ac_blocks.c``
``ct_ac_blocks_step``) against its Python reference (``measure.ac_blocks.ACBlockMeasurement._tick``:
each channel's ``Demodulator.step``, the solved blocks' bookkeeping, the hand-over of a block every
channel has solved), tick by tick on seeded samples, bit for bit: the stage's state and counters,
the schedule's per-coil edges and currents, every channel's burst (S, var, flags, done, middle,
change count) and its earth ring. Two sensors (a hand-over waits for both), a stretch with the
drive off (the no-signal gate), a sensor near a conductor (a lagging quadrature: the distortion
gate) and a tracker that keeps a block (the next one skipped). Skipped where the extension is not
built."""
import math

import numpy as np
import pytest

from coiltrack.firmware import core as fcore
from coiltrack.firmware.actuate.schedule import PulseSchedule
from coiltrack.firmware.measure.ac_blocks import ACBlockMeasurement
from coiltrack.firmware.measure.windows import SensorChannel
from coiltrack.tools.scenarios.ac import ac_config

pytestmark = pytest.mark.skipif(not fcore.available(), reason="the compiled core is not built")


class _Drive:
    """The actuation's part the measure stage reads: an accepted plan and its measured phasors."""

    def __init__(self, n):
        self.ready = True
        self.plan_id = 3
        self.on_us = 200_000
        self.ref_us = 123_457
        self.amplitude_a = np.array([1.5, 1.45, 1.52][:n])
        self.phase_rad = np.array([0.02, -0.01, 0.03][:n])


def _stage(cfg, core, nodes):
    n = len(cfg.source.coils)
    chans = [SensorChannel(node, cfg, core) for node in nodes]
    sched = PulseSchedule(n, None, [1.0] * n)
    m = ACBlockMeasurement(cfg, chans, sched, _Drive(n), core=core)
    return m, chans, sched


def _field(rng, t_us, cfg, coupling, quad, on):
    """A sample (T) at ``t_us``: an earth field, each coil's carrier through ``coupling`` (3, n) at
    the drive's measured phase, averaged over the magnetometer's integration time ``T_i`` before
    the sample (``sinc(f T_i)``, delayed ``T_i / 2``), a lagging part ``quad`` of it (an eddy
    current), noise."""
    ti = cfg.ac.mag_integration_us * 1e-6
    dt = (t_us - 123_457) * 1e-6 - 0.5 * ti
    b = np.array([20e-6, -4e-6, 41e-6]) + rng.normal(0.0, 1.2e-7, 3)
    if on:
        for k, f in enumerate(cfg.ac.ac_freqs_hz):
            w = 2 * math.pi * f * dt + _Drive(3).phase_rad[k]
            g = math.sin(math.pi * f * ti) / (math.pi * f * ti)
            b = b + g * coupling[:, k] * (math.cos(w) + quad * math.sin(w))
    return b


def _state(m, chans, sched):
    out = [m._st.copy(), m._fs.copy(), m.solved_k.copy(), m._dist.copy(), m._qr.copy(), sched.start.copy(),
           sched.end.copy(), sched.measured.copy()]
    for ch in chans:
        out += [ch.S.copy(), ch.var.copy(), ch.flags.copy(), ch.done.copy(), ch.pulse_mid.copy(), ch.changes]
    for e in m._earth:
        out += [len(e), e.t.copy(), e.b.copy()]
    return out


def _same(a, b, t):
    for i, (x, y) in enumerate(zip(a, b)):
        if isinstance(x, np.ndarray):
            assert np.array_equal(x, y), (t, i, x, y)
        else:
            assert x == y, (t, i, x, y)


def test_the_compiled_tick_equals_the_reference_bit_for_bit():
    """Both stages fed the same samples tick by tick (1 kHz with jitter, a dropped sample, the
    drive off for 60 ms, a growing quadrature on the second sensor, the tracker keeping every
    fifth block a tick too long): after every tick the same state, bit for bit; the run covers
    hand-overs, skipped blocks, no-signal and distorted blocks, so a counter, a gate or a copy
    that differs shows."""
    cfg = ac_config(fusion=False)
    n = len(cfg.source.coils)
    rng = np.random.default_rng(5)
    coupling = [rng.normal(0.0, 2e-6, (3, n)) for _ in range(2)]
    py, cp = _stage(cfg, fcore.PYTHON, (16, 17)), _stage(cfg, fcore.DEFAULT, (16, 17))
    assert py[0].core == "python" and cp[0].core == "compiled"
    seen = {"handed": 0, "skipped": 0, "no_signal": 0, "distorted": 0}
    hold = 0
    for tick in range(1_500):
        t = 200_000 + tick * 1000
        on = not 700 <= tick < 760
        for c in range(2):
            if tick % 97 == 13:
                continue                                   # a sample lost
            ts = t - 300 + int(rng.integers(-40, 41))
            quad = 0.0 if c == 0 else 0.2 * max(0.0, (tick - 900) / 600)
            b = _field(rng, ts, cfg, coupling[c], quad, on)
            for stage in (py, cp):
                stage[1][c].ring.push(ts, float(b[0]), float(b[1]), float(b[2]), False, 0)
        for stage in (py, cp):
            stage[0].step(t)
        _same(_state(*py), _state(*cp), t)
        m = py[0]
        if m.complete:
            hold += 1
            if hold >= (12 if m.blocks % 5 == 0 else 1):
                for stage in (py, cp):
                    stage[0].release()
                hold = 0
        seen = {"handed": m.blocks, "skipped": m.blocks_skipped, "no_signal": m.blocks_no_signal,
                "distorted": m.blocks_distorted, "clean": m.blocks_distorted == 0 or tick > 900}
    assert cp[0].counters() == py[0].counters()
    assert seen["handed"] > 100 and seen["skipped"] > 5 and seen["no_signal"] >= 4, seen
    assert seen["clean"] and 5 < seen["distorted"] < seen["handed"], seen     # only the second sensor, late


def test_a_handed_over_block_is_every_channel_burst_at_its_middle():
    """The compiled stage's hand-over against closed forms: the schedule's edges (the last coil's
    window ``[t0 + k hop, + T_w]``, the others' a block longer), the measured currents, each
    channel's burst equal to its demodulator's S and var, every window done, flagged with the
    block's flags and referred to the block's middle, ``t_ref`` that middle."""
    cfg = ac_config(fusion=False)
    n = len(cfg.source.coils)
    rng = np.random.default_rng(8)
    coupling = rng.normal(0.0, 2e-6, (3, n))
    m, chans, sched = _stage(cfg, fcore.DEFAULT, (16,))
    for tick in range(60):
        t = 200_000 + tick * 1000
        b = _field(rng, t - 300, cfg, coupling, 0.0, True)
        chans[0].ring.push(t - 300, float(b[0]), float(b[1]), float(b[2]), False, 0)
        m.step(t)
        if m.complete:
            break
    assert m.complete
    d = m.demods[0]
    k = m.block_k
    start = d.t0 + k * d.hop_us
    end = start + d.window_us
    assert d.t0 == 200_000 + cfg.ac.ac_settle_us
    assert m.t_ref == (start + end) // 2
    assert list(sched.start) == [start] * n
    assert list(sched.end) == [end + d.window_us] * (n - 1) + [end]
    assert np.array_equal(sched.measured, m.act.amplitude_a)
    ch = chans[0]
    assert np.array_equal(ch.S, d.S) and np.array_equal(ch.var, d.var)
    assert ch.done.all() and list(ch.flags) == [d.block_flags] * n and list(ch.pulse_mid) == [m.t_ref] * n
    assert np.all(np.abs(ch.S - coupling) < 5.0 * np.sqrt(ch.var))    # the carriers' couplings, to the noise
