"""A window's readiness over many channels and a run's PULSE_WINDOWs in one call each
(firmware_py/core/src/ahead.c ``ct_ready_upto``, py_ahead.c ``ReadyUpto``, ``WindowFrames``)
against their Python references.

* ``WindowCloser.ready_upto`` on the compiled core against the reference on sixteen channels'
  rings at random newest times (at, just before and after the window's reading end), from random
  first channels, before and after the timeout, and a hand-made case with its answers worked out.
* ``Transmitter.pulse_window_run`` with ``ext.WindowFrames`` against the loop of ``pulse_window``
  on the Python core (``encode_frame``): the same frames, in order, the same sequence and error
  counts, with n_used and n_base beyond 255 (clipped), flags beyond a byte (masked), a negative
  first time or a node id beyond a byte (refused: a tx error, no number taken), a link that fails
  every third write, the sequence wrapping past 255; the frames decoded independently carry the
  fields sent.
Seeded; skipped without the extension."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.measure.windows import SensorChannel, WindowCloser
from coiltrack.firmware.transmit import Transmitter
from coiltrack.protocol import FrameDecoder

pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
COMPILED = core.load("compiled")
K = 16


class _Port:
    def __init__(self, fail_every=0):
        self.frames, self.n, self.fail_every = [], 0, fail_every

    def write(self, data):
        self.n += 1
        if self.fail_every and self.n % self.fail_every == 0:
            raise OSError("link full")
        self.frames.append(bytes(data))


class _Decoder:
    frames_bad = 0


def _closer(kernels, cfg, tx=None):
    chans = [SensorChannel(16 + k, cfg, kernels) for k in range(K)]
    return chans, WindowCloser(chans, cfg.pulse.fall_us, cfg.pulse.baseline_us, 50_000, tx)


def _reads_to(cfg, end):
    return end + cfg.pulse.fall_us + cfg.pulse.baseline_us


def test_ready_upto_equals_the_reference():
    """2000 random cases on sixteen channels: the compiled count equals the reference's. Catches the
    closer's timeout compared with >= (or without the fall), a channel skipped, ``>=`` for ``>``,
    the count from 0 instead of ``first``."""
    cfg = FirmwareConfig().validate()
    chans, closer = _closer(COMPILED, cfg)
    assert closer.ready_upto.__func__ is WindowCloser._ready_upto_compiled
    rng = np.random.default_rng(3031)
    seen = set()
    for _ in range(2000):
        end = int(rng.integers(0, 1 << 40))
        lim = _reads_to(cfg, end)
        ready_to = int(rng.integers(0, K + 1))
        for i, ch in enumerate(chans):
            ch.ring.hc[2] = lim + (int(rng.integers(1, 50)) if i < ready_to else -int(rng.integers(0, 3)))
            if rng.random() < 0.1:
                ch.ring.hc[2] = lim + int(rng.integers(-1, 2))
        now = lim + 50_000 + int(rng.integers(-2, 3)) if rng.random() < 0.3 else lim - int(rng.integers(0, 1000))
        first = int(rng.integers(0, K + 2))
        start = end - 5000
        ref = WindowCloser.ready_upto(closer, start, end, now, first)
        assert closer.ready_upto(start, end, now, first) == ref
        seen.add(ref == K)
    assert seen == {True, False}


def test_ready_upto_hand_made():
    """Window end 10000 us: channels 0-2 have a sample after end + fall + baseline, channel 3 one at
    exactly it (the window reads it: not ready): 3 from 0, 3 from 2, 16 from 4 on if 4-15 are
    ready, 16 once now passes end + fall + baseline + timeout (and not at it)."""
    cfg = FirmwareConfig().validate()
    chans, closer = _closer(COMPILED, cfg)
    end = 10_000
    lim = _reads_to(cfg, end)
    for i, ch in enumerate(chans):
        ch.ring.hc[2] = lim if i == 3 else lim + 1
    assert closer.ready_upto(end - 500, end, lim, 0) == 3
    assert closer.ready_upto(end - 500, end, lim, 2) == 3
    assert closer.ready_upto(end - 500, end, lim, 4) == K
    assert closer.ready_upto(end - 500, end, lim + 50_000, 0) == 3
    assert closer.ready_upto(end - 500, end, lim + 50_001, 0) == K
    assert closer.ready_upto(1 << 62, (1 << 62) + 10, 0, 0) == WindowCloser.ready_upto(closer, 1 << 62, (1 << 62) + 10,
                                                                                        0, 0)


def _fill(chans, flags, rng):
    for i, ch in enumerate(chans):
        ch.info[:] = (int(rng.integers(0, 300)), int(rng.integers(0, 300)), int(rng.integers(0, 1 << 40)),
                      int(rng.integers(0, 1 << 40)))
        if rng.random() < 0.05:
            ch.info[2] = -int(rng.integers(1, 100))
        flags[i] = int(rng.integers(0, 1 << 12))


@pytest.mark.parametrize("fail_every", [0, 3])
def test_pulse_window_run_sends_the_python_frames(fail_every):
    """300 runs of random channel ranges: the compiled run's frames, sequence and error count equal
    those of the loop over ``pulse_window`` on the Python core (node 300 on one channel: refused).
    Catches the clip at 255 missing, flags not masked, the sequence counted for a refused frame,
    a failed write not counted, a channel of the run skipped or sent twice."""
    cfg = FirmwareConfig().validate()
    rng = np.random.default_rng(3032)
    ref_tx = Transmitter(_Port(fail_every), 1, 1_000_000, _Decoder(), core=core.PYTHON)
    got_tx = Transmitter(_Port(fail_every), 1, 1_000_000, _Decoder(), core=COMPILED)
    chans, closer = _closer(COMPILED, cfg, got_tx)
    closer._nodes[5] = 300
    for _ in range(300):
        _fill(chans, closer._run_flags, rng)
        c0 = int(rng.integers(0, K))
        c1 = int(rng.integers(c0, K + 1))
        coil, pid = int(rng.integers(0, 3)), int(rng.integers(0, 60000))
        for i in range(c0, c1):
            iv = chans[i].info
            n_used, n_base = int(iv[0]), int(iv[1])
            ref_tx.pulse_window(int(closer._nodes[i]), coil, pid, int(iv[2]), int(iv[3]), min(n_used, 255),
                                min(n_base, 255), int(closer._run_flags[i]) & 0xFF)
        assert got_tx.pulse_window_run(closer._framesk, coil, pid, c0, c1)
        assert got_tx.port.frames == ref_tx.port.frames          # (their bytes carry the sequence)
        assert got_tx.tx_errors == ref_tx.tx_errors
    assert ref_tx.tx_errors > 20 and len(got_tx.port.frames) > 500


def test_pulse_window_frames_decode_to_the_fields_sent():
    """One run of four channels decoded by the protocol's FrameDecoder: each PULSE_WINDOW carries its
    channel's node, the coil, the pulse id, first and last, n_used and n_base clipped at 255 and the
    flags' low byte, with consecutive sequence numbers; the Python core sends nothing this way."""
    cfg = FirmwareConfig().validate()
    tx = Transmitter(_Port(), 1, 1_000_000, _Decoder(), core=COMPILED)
    chans, closer = _closer(COMPILED, cfg, tx)
    for i, ch in enumerate(chans):
        ch.info[:] = (10 * i, 300, 1000 + i, 2000 + i)
        closer._run_flags[i] = 0x1F0 + i
    assert tx.pulse_window_run(closer._framesk, 2, 777, 3, 7)
    dec = FrameDecoder()
    msgs = [m for f in tx.port.frames for m in dec.feed(f)]
    assert [m.node for m in msgs] == [19, 20, 21, 22]
    for m, i in zip(msgs, range(3, 7)):
        assert (m.coil, m.pulse_id, m.first_us, m.last_us) == (2, 777, 1000 + i, 2000 + i)
        assert (m.n_used, m.n_base, m.flags) == (min(10 * i, 255), 255, (0x1F0 + i) & 0xFF)
    py = Transmitter(_Port(), 1, 1_000_000, _Decoder(), core=core.PYTHON)
    assert not py.pulse_window_run(closer._framesk, 2, 777, 3, 7) and py.port.frames == []
