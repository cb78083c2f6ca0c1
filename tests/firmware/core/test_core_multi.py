"""The many-sensor kernels (firmware_py/core/src/multi.c, py_multi.c) against their Python
references, and the many-sensor bookkeeping of the measure stage and of solving ahead.

* ``window_frame``: the PULSE_WINDOW frame, byte for byte the one ``protocol.framing.encode_frame``
  makes (header, struct-packed payload, CRC-16 with the CRC extra, COBS, delimiter), and ``None``
  exactly where ``struct.pack`` refuses a field; through ``Transmitter.pulse_window`` the same
  bytes, sequence numbers and tx errors on both cores.
* ``sigma_from``: a channel's solver weights, bit for bit the Python loop's and numpy's
  ``sqrt(fmax(var, floor))`` (an independent reference), NaN and infinities included.
* ``WindowColumn`` (``SensorChannel.close_window``): the window's amplitude, variance, flags,
  middle, counts and used times, bit for bit the reference's, on random rings.
* ``BurstMeasurement`` asks only the channels not known ready, and ``MagneticTracker`` solving
  ahead asks only the channels whose samples or windows changed.
Seeded; the kernel tests skip without the extension."""
import struct

import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.measure.burst import BurstMeasurement
from coiltrack.firmware.measure.windows import SensorChannel, WindowCloser
from coiltrack.firmware.transmit import Transmitter, _WINDOW
from coiltrack.protocol.errors import ProtocolError
from coiltrack.protocol.framing import encode_frame

ext = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
COMPILED = core.load("compiled")


# ---------------------------------------------------------------- PULSE_WINDOW
def _fields(rng):
    """Random PULSE_WINDOW fields, now and then at or beyond the edges of their ranges, and with
    zero bytes (COBS) in every part."""
    def pick(lo, hi, edge_lo, edge_hi):
        r = rng.random()
        if r < 0.1:
            return int(rng.choice([edge_lo, edge_hi, lo, hi]))
        if r < 0.2:
            return 0
        return int(rng.integers(lo, hi, endpoint=True))
    u64 = (1 << 64) - 1
    return (pick(0, 255, -1, 256), pick(0, 255, -1, 256), pick(0, 65535, -1, 65536),
            pick(0, 1 << 62, -1, 1 << 64) if rng.random() < 0.9 else u64,
            pick(0, 1 << 62, -1, 1 << 64) if rng.random() < 0.9 else u64,
            pick(0, 255, -1, 256), pick(0, 255, -1, 256), pick(0, 255, -1, 256))


def _reference(fields, seq, src):
    try:
        return encode_frame(_WINDOW(*fields), seq, src)
    except (struct.error, ProtocolError):       # (encode_frame's EncodeError)
        return None


def test_window_frame_is_encode_frame_byte_for_byte():
    """3000 random field sets: the same bytes as encode_frame, and None exactly where struct.pack
    refuses a field (a node of 256, a negative time, a pulse id of 65536, ...). Catches a field at
    the wrong offset, a byte-order slip, a CRC without the extra byte, a COBS block miscounted and a
    range check missing or too tight."""
    rng = np.random.default_rng(31)
    refused = ok = 0
    for _ in range(3000):
        f = _fields(rng)
        seq, src = int(rng.integers(0, 256)), int(rng.integers(0, 256))
        want = _reference(f, seq, src)
        got = ext.window_frame(seq, src, *f)
        assert got == want, (f, seq, src)
        refused += want is None
        ok += want is not None
    assert refused > 300 and ok > 1500


def test_window_frame_refuses_what_struct_refuses():
    """A float, None or a too large time: None, as struct.pack raises (a tx error), not an exception."""
    good = (16, 1, 7, 1000, 2000, 5, 6, 0)
    assert ext.window_frame(0, 1, *good) == encode_frame(_WINDOW(*good), 0, 1)
    for k, bad in ((0, 1.0), (2, None), (3, -5), (4, 1 << 64), (7, 300), (5, 2.5)):
        f = list(good)
        f[k] = bad
        assert _reference(f, 0, 1) is None
        assert ext.window_frame(0, 1, *f) is None
    with pytest.raises(TypeError):
        ext.window_frame(0, 1, *good[:-1])


class _Capture:
    def __init__(self, fail=False):
        self.frames = []
        self.fail = fail

    def write(self, data):
        if self.fail:
            raise OSError("link down")
        self.frames.append(bytes(data))


class _Decoder:
    frames_bad = 0


def _transmitter(kernels, port):
    return Transmitter(port, 1, 1_000_000, _Decoder(), core=kernels)


def test_pulse_window_through_the_transmitter_on_both_cores():
    """Interleaved with other messages, windows in range and out of it: both cores write the same
    frames with the same sequence numbers and count the same tx errors (a refused window takes no
    sequence number; a failed write does)."""
    outs = []
    for kernels in (core.PYTHON, COMPILED):
        port = _Capture()
        tx = _transmitter(kernels, port)
        assert tx.core == kernels.name
        r = np.random.default_rng(33)
        for _ in range(400):
            tx.pulse_window(*_fields(r))
            if r.random() < 0.2:
                tx.event(3, 7)
        failing = _transmitter(kernels, _Capture(fail=True))
        failing.pulse_window(16, 0, 1, 10, 20, 3, 4, 0)
        outs.append((port.frames, tx.tx_errors, failing.tx_errors))
    assert outs[0] == outs[1]
    assert outs[0][1] > 20 and outs[0][2] == 1


# ---------------------------------------------------------------- solver weights
def _sigma_reference(var, floor):
    out = np.empty_like(var)
    for idx, v in np.ndenumerate(var):
        v = float(v)
        out[idx] = np.sqrt(v if v > floor else floor)
    return out


def test_sigma_from_bit_for_bit():
    """Random variances over twelve decades with zeros, negatives, NaN and infinities: the compiled
    channel's weights equal the Python channel's and numpy's sqrt(fmax(var, floor)) to the bit, in
    place too. Catches max for fmax (NaN through), a floor on sigma instead of the variance, a
    column left out."""
    cfg = FirmwareConfig().with_(link={"sensor_ids": (16,)}).validate()
    ref = SensorChannel(16, cfg, core.PYTHON)
    got = SensorChannel(16, cfg, COMPILED)
    floor = ref._sigma_floor2
    rng = np.random.default_rng(34)
    for _ in range(200):
        var = 10.0 ** rng.uniform(-22, -10, size=ref.var.shape)
        mask = rng.random(var.shape)
        var[mask < 0.1] = 0.0
        var[(mask > 0.1) & (mask < 0.15)] = -1e-14
        var[(mask > 0.15) & (mask < 0.2)] = np.nan
        var[(mask > 0.2) & (mask < 0.25)] = np.inf
        for ch in (ref, got):
            np.copyto(ch.var, var)
            ch.fill_sigma()
        np.testing.assert_array_equal(got.sigma, ref.sigma)
        np.testing.assert_array_equal(got.sigma, np.sqrt(np.fmax(var, floor)))
        np.testing.assert_array_equal(got.sigma, _sigma_reference(var, floor))
        inplace = var.copy()
        got.sigma_from(memoryview(inplace), memoryview(inplace))
        np.testing.assert_array_equal(inplace, ref.sigma)


# ---------------------------------------------------------------- window columns
def _channels(**pulse):
    cfg = FirmwareConfig().with_(link={"sensor_ids": (16,)}, **({"pulse": pulse} if pulse else {})).validate()
    ref = SensorChannel(16, cfg, core.PYTHON)
    got = SensorChannel(16, cfg, COMPILED)
    assert ref.close_window.__func__ is SensorChannel.close_window
    assert got.close_window.__func__ is SensorChannel._close_window_compiled
    return ref, got


class _Sample:
    def __init__(self, t, x, y, z, flip):
        self.t_us, self.x, self.y, self.z, self.flip = t, x, y, z, flip


def _same_channel(ref, got, case):
    for name in ("S", "var", "flags", "done", "pulse_mid", "amp", "amp_var", "info"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=f"{name} {case}")
    assert got.changes == ref.changes, case
    assert got.extractor.last_used_span() == ref.extractor.last_used_span(), case
    e0, e1 = np.zeros(3), np.zeros(3)
    assert got.extractor.last_empirical_var(e1) == ref.extractor.last_empirical_var(e0), case
    np.testing.assert_array_equal(e1, e0, err_msg=str(case))


def test_close_window_bit_for_bit_on_random_rings():
    """A sample stream at the magnetometer's rate with jitter, gaps, flips and saturated samples,
    wrapped round the ring; windows closed into random columns at random times (before, across and
    after the samples, one far beyond the compiled range): every output of the compiled
    close_window equals the reference's to the bit, the flags cover every PULSE_* bit. Catches a
    middle rounded toward zero instead of floored, a column written into the wrong row, a count or
    a used time not passed on, the extractor's last window not kept."""
    rng = np.random.default_rng(35)
    flags_seen = 0
    ref, got = _channels()
    n = ref.S.shape[1]
    t = int(rng.integers(-40_000, 40_000))
    flip = 0
    for step in range(6000):
        t += int(rng.integers(15_000, 30_000)) if rng.random() < 0.03 else int(rng.integers(8_000, 8_700))
        if rng.random() < 0.01:
            flip ^= 1
        counts = rng.integers(-3000, 3000, size=3)
        sat = 2 if rng.random() < 0.01 else 0
        for ch in (ref, got):
            ch.push(_Sample(t, int(counts[0]), int(counts[1]), int(counts[2]), sat | flip), 1e-8)
        if step % 7 == 0:
            if rng.random() < 0.1:
                for ch in (ref, got):
                    ch.new_burst()
            start = t - int(rng.integers(-50_000, 200_000))
            end = start + int(rng.integers(-1000, 90_000))
            if rng.random() < 0.005:
                start, end = 1 << 62, (1 << 62) + 1000
            coil = int(rng.integers(0, n))
            f0 = ref.close_window(coil, start, end)
            f1 = got.close_window(coil, start, end)
            assert f1 == f0, (step, start, end)
            flags_seen |= f0
            _same_channel(ref, got, (step, start, end))
    assert flags_seen == 31


def test_close_one_sends_what_it_closed():
    """Through the window closer on both cores: the same PULSE_WINDOW frames (the window's used
    sample span, counts clipped at 255) and the same flagged count."""
    outs = []
    for kernels in (core.PYTHON, COMPILED):
        cfg = FirmwareConfig().with_(link={"sensor_ids": (16, 17)}).validate()
        port = _Capture()
        tx = _transmitter(kernels, port)
        chans = [SensorChannel(16 + k, cfg, kernels) for k in range(2)]
        closer = WindowCloser(chans, cfg.pulse.fall_us, cfg.pulse.baseline_us, 100_000, tx)
        r = np.random.default_rng(37)
        t = 0
        for step in range(3000):
            t += int(r.integers(8000, 8700))
            for ch in chans:
                ch.push(_Sample(t, *map(int, r.integers(-3000, 3000, size=3)), 0), 1e-8)
            if step % 11 == 0:
                start = t - int(r.integers(0, 150_000))
                closer.close_one(chans[step % 2], int(r.integers(0, 3)), step & 0xFFFF, start, start + 60_000)
        outs.append((port.frames, closer.closed, closer.flagged))
    assert outs[0] == outs[1] and len(outs[0][0]) > 200


# ---------------------------------------------------------------- asked only what is due
class _Extractor:
    def __init__(self):
        self.is_ready = False
        self.asked = 0

    def ready(self, start, end):
        self.asked += 1
        return self.is_ready


class _Channel:
    def __init__(self):
        self.extractor = _Extractor()
        self.done = [False] * 3
        self.node = 16


class _Schedule:
    n = 3

    def __init__(self):
        self.burst_start = 0
        self.commanded = 3
        self.start = np.array([0, 100_000, 200_000])
        self.end = np.array([60_000, 160_000, 260_000])
        self.pulse_id = np.array([7, 8, 9])
        self.ended = 0

    def end_burst(self):
        self.ended += 1


class _Closing(WindowCloser):
    def close_one(self, ch, coil, pulse_id, start, end):
        ch.done[coil] = True
        self.closed += 1
        return 0


def test_measure_asks_only_the_channels_not_known_ready():
    """Sixteen channels becoming ready one a tick: each channel is asked about a window once it
    is ready and not again (the count grows with the channels, not with channels x ticks), the
    windows close in channel order four a tick, and after release the next burst asks afresh.
    Catches a count that is not kept, kept across bursts, or trusted after a timeout it did not see."""
    chans = [_Channel() for _ in range(16)]
    closer = _Closing(chans, 1000, 5000, 1 << 40, None)
    sched = _Schedule()
    m = BurstMeasurement(chans, sched, closer, budget=4)
    for k in range(16):
        chans[k].extractor.is_ready = True
        m.step(1_000_000 + k)
        assert m.ready_upto[0] == k + 1
    asked = sum(c.extractor.asked for c in chans)
    # per tick and coil the channel that became ready and the next one: 2 x 16 x 3 (asking every
    # channel from the first each tick: 3 x (2 + 3 + ... + 17) = 504)
    assert asked <= 2 * 16 * 3
    for k in range(20):
        m.step(2_000_000 + k)
    assert m.complete and closer.closed == 48
    # coils 1 and 2 are asked once more about the last channel (the tick that found coil 0 ready
    # spent its budget closing it before asking them), then never again
    assert sum(c.extractor.asked for c in chans) == asked + 2
    assert all(c.done == [True] * 3 for c in chans)
    m.release()
    assert sched.ended == 1 and m.ready_upto == [0, 0, 0] and m.closed_upto == [0, 0, 0]


def test_ready_upto_and_ready_agree():
    """ready() is ready_upto(..., 0) == every channel; a timed-out window is ready on every channel."""
    chans = [_Channel() for _ in range(4)]
    closer = WindowCloser(chans, 1000, 5000, 100_000, None)
    chans[0].extractor.is_ready = chans[1].extractor.is_ready = True
    assert closer.ready_upto(0, 60_000, 0, 0) == 2 and not closer.ready(0, 60_000, 0)
    assert closer.ready_upto(0, 60_000, 60_000 + 106_001, 0) == 4 and closer.ready(0, 60_000, 166_001)
    for c in chans:
        c.extractor.is_ready = True
    assert closer.ready_upto(0, 60_000, 0, 2) == 4 and closer.ready(0, 60_000, 0)


def test_solving_ahead_asks_only_channels_that_changed():
    """multi16, 3 s on the virtual clock: the prediction that a channel's last window is in
    (expect_complete) is asked at most once per change of the channel (a sample in or a window
    closed) and burst, not once per channel and tick; the bursts are solved ahead as before. The
    asks counted are the Python scan's (``MagneticTracker._ahead_scan``, the compiled binding taken
    off this tracker): the compiled scan makes the same (test_core_ahead.py)."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.firmware.measure.pulse import PulseExtractor
    from coiltrack.tools import scenarios
    from coiltrack.tools.bench.links import inproc_pair
    from coiltrack.tools.bench.runner import BenchSetup

    sc = scenarios.get("multi16")
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, 1, 4.0, emu_end)
    cfg = sc.firmware_config().validate()
    fw = Firmware(cfg, fw_end)
    asked = [0]
    real = PulseExtractor.expect_complete

    def counted(self, start, end):
        asked[0] += 1
        return real(self, start, end)

    for ch in fw.channels:
        ch.extractor.expect_complete = counted.__get__(ch.extractor)
    vars(fw.tracker).pop("_ahead_scan", None)
    ticks = 0
    t = 0
    while t < 3_000_000:
        bench.emulator.step(t)
        fw.tick(t)
        t += cfg.timing.tick_us
        ticks += 1
    changes = sum(ch.changes for ch in fw.channels)
    assert fw.tracker.ahead_solves >= 16
    assert 0 < asked[0] <= changes
    assert asked[0] < ticks               # before: each channel asked in every tick of the last pulse
