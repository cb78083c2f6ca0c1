"""A pulse's windows closed on a run of sensor channels in one call (``WindowCloser.close_run`` on
the compiled core: ``ext.WindowRun``, ``core/src/multi.c`` ``ct_window_run``) against its reference,
the loop over ``WindowCloser.close_one``, and against the Python core.

Sixteen channels with their own sample streams (jitter, gaps, flips, saturated samples, wrapped
round the ring), windows closed on random runs of them at random times: every channel's burst
columns, last window, info and counters, the extractor's last used samples, the closer's counts
and the PULSE_WINDOW frames (bytes and order) are the same, to the bit. And ``BurstMeasurement``
with a windows budget closes the same windows in the same ticks through it. Seeded; skipped
without the extension."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.measure.windows import SensorChannel, WindowCloser
from coiltrack.firmware.transmit import Transmitter

ext = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
COMPILED = core.load("compiled")
K = 16


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


def _set(kernels, cfg):
    port = _Capture()
    tx = Transmitter(port, 1, 1_000_000, _Decoder(), core=kernels)
    chans = [SensorChannel(16 + k, cfg, kernels) for k in range(K)]
    return port, chans, WindowCloser(chans, cfg.pulse.fall_us, cfg.pulse.baseline_us, 100_000, tx)


def _same(a, b, case):
    for ca, cb in zip(a, b):
        for name in ("S", "var", "flags", "done", "pulse_mid", "amp", "amp_var", "info", "cnt"):
            np.testing.assert_array_equal(getattr(ca, name), getattr(cb, name), err_msg=f"{name} {case}")
        assert ca.extractor.last_used_span() == cb.extractor.last_used_span(), case
        ua, ub = np.zeros(64, dtype=np.int64), np.zeros(64, dtype=np.int64)
        assert ca.extractor.last_used_times(ua) == cb.extractor.last_used_times(ub), case
        np.testing.assert_array_equal(ua, ub)


def test_close_run_equals_close_one_and_the_python_core():
    """3000 sample steps of 16 channels; every 5th step a random run of channels closes a window
    (before, across and after the samples; now and then one far beyond the compiled range, which
    the reference takes): the compiled run, the loop over close_one on the compiled channels and
    the Python core leave the same state and send the same frames. Catches a channel of the run
    skipped or closed twice, a ring's head or count read from another channel, the changes not
    counted, a frame sent with another window's flags, the extractor's used samples not kept."""
    cfg = FirmwareConfig().with_(link={"sensor_ids": tuple(range(16, 16 + K))}).validate()
    port_r, chs_r, run = _set(COMPILED, cfg)
    port_l, chs_l, loop = _set(COMPILED, cfg)
    port_p, chs_p, py = _set(core.PYTHON, cfg)
    assert run.close_run.__func__ is WindowCloser._close_run_compiled
    assert py.close_run.__func__ is WindowCloser.close_run
    rng = np.random.default_rng(30)
    n = chs_r[0].S.shape[1]
    t = [int(rng.integers(-40_000, 40_000)) for _ in range(K)]
    flip = [0] * K
    flags_seen = 0
    for step in range(3000):
        for k in range(K):
            t[k] += int(rng.integers(15_000, 30_000)) if rng.random() < 0.03 else int(rng.integers(8_000, 8_700))
            if rng.random() < 0.01:
                flip[k] ^= 1
            counts = rng.integers(-3000, 3000, size=3)
            sat = 2 if rng.random() < 0.01 else 0
            for chs in (chs_r, chs_l, chs_p):
                chs[k].push(_Sample(t[k], int(counts[0]), int(counts[1]), int(counts[2]), sat | flip[k]), 1e-8)
        if step % 5:
            continue
        start = min(t) - int(rng.integers(-50_000, 200_000))
        end = start + int(rng.integers(-1000, 90_000))
        if rng.random() < 0.01:
            start, end = 1 << 62, (1 << 62) + 1000
        c0 = int(rng.integers(0, K))
        c1 = int(rng.integers(c0, K + 1))
        coil, pid = int(rng.integers(0, n)), step & 0xFFFF
        run.close_run(coil, pid, start, end, c0, c1)
        WindowCloser.close_run(loop, coil, pid, start, end, c0, c1)
        py.close_run(coil, pid, start, end, c0, c1)
        for ch in chs_r[c0:c1]:
            flags_seen |= int(ch.flags[coil])
        _same(chs_r, chs_l, (step, c0, c1))
        _same(chs_r, chs_p, (step, c0, c1))
        assert (run.closed, run.flagged) == (loop.closed, loop.flagged) == (py.closed, py.flagged)
    assert port_r.frames == port_l.frames == port_p.frames
    assert len(port_r.frames) > 2000 and flags_seen == 31


def test_window_run_refuses_what_it_cannot_close():
    """The kernel's checks: channels outside the bound ones, a coil outside the burst."""
    cfg = FirmwareConfig().with_(link={"sensor_ids": (16, 17)}).validate()
    _, chs, closer = _set(COMPILED, cfg)
    k = closer._runk
    with pytest.raises(ValueError, match="channels"):
        k.close(0, 0, 1000, 1, K + 1)
    with pytest.raises(ValueError, match="channels"):
        k.close(0, 0, 1000, 2, 1)
    with pytest.raises(ValueError, match="coil"):
        k.close(chs[0].S.shape[1], 0, 1000, 0, 2)
    with pytest.raises(ValueError, match="coil"):
        k.close(-1, 0, 1000, 0, 1)
    with pytest.raises(TypeError):
        ext.WindowRun((object(),), (chs[0].ring.hc,), (chs[0].cnt,), np.zeros(1, dtype=np.int64))
