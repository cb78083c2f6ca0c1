"""The measurement stage of AC excitation: demodulated blocks handed to the trackers as bursts.

Each sensor channel's new samples go through its
:class:`coiltrack.firmware.measure.demod.Demodulator` (at most
``max_samples`` per channel and tick, at most one block solved per channel
and tick). When every channel has solved block ``k`` and the tracker is free
(:attr:`complete` False), the block becomes the channels' burst: ``ch.S``
(in-phase, sensor frame, T, column per coil), ``ch.var``, ``ch.flags``,
``ch.pulse_mid`` (the block's middle), and the schedule's per-coil edges and
measured currents (the current amplitude of ``AC_DRIVE_STATUS``), so the
trackers of pulsed DC (:class:`coiltrack.firmware.track.magnetic.MagneticTracker`
and its fusing subclass) solve it unchanged: they refer the pose to
``(start[0] + end[-1]) / 2``, the block's middle. The other coils' ``end``
is kept a block past the block's end, so the supervisor treats every sample
as taken with the coils on (no compass and no earth-field distortion check
on AC samples). A block that completes while the tracker is still busy is
counted (``ac_blocks_skipped``) and dropped; a block whose in-phase part is
not significant (``sum S^2 / var`` below the 0.9999 chi-square quantile of
``3 n`` degrees of freedom: the drive is off) is flagged ``PULSE_TOO_FEW``,
so the trackers report it without solving (``ac_blocks_no_signal``).

Each block's DC term (the earth field at its middle, sensor frame) goes into
a small :class:`coiltrack.firmware.measure.pulse.SampleRing` per channel
(``earth``): the compass of the orientation filter under AC excitation.

On the compiled core (``coiltrack.firmware.core``, chosen at construction) a tick's work after the
plan check, every channel's demodulator step, the solved blocks' bookkeeping and the hand-over
(:meth:`ACBlockMeasurement._tick`), is one call of ``ct_ac_blocks_step`` (``core/src/ac_blocks.c``),
which follows the Python here operation by operation (the same bits); the earth rings' pushes and
the channels' change counts stay with their owners. The integer state (the last block, the
hand-over flag, ``t_ref``, the counters) is the int64 array ``_st``, the sums the float64 array
``_fs``: both cores share them.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import chi2_gate
from coiltrack.firmware.estimate.fusion_rings import KernelRing
from coiltrack.firmware.measure.demod import STEP_DISTORTED, STEP_NO_SIGNAL, STEP_SOLVED, Demodulator
from coiltrack.firmware.measure.pulse import NO_TIME_US, SampleRing
from coiltrack.firmware.ring import Ring

# the integer state, an int64 array (``ACBlockMeasurement._st``; ``core/include/ct_ac.h``: CT_ACB_*)
_BLOCK_K, _COMPLETE, _T_REF, _BLOCKS, _SKIPPED, _BAD, _DISTORTED, _NO_SIGNAL, _MAX_SAMPLES = range(9)
_NST = 9
# the float state (``_fs``; CT_ACBF_*): the sums and the gates
_QUAD_SUM, _QUAD_MAX, _RESID_SUM, _SIGNAL_GATE, _RATIO_MAX, _Q_GATE = range(6)
_NFS = 6
#: channels the compiled tick takes (a bit of its result each; ``CT_ACB_MAX_CH``)
_MAX_CH = 48


class ACBlockMeasurement:
    """The measure stage of AC excitation (``step(now_us)``); ``complete`` / :meth:`release` as a burst."""

    def __init__(self, cfg, channels, schedule, actuation, max_samples: int = 0, core=_DEFAULT_CORE):
        self.cfg = cfg
        self.channels = tuple(channels)
        self.schedule = schedule
        self.act = actuation
        self.n = schedule.n
        # each channel's demodulator reads its sample ring (``Demodulator.feed``) and, for each block it
        # solves, the actuation's measured current phasors (``Demodulator.step``) on the numeric core ``core``
        currents = (actuation.amplitude_a, actuation.phase_rad)
        self.demods = tuple(Demodulator(cfg.ac.ac_freqs_hz, cfg.ac.ac_window_us, cfg.ac.ac_hop_us, cfg.pulse.mag_sigma_t,
                                        cfg.ac.mag_integration_us, ch.ring, core, currents) for ch in self.channels)
        self.earth = {ch.node: SampleRing(64) for ch in self.channels}
        self._earth = tuple(self.earth[ch.node] for ch in self.channels)
        nch = len(self.channels)
        per_tick = cfg.pulse.mag_rate_hz * cfg.timing.tick_us * 1e-6
        self.solved_k = np.full(nch, -1, dtype=np.int64)
        self._skv = memoryview(self.solved_k)
        self.closed_last = 0             # pulse windows closed in a step: AC blocks close none
        #: each channel's last solved block distorted (1) or not, and its quadrature ratio
        self._dist = np.zeros(nch, dtype=np.int64)
        self._qr = np.zeros(nch)
        self.distorted = memoryview(self._dist)
        self.quad_ratio = memoryview(self._qr)
        self._st = np.zeros(_NST, dtype=np.int64)
        self._fs = np.zeros(_NFS)
        self._stv = st = memoryview(self._st)
        self._fsv = fs = memoryview(self._fs)
        st[_BLOCK_K] = -1
        st[_MAX_SAMPLES] = max_samples or max(4, int(math.ceil(4 * per_tick)))
        #: :attr:`t_ref` and :attr:`complete` as int64 views (1,) of the state, read in place by a
        #: tracker's compiled solve start and its tick (``track.ac.ACFusionTracker._bind_ac_tick``)
        self.t_ref_view = st[_T_REF:_T_REF + 1]
        self.complete_view = st[_COMPLETE:_COMPLETE + 1]
        self.signal_gate = fs[_SIGNAL_GATE] = chi2_gate(3 * self.n, 0.9999)
        self.q_gate = fs[_Q_GATE] = chi2_gate(3 * self.n, cfg.ac.ac_distortion_probability)
        fs[_RATIO_MAX] = float(cfg.ac.ac_distortion_ratio)
        self.started = False
        self.plan_id = -1
        self.core = "python"
        if core.ext is not None and all(d.core == "compiled" for d in self.demods) and 0 < nch <= _MAX_CH:
            self._bind_compiled(core.ext)

    def _bind_compiled(self, ext) -> None:
        """:meth:`_tick` in one call of ``ct_ac_blocks_step`` (``core/src/ac_blocks.c``): the
        demodulators, the channels' rings and burst arrays, the schedule's and the actuation's
        arrays and this object's state bound once; replaced on this instance."""
        sched, act = self.schedule, self.act
        chans = tuple((d._ck, ch.ring.t, ch.ring.b, ch.ring.flags, ch.S, ch.var, ch.flags, ch.pulse_mid, ch.done)
                      for d, ch in zip(self.demods, self.channels))
        self._rings = tuple(ch.ring for ch in self.channels)
        self._rs = np.zeros(2 * len(self.channels), dtype=np.int64)       # each ring's count and last slot
        self._rsv = memoryview(self._rs)
        # each ring's head and count read in place (``KernelRing.hc``) where its ``len`` and
        # ``last_pushed_slot`` are the reference's: (its hc, its capacity), else None
        self._ring_hc = tuple((memoryview(r.hc), r.capacity) for r in self._rings) if all(
            type(r).__len__ is KernelRing.__len__ and type(r).last_pushed_slot is Ring.last_pushed_slot
            for r in self._rings) else None
        self._ck = ext.ACBlocks(self.n, chans, act.phase_rad, act.amplitude_a, sched.start, sched.end,
                                sched.measured, self.solved_k, self._dist, self._qr, self._st, self._fs, self._rs)
        self._tick = self._tick_compiled
        self.core = "compiled"

    # ------------------------------------------------------------ state (``_st``, ``_fs``)
    @property
    def complete(self) -> bool:
        """A block was handed to the channels and the tracker is not done with it."""
        return self._stv[_COMPLETE] != 0

    @property
    def t_ref(self) -> int:
        """The middle of the last block handed over (us)."""
        return self._stv[_T_REF]

    @property
    def block_k(self) -> int:
        """The last block every channel solved (handed over or skipped), -1 before one."""
        return self._stv[_BLOCK_K]

    @property
    def max_samples(self) -> int:
        return self._stv[_MAX_SAMPLES]

    blocks = property(lambda self: self._stv[_BLOCKS])
    blocks_skipped = property(lambda self: self._stv[_SKIPPED])
    blocks_bad = property(lambda self: self._stv[_BAD])
    blocks_distorted = property(lambda self: self._stv[_DISTORTED])
    blocks_no_signal = property(lambda self: self._stv[_NO_SIGNAL])
    quad_sum = property(lambda self: self._fsv[_QUAD_SUM])
    quad_max = property(lambda self: self._fsv[_QUAD_MAX])
    resid_sum = property(lambda self: self._fsv[_RESID_SUM])

    # ------------------------------------------------------------ tick
    def step(self, now_us: int) -> None:
        act = self.act
        if not act.ready:
            return
        if not self.started or self.plan_id != act.plan_id:      # the first plan, or a new one
            t0 = act.on_us + self.cfg.ac.ac_settle_us
            for d in self.demods:
                d.start(t0, act.ref_us, act.amplitude_a, act.phase_rad)
            for i in range(len(self.demods)):
                self._skv[i] = -1
            self._stv[_BLOCK_K] = -1
            self.plan_id = act.plan_id
            self.started = True
        r = self._tick()
        if r > 1:
            self._after(r)

    def _tick(self) -> int:
        """Every channel's demodulator step (:meth:`_feed`), then the hand-over (:meth:`_assemble`).
        Returns bit 0 when a block was handed over, bit ``1 + i`` when channel ``i`` solved a block
        with signal (its DC term for the earth ring: :meth:`_after`)."""
        r = 0
        for i in range(len(self.demods)):
            if self._feed(i):
                r |= 2 << i
        if self._assemble():
            r |= 1
        return r

    def _tick_compiled(self) -> int:
        """:meth:`_tick` in one call (the channels' bursts loaded by ``SensorChannel.load_block``'s
        copies in C; each channel then counts the change itself: ``block_loaded``)."""
        rs, rings, hcs = self._rsv, self._rings, self._ring_hc
        if hcs is not None:                  # (len and last_pushed_slot on the rings' hc, in place)
            for i in range(len(hcs)):
                hc, cap = hcs[i]
                h = hc[0]
                rs[2 * i] = hc[1]
                rs[2 * i + 1] = h - 1 if h > 0 else cap - 1
        else:
            for i in range(len(rings)):
                ring = rings[i]
                rs[2 * i] = len(ring)
                rs[2 * i + 1] = ring.last_pushed_slot()
        r = self._ck.step()
        if r & 1:
            for ch in self.channels:
                ch.block_loaded()
        return r

    def _after(self, r: int) -> None:
        """Each block a tick solved with signal (bit ``1 + i`` of :meth:`_tick`'s result ``r``):
        its DC term into its channel's earth ring."""
        for i in range(len(self.demods)):
            if r & (2 << i):
                d = self.demods[i]
                dc = d._dcv
                self._earth[i].push(d.block_mid(d.block_k), dc[0], dc[1], dc[2], False, 0)

    def _feed(self, i: int) -> bool:
        """Solve the block channel ``i`` completed in the previous tick, else feed its new samples
        (``Demodulator.step``: at most ``max_samples``, up to one that completes a block; the
        block's signal and distortion gates). True when it solved a block with signal."""
        d, st, fs = self.demods[i], self._stv, self._fsv
        r = d.step(st[_MAX_SAMPLES], fs[_SIGNAL_GATE], fs[_RATIO_MAX], fs[_Q_GATE])
        if not r:
            return False
        self._skv[i] = d.block_k
        if r & STEP_NO_SIGNAL:
            st[_NO_SIGNAL] += 1                      # no coil field in the block (drive off): not solved
            return False
        if r & STEP_SOLVED:
            self.quad_ratio[i] = d.quadrature_ratio()
            self.distorted[i] = dist = 1 if r & STEP_DISTORTED != 0 else 0
            if dist:
                st[_DISTORTED] += 1
            return True
        return False

    def _assemble(self) -> bool:
        """Hand block ``k`` to the tracker when every channel has solved it (True)."""
        sk, st, fs = self._skv, self._stv, self._fsv
        k = sk[0]
        if k < 0 or k == st[_BLOCK_K]:
            return False
        for i in range(1, len(sk)):
            if sk[i] != k:
                return False
        if st[_COMPLETE]:
            st[_SKIPPED] += 1
            st[_BLOCK_K] = k
            return False
        st[_BLOCK_K] = k
        d0 = self.demods[0]
        start = d0.t0 + k * d0.hop_us
        end = start + d0.window_us
        mid = (start + end) // 2
        self.schedule.ac_block(start, end, end + d0.window_us, self.act.amplitude_a)
        bad = False
        for i, ch in enumerate(self.channels):
            d = self.demods[i]
            ch.load_block(d.S, d.var, d.block_flags, mid)
            if d.block_flags:
                bad = True
            fs[_QUAD_SUM] += self.quad_ratio[i]
            if self.quad_ratio[i] > fs[_QUAD_MAX]:
                fs[_QUAD_MAX] = self.quad_ratio[i]
            fs[_RESID_SUM] += d.residual_ratio
        st[_BLOCKS] += 1
        if bad:
            st[_BAD] += 1
        st[_T_REF] = mid
        st[_COMPLETE] = 1
        return True

    def release(self) -> None:
        """The tracker is done with the block."""
        self._stv[_COMPLETE] = 0

    def completing_sample_us(self) -> int:
        """No hint: a block completes with the demodulation's own sample count, not at a sample
        the wall-clock loop could start a tick after (``Measurement.completing_sample_us``)."""
        return NO_TIME_US

    def counters(self) -> dict:
        nb = max(self.blocks * len(self.channels), 1)
        return {"ac_blocks": self.blocks, "ac_blocks_skipped": self.blocks_skipped, "ac_blocks_bad": self.blocks_bad,
                "ac_blocks_distorted": self.blocks_distorted, "ac_blocks_no_signal": self.blocks_no_signal,
                "ac_quadrature_ratio_mean": self.quad_sum / nb, "ac_quadrature_ratio_max": self.quad_max,
                "ac_residual_ratio_mean": self.resid_sum / nb}
