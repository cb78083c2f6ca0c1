"""A burst's opening for many sensors (firmware_py/core/src/burst_open.c, py_burst_open.c) against
its Python reference.

* ``ChannelBursts.new_burst`` (``ext.NewBursts``, ``ct_new_burst`` per channel): every channel's
  ``done`` and ``flags`` cleared and its ``changes`` counted, its amplitudes, samples and other
  columns untouched, bit for bit the loop over ``SensorChannel.new_burst``.
* ``BurstFusionTracker.on_burst`` (``ext.Schedules``, ``ct_schedule`` per sensor): each sensor's
  ``t_ref`` and its fusion snapshot's time, pending and valid flags exactly as the loop over
  ``SensorInertial.schedule`` leaves them, from random earlier states.
* ``BurstActuation`` on the compiled core makes both calls (the kernels bound at start-up) and
  opens the same bursts, with the same commands, as on the Python core.
Seeded; skipped without the extension."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.actuate.burst import BurstActuation
from coiltrack.firmware.loop import Firmware
from coiltrack.firmware.measure.windows import ChannelBursts, SensorChannel
from coiltrack.tools import scenarios

ext = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
COMPILED = core.load("compiled")


class _NullPort:
    def read(self) -> bytes:
        return b""

    def write(self, data: bytes) -> None:
        pass


def _channels(cfg, k, rng):
    """``k`` channels with random burst state (done, flags, amplitudes, counters)."""
    out = []
    for i in range(k):
        ch = SensorChannel(16 + i, cfg, core=COMPILED)
        ch.done[:] = rng.random(ch.done.shape[0]) < 0.5
        ch.flags[:] = rng.integers(0, 1 << 20, ch.flags.shape[0])
        ch.S[:] = rng.normal(size=ch.S.shape)
        ch.pulse_mid[:] = rng.integers(0, 1 << 40, ch.pulse_mid.shape[0])
        ch.cnt[:] = rng.integers(0, 1 << 40, 2)
        out.append(ch)
    return out


def _state(ch):
    return [a.copy() for a in (ch.done, ch.flags, ch.S, ch.var, ch.pulse_mid, ch.cnt)]


def test_new_bursts_equal_the_python_loop():
    """20 rounds of 16 channels in random states: the one call leaves every array as the loop over
    ``SensorChannel.new_burst`` does; independently, ``done`` and ``flags`` are all zero and only
    ``changes`` moved (by one). Catches a channel skipped, a coil column left, the samples counter
    counted instead of the changes, a write into a neighbouring array."""
    cfg = scenarios.get("multi16").firmware_config()
    rng = np.random.default_rng(30)
    for _ in range(20):
        seed = int(rng.integers(1 << 31))
        a = _channels(cfg, 16, np.random.default_rng(seed))
        b = _channels(cfg, 16, np.random.default_rng(seed))
        before = [_state(ch) for ch in a]
        ka = ChannelBursts(a, COMPILED)
        assert ka.kernel is not None
        ka.new_burst()
        for ch in b:
            SensorChannel.new_burst(ch)
        for ca, cb, st in zip(a, b, before):
            for x, y in zip(_state(ca), _state(cb)):
                assert np.array_equal(x, y)
            assert not ca.done.any() and not ca.flags.any()
            assert ca.changes == st[5][1] + 1 and ca.samples == st[5][0]
            assert np.array_equal(ca.S, st[2]) and np.array_equal(ca.pulse_mid, st[4])


def test_new_bursts_python_core_keeps_the_loop():
    cfg = scenarios.get("multi16").firmware_config()
    chs = _channels(cfg, 3, np.random.default_rng(1))
    cb = ChannelBursts(chs, core.PYTHON)
    assert cb.kernel is None
    cb.new_burst()
    assert all(not ch.done.any() and not ch.flags.any() for ch in chs)


def _firmware(impl):
    cfg = scenarios.get("multi16").firmware_config().with_(core={"impl": impl})
    return Firmware(cfg, _NullPort())


def _sched_state(tracker):
    return [(ins.t_ref, ins.fusion.snap.t, ins.fusion.snap.pending, ins.fusion.snap.valid, ins.fusion.snap.sq.copy())
            for ins in tracker.inertial.values()]


def test_schedules_equal_the_python_loop():
    """The compiled ``on_burst`` of multi16's sixteen sensors against the Python core's loop, from
    random earlier states (a snapshot valid or pending, another time): the same ``t_ref``, snapshot
    time, pending and valid on every sensor. Catches the valid flag left set (a stale snapshot
    would be taken for the new burst's), the pending flag not raised, a sensor skipped."""
    fc, fp = _firmware("compiled"), _firmware("python")
    tc, tp = fc.tracker, fp.tracker
    assert "on_burst" in vars(tc) and "on_burst" not in vars(tp)     # bound on the compiled core only
    rng = np.random.default_rng(6)
    for _ in range(50):
        seed = int(rng.integers(1 << 31))
        for t in (tc, tp):
            r = np.random.default_rng(seed)
            for ins in t.inertial.values():
                snap = ins.fusion.snap
                snap.t = int(r.integers(0, 1 << 40))
                snap.pending = bool(r.random() < 0.5)
                snap.valid = bool(r.random() < 0.5)
                ins.t_ref = int(r.integers(0, 1 << 40))
        t_ref = int(rng.integers(0, 1 << 40))
        tc.on_burst(t_ref)
        tp.on_burst(t_ref)
        sc, sp = _sched_state(tc), _sched_state(tp)
        for a, b in zip(sc, sp):
            assert a[:4] == b[:4]
            assert np.array_equal(a[4], b[4])
            assert a[0] == t_ref and a[1] == t_ref and a[2] is True and a[3] is False


def test_burst_actuation_opens_the_same_bursts():
    """Both cores' actuation over three cycles: the same pulse commands (ids, starts, ends), the
    channels' counters and flags, the sensors' ``t_ref`` after every tick; the compiled one holds
    the bound kernels."""
    fc, fp = _firmware("compiled"), _firmware("python")
    ac = fc.pipeline.actuate.__self__
    ap = fp.pipeline.actuate.__self__
    assert isinstance(ac, BurstActuation) and ac._bursts.kernel is not None and ap._bursts.kernel is None
    opened = 0
    for now in range(0, 1_900_001, 1000):
        for fw in (fc, fp):
            fw.pipeline.actuate(now)
            if fw.schedule.burst_start is not None and now % 7000 == 0:
                fw.schedule.end_burst()              # (what the measure stage does once the windows close)
        sc, sp = fc.schedule, fp.schedule
        assert sc.burst_start == sp.burst_start and sc.pulses == sp.pulses
        assert np.array_equal(sc.start, sp.start) and np.array_equal(sc.pulse_id, sp.pulse_id)
        for a, b in zip(fc.channels, fp.channels):
            assert np.array_equal(a.cnt, b.cnt) and np.array_equal(a.done, b.done)
        assert [i.t_ref for i in fc.tracker.inertial.values()] == [i.t_ref for i in fp.tracker.inertial.values()]
        opened = fc.channels[0].changes
    assert opened >= 3
