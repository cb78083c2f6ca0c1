"""The measurement stage of pulsed DC: sensor channels and the one window closer.

A :class:`SensorChannel` is one magnetometer node: its sample ring, its pulse
extractor (:mod:`coiltrack.firmware.measure.pulse`) and the amplitude matrix of
the current burst (``S[:, j]``: coil ``j``'s amplitude in the sensor frame,
``var`` its variances, ``flags`` the window flags, ``pulse_mid`` the mean time
of the samples used).

:class:`WindowCloser` closes one commanded pulse's window for every channel
(:meth:`WindowCloser.close`): it extracts the amplitude, reports the window
(``PULSE_WINDOW``) and counts flagged windows. Every excitation policy closes
its windows through it. A channel's extractor is a
:class:`coiltrack.firmware.measure.WindowExtractor` (the plain baseline or the
gyroscope-turned one).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.measure.gyro_baseline import GyroBaselineExtractor, GyroRing
from coiltrack.firmware.measure.pulse import _T_FAR, PulseExtractor, SampleRing


def window_samples(cfg) -> int:
    """The most samples one window can hold (extractor scratch size)."""
    return max(64, int(2 * (cfg.timing.pulse_us + 2 * cfg.pulse.baseline_us) * 1e-6 * cfg.pulse.mag_rate_hz) + 8)


def gyro_samples(cfg) -> int:
    """Gyroscope samples a node keeps for its windows: two windows' spans and
    the closer's timeout (half a cycle) at the IMU rate."""
    span_us = cfg.timing.pulse_us + cfg.pulse.fall_us + 2 * cfg.pulse.baseline_us + cfg.timing.cycle_us // 2
    return max(16, int(2 * span_us * 1e-6 * cfg.imu.imu_rate_hz) + 8)


class SensorChannel:
    """One magnetometer node: ring, extractor and the burst's amplitudes.

    With ``body.baseline_gyro`` the node's gyroscope rates are kept
    (``gyro``, fed by :meth:`push_imu`) and the extractor turns each window's
    samples with them (:mod:`coiltrack.firmware.measure.gyro_baseline`);
    otherwise ``gyro`` is None and the IMU samples are not kept here. ``core``: the numeric core
    (``coiltrack.firmware.core``, chosen at composition) the plain extractor runs."""

    def __init__(self, node: int, cfg, core=_DEFAULT_CORE):
        n = len(cfg.source.coils)
        self.node = node
        self.ring = SampleRing(cfg.pulse.ring_capacity)
        kw = dict(settle_us=cfg.pulse.settle_us, fall_us=cfg.pulse.fall_us, baseline_us=cfg.pulse.baseline_us,
                  guard_us=cfg.pulse.guard_us, min_pulse_samples=cfg.pulse.min_pulse_samples,
                  min_baseline_samples=cfg.pulse.min_baseline_samples, drift_limit_t=cfg.pulse.drift_limit_t,
                  sigma_t=cfg.pulse.mag_sigma_t, max_samples=window_samples(cfg))
        if cfg.body.baseline_gyro:
            self.gyro = GyroRing(gyro_samples(cfg))
            self.extractor = GyroBaselineExtractor(self.ring, self.gyro, window_samples(cfg),
                                                   gyro_gap_us=int(3e6 / cfg.imu.imu_rate_hz), **kw)
        else:
            self.gyro = None
            self.extractor = PulseExtractor(self.ring, core=core, **kw)
        self.S = np.zeros((3, n))          # amplitudes, sensor frame, column per coil (T)
        self.var = np.zeros((3, n))        # their variances (T^2)
        self.sigma = np.zeros((3, n))      # their standard deviations, floored, for the solver (T)
        self.flags = np.zeros(n, dtype=np.int64)
        self.done = np.zeros(n, dtype=bool)
        self.pulse_mid = np.zeros(n, dtype=np.int64)   # mean time of each window's used samples
        self.amp = np.zeros(3)             # the last closed window
        self.amp_var = np.zeros(3)
        self.used_times = np.zeros(self.extractor.max_samples, dtype=np.int64)
        self.info = np.zeros(4, dtype=np.int64)    # the last closed window: n_used, n_base, first, last (us)
        self.infov = memoryview(self.info)
        self.cnt = np.zeros(2, dtype=np.int64)     # samples, changes (the properties below)
        self._cntv = memoryview(self.cnt)
        self._Sv = memoryview(self.S)
        self._varv = memoryview(self.var)
        self._ampv = memoryview(self.amp)
        self._avv = memoryview(self.amp_var)
        self._donev = memoryview(self.done)
        self._sigv = memoryview(self.sigma)
        self._flv = memoryview(self.flags)
        self.pmv = memoryview(self.pulse_mid)
        self._sigma_floor2 = (0.1 * cfg.pulse.mag_sigma_t) ** 2
        if core.ext is not None:         # the solver weights on the compiled core (core/src/multi.c)
            self._sigma_k = core.ext.sigma_from
            self.sigma_from = self._sigma_from_compiled
        if self.extractor.bind_column(self.S, self.var, self.flags, self.done, self.pulse_mid, self.amp,
                                      self.amp_var, self.info):
            self.close_window = self._close_window_compiled
        if core.ext is not None:         # the sample's way into the ring (core/src/multi.c)
            self._push_k = self.ring.push_kernel(core.ext, self.cnt).push
            self.push = self._push_compiled

    def _set_samples(self, v: int) -> None:
        self._cntv[0] = v

    def _set_changes(self, v: int) -> None:
        self._cntv[1] = v

    #: samples pushed (refused ones included)
    samples = property(lambda self: self._cntv[0], _set_samples)
    #: changes of what this channel's windows are read from (samples pushed, windows taken, burst
    #: started or loaded): a caller that computed something from them may keep it while this holds
    changes = property(lambda self: self._cntv[1], _set_changes)

    def push(self, msg, lsb: float) -> None:
        """A ``MAG_SAMPLE`` (counts of ``lsb`` tesla). On the compiled core one call of
        ``ct_sample_push`` (:meth:`_push_compiled`, bound at construction)."""
        self.ring.push(msg.t_us, msg.x * lsb, msg.y * lsb, msg.z * lsb, bool(msg.flip & 2), msg.flip & 1)
        c = self._cntv
        c[0] += 1
        c[1] += 1

    def _push_compiled(self, msg, lsb: float) -> None:
        """:meth:`push` in one call (``SampleRing.push_kernel``: the same checks, the same products
        ``count * lsb``, the same ring and counters); an argument of another kind than an int (a
        float field) goes to the reference."""
        if self._push_k(msg.t_us, msg.x, msg.y, msg.z, msg.flip, lsb) < 0:
            SensorChannel.push(self, msg, lsb)

    def push_imu(self, msg) -> None:
        """An ``IMU_SAMPLE`` of this node: its rates for the extractor (kept only with a gyro ring)."""
        if self.gyro is not None:
            self.gyro.push(msg)

    def take_window(self, coil: int, flags: int, mid_us: int) -> None:
        """The window just extracted into ``amp``, ``amp_var`` as coil ``coil``'s column of the
        burst, with its flags and the mean time ``mid_us`` of its samples; the window done."""
        S, var, a, v = self._Sv, self._varv, self._ampv, self._avv
        S[0, coil], S[1, coil], S[2, coil] = a[0], a[1], a[2]
        var[0, coil], var[1, coil], var[2, coil] = v[0], v[1], v[2]
        self._flv[coil] = flags
        self._donev[coil] = True
        self.pmv[coil] = mid_us
        self.changes += 1

    def close_window(self, coil: int, start: int, end: int) -> int:
        """Extract the window ``[start, end]`` into ``amp``, ``amp_var`` and, as coil ``coil``'s,
        into the burst (:meth:`take_window`, its middle the mean of the first and the last used
        sample times, or of ``start`` and ``end`` with none); ``info`` = n_used, n_base, first,
        last. Returns the window flags. On the compiled core one call of ``ct_window_column``
        (:meth:`_close_window_compiled`, bound at construction)."""
        ex = self.extractor
        flags, n_used, n_base = ex.extract(start, end, self.amp, self.amp_var)
        first, last = ex.last_used_span() if n_used else (0, 0)
        self.take_window(coil, flags, (first + last) // 2 if last else (start + end) // 2)
        iv = self.infov
        iv[0], iv[1], iv[2], iv[3] = n_used, n_base, first, last
        return flags

    def _close_window_compiled(self, coil: int, start: int, end: int) -> int:
        """:meth:`close_window` in one call (``PulseExtractor.extract_column``); a time the compiled
        extraction does not take goes to the reference."""
        flags = self.extractor.extract_column(coil, start, end)
        if flags is None:
            return SensorChannel.close_window(self, coil, start, end)
        self.changes += 1
        return flags

    def new_burst(self) -> None:
        self.done.fill(False)
        self.flags.fill(0)
        self.changes += 1

    def load_block(self, S, var, flags: int, mid_us: int) -> None:
        """A demodulated AC block as this channel's burst (``measure.ac_blocks``): amplitudes
        ``S`` and variances ``var`` (3, n), every window flagged ``flags``, done, its middle at
        ``mid_us``."""
        np.copyto(self.S, S)
        np.copyto(self.var, var)
        self.flags.fill(flags)
        self.done.fill(True)
        self.pulse_mid.fill(mid_us)
        self.changes += 1

    def block_loaded(self) -> None:
        """:meth:`load_block`'s copies were made by the compiled AC measure stage
        (``measure.ac_blocks``, ``core/src/ac_blocks.c``): counted as a change."""
        self.changes += 1

    def burst_flags(self) -> int:
        f = 0
        fl = self._flv
        for j in range(len(fl)):
            f |= fl[j]
        return f

    def fill_sigma(self) -> None:
        """``sigma = sqrt(max(var, floor))``: the solver's weights (a window
        that found no noise is not trusted beyond a tenth of the sensor's)."""
        self.sigma_from(self._varv, self._sigv)

    def _sigma_from_compiled(self, var, sig) -> None:
        """:meth:`sigma_from` in one call of ``ct_sigma_from`` (the same square roots of the same
        values: equal to the bit)."""
        self._sigma_k(var, sig, self._sigma_floor2)

    def sigma_from(self, var, sig) -> None:
        """``sig = sqrt(max(var, floor))`` for variances ``var`` (3, n) of this channel's
        windows (2-D memoryviews; ``sig`` may be ``var`` itself). On the compiled core one call
        of ``ct_sigma_from`` (:meth:`_sigma_from_compiled`, bound at construction)."""
        floor = self._sigma_floor2
        n = self.S.shape[1]
        for i in range(3):
            for j in range(n):
                v = var[i, j]
                sig[i, j] = math.sqrt(v if v > floor else floor)


class ChannelBursts:
    """Every sensor channel's :meth:`SensorChannel.new_burst` as one step: the burst the actuation
    opens serves them all (thesis ``002_cd7f1fdb7fc67471.txt`` sec 5.3). On the compiled core one
    call (``core/src/burst_open.c`` ``ct_new_burst`` for each channel, ``ext.NewBursts`` bound here
    to the channels' ``done``, ``flags`` and counters once): the burst's opening touches no Python
    object of the sixteen channels of ``multi16``."""

    def __init__(self, channels, core=_DEFAULT_CORE):
        self.channels = tuple(channels)
        self._k = None
        ok = all(type(ch).new_burst is SensorChannel.new_burst and ch.done.dtype == np.bool_ for ch in self.channels)
        if core.ext is not None and self.channels and ok:
            n = self.channels[0].done.shape[0]
            self._k = core.ext.NewBursts(n, tuple(ch.done for ch in self.channels),
                                         tuple(ch.flags for ch in self.channels), tuple(ch.cnt for ch in self.channels))
            self.new_burst = self._k.run

    kernel = property(lambda self: self._k)    # ext.NewBursts, or None: the Python loop

    def new_burst(self) -> None:
        """Each channel's :meth:`SensorChannel.new_burst`, in the channels' order."""
        for ch in self.channels:
            ch.new_burst()


class WindowCloser:
    """Closes a pulse's window on every channel and reports it."""

    def __init__(self, channels, fall_us: int, baseline_us: int, timeout_us: int, tx):
        self.channels = tuple(channels)
        self.fall_us = fall_us
        self.baseline_us = baseline_us
        self.timeout_us = timeout_us       # a window is closed this long after its end, complete or not
        self.tx = tx
        self.flagged = 0
        self.closed = 0                    # windows closed (extracted)
        self._bind_run()
        self._bind_ready()

    def _bind_run(self) -> None:
        """Where every channel closes its windows on the compiled core (``SensorChannel``'s
        ``_close_window_compiled``, bound to its extractor's ``ext.WindowColumn``), :meth:`close_run`
        closes a run of channels' windows in one call (``ext.WindowRun``, ``core/src/multi.c``
        ``ct_window_run``: the same kernel per window, in the same order), bound here once."""
        chs = self.channels
        if not chs or not all(type(ch) is SensorChannel and getattr(ch.close_window, "__func__", None)
                              is SensorChannel._close_window_compiled for ch in chs):
            return
        ext = chs[0].extractor._ext
        self._run_flags = np.zeros(len(chs), dtype=np.int64)
        self._rfv = memoryview(self._run_flags)
        self._runk = ext.WindowRun(tuple(ch.extractor.column_kernel for ch in chs), tuple(ch.ring.hc for ch in chs),
                                   tuple(ch.cnt for ch in chs), self._run_flags)
        self._nodes = np.array([ch.node for ch in chs], dtype=np.int64)
        self._framesk = ext.WindowFrames(tuple(ch.info for ch in chs), self._nodes, self._run_flags).send
        self.close_run = self._close_run_compiled
        self._chi = {id(ch): i for i, ch in enumerate(chs)}      # a channel's place in the run
        self.close_one = self._close_one_compiled

    def _bind_ready(self) -> None:
        """:meth:`ready_upto` on the compiled core (``ext.ReadyUpto``, ``core/src/ahead.c``
        ``ct_ready_upto``: the same comparisons in the same order), bound here once to the channels'
        ring states, where every channel's extractor is a plain ``PulseExtractor`` on the compiled core
        over a ``SampleRing``; replaced on this instance."""
        chs = self.channels
        ext = getattr(chs[0].extractor, "_ext", None) if chs else None
        if ext is None or not all(type(ch.extractor).ready is PulseExtractor.ready and isinstance(ch.extractor._ring, SampleRing)
                                  for ch in chs):
            return
        self._ready_extra = np.array([ch.extractor._fall_us + ch.extractor._baseline_us for ch in chs], dtype=np.int64)
        self._uptok = ext.ReadyUpto(tuple(ch.extractor._ring.hc for ch in chs), self._ready_extra,
                                     self.fall_us, self.baseline_us, self.timeout_us).upto
        self.ready_upto = self._ready_upto_compiled
        self.ready = self._ready_compiled

    def _ready_upto_compiled(self, start: int, end: int, now_us: int, first: int) -> int:
        """:meth:`ready_upto` in one call; a time the kernel does not take goes to the reference."""
        r = self._uptok(start, end, now_us, first)
        return WindowCloser.ready_upto(self, start, end, now_us, first) if r < 0 else r

    def ready(self, start: int, end: int, now_us: int) -> bool:
        """Every channel has the samples after the window, or it timed out."""
        return self.ready_upto(start, end, now_us, 0) == len(self.channels)

    def _ready_compiled(self, start: int, end: int, now_us: int) -> bool:
        """:meth:`ready` in one call (``ext.ReadyUpto`` from the first channel, bound in
        :meth:`_bind_ready`); a time the kernel does not take goes to the reference."""
        r = self._uptok(start, end, now_us, 0)
        return WindowCloser.ready(self, start, end, now_us) if r < 0 else r == len(self.channels)

    def ready_upto(self, start: int, end: int, now_us: int, first: int) -> int:
        """How many channels, in order, have every sample the window reads (all of them once it
        timed out), asking from channel ``first`` on: a caller that keeps the count asks only
        the channels not ready yet, since a window once ready stays ready (a ring takes only
        later samples and is never emptied: ``SampleRing.push``)."""
        chs = self.channels
        n = len(chs)
        if now_us > end + self.fall_us + self.baseline_us + self.timeout_us:
            return n
        i = first
        while i < n:
            if not chs[i].extractor.ready(start, end):
                return i
            i += 1
        return n

    def close_one(self, ch: SensorChannel, coil: int, pulse_id: int, start: int, end: int) -> int:
        """Extract coil ``coil``'s amplitude on channel ``ch`` into ``ch.amp``,
        ``ch.amp_var`` and column ``coil`` of the burst; send its PULSE_WINDOW;
        return the window flags."""
        flags = ch.close_window(coil, start, end)
        self.closed += 1
        if flags:
            self.flagged += 1
        iv = ch.infov
        n_used, n_base = iv[0], iv[1]
        self.tx.pulse_window(ch.node, coil, pulse_id, iv[2], iv[3], n_used if n_used < 255 else 255,
                             n_base if n_base < 255 else 255, flags & 0xFF)
        return flags

    def _close_one_compiled(self, ch: SensorChannel, coil: int, pulse_id: int, start: int, end: int) -> int:
        """:meth:`close_one` with the window extracted in one call (``ct_window_run`` on the channel
        alone: ``ct_window_column`` at its ring's state, counted in the channel's ``cnt`` as
        :meth:`SensorChannel.close_window` counts it), then its PULSE_WINDOW. A channel not of this
        closer or a time the compiled extraction does not take goes to the reference."""
        i = self._chi.get(id(ch), -1)
        if i < 0 or type(start) is not int or type(end) is not int or not (-_T_FAR < start < _T_FAR
                                                                            and -_T_FAR < end < _T_FAR):
            return WindowCloser.close_one(self, ch, coil, pulse_id, start, end)
        self.flagged += self._runk.close(coil, start, end, i, i + 1)
        self.closed += 1
        flags = self._rfv[i]
        iv = ch.infov
        n_used, n_base = iv[0], iv[1]
        self.tx.pulse_window(ch.node, coil, pulse_id, iv[2], iv[3], n_used if n_used < 255 else 255,
                             n_base if n_base < 255 else 255, flags & 0xFF)
        return flags

    def close_run(self, coil: int, pulse_id: int, start: int, end: int, c0: int, c1: int) -> None:
        """:meth:`close_one` on channels ``c0 .. c1 - 1``, in their order (``measure.burst``: a
        pulse's windows within the tick's budget). On the compiled core the windows are closed in
        one call (:meth:`_bind_run`) and their PULSE_WINDOWs sent after it, in the same order."""
        chs = self.channels
        for i in range(c0, c1):
            self.close_one(chs[i], coil, pulse_id, start, end)

    def _close_run_compiled(self, coil: int, pulse_id: int, start: int, end: int, c0: int, c1: int) -> None:
        """:meth:`close_run` in one call of ``ct_window_run``: every window extracted into its channel's
        column and counted there as :meth:`SensorChannel.close_window` does, then each one's
        PULSE_WINDOW as :meth:`close_one` sends it (on a transmitter that takes them, in one call of
        ``ext.WindowFrames``: ``Transmitter.pulse_window_run``). A time the compiled extraction does not take
        (not an int64 well inside its range) goes to the reference."""
        if type(start) is not int or type(end) is not int or not (-_T_FAR < start < _T_FAR and -_T_FAR < end < _T_FAR):
            WindowCloser.close_run(self, coil, pulse_id, start, end, c0, c1)
            return
        self.flagged += self._runk.close(coil, start, end, c0, c1)
        self.closed += c1 - c0
        chs, fl, pw = self.channels, self._rfv, self.tx.pulse_window
        for i in range(c0, c1):
            chs[i].extractor.column_closed()
        if self.tx.pulse_window_run(self._framesk, coil, pulse_id, c0, c1):
            return                       # the frames built and written in one call (ext.WindowFrames)
        for i in range(c0, c1):
            ch = chs[i]
            iv = ch.infov
            n_used, n_base = iv[0], iv[1]
            pw(ch.node, coil, pulse_id, iv[2], iv[3], n_used if n_used < 255 else 255, n_base if n_base < 255 else 255,
               fl[i] & 0xFF)
