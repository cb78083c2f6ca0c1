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
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import chi2_gate
from coiltrack.firmware.measure.demod import STEP_DISTORTED, STEP_NO_SIGNAL, STEP_SOLVED, Demodulator
from coiltrack.firmware.measure.pulse import SampleRing


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
        per_tick = cfg.pulse.mag_rate_hz * cfg.timing.tick_us * 1e-6
        self.max_samples = max_samples or max(4, int(math.ceil(4 * per_tick)))
        self.solved_k = np.full(len(self.channels), -1, dtype=np.int64)
        self._skv = memoryview(self.solved_k)
        self.complete = False
        self.closed_last = 0             # pulse windows closed in a step: AC blocks close none
        self.t_ref = 0
        self.block_k = -1
        self.distorted = [False] * len(self.channels)
        self.quad_ratio = [0.0] * len(self.channels)
        # counters
        self.blocks = 0
        self.blocks_skipped = 0
        self.blocks_bad = 0
        self.blocks_distorted = 0
        self.blocks_no_signal = 0
        self.signal_gate = chi2_gate(3 * self.n, 0.9999)
        self.q_gate = chi2_gate(3 * self.n, cfg.ac.ac_distortion_probability)
        self._ratio_max = float(cfg.ac.ac_distortion_ratio)
        self.quad_sum = 0.0
        self.quad_max = 0.0
        self.resid_sum = 0.0
        self.started = False
        self.plan_id = -1

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
            self.block_k = -1
            self.plan_id = act.plan_id
            self.started = True
        for i in range(len(self.demods)):
            self._feed(i)
        self._assemble()

    def _feed(self, i: int) -> None:
        """Solve the block channel ``i`` completed in the previous tick, else feed its new samples
        (``Demodulator.step``: at most ``max_samples``, up to one that completes a block; the
        block's signal and distortion gates)."""
        d = self.demods[i]
        r = d.step(self.max_samples, self.signal_gate, self._ratio_max, self.q_gate)
        if not r:
            return
        k = d.block_k
        self._skv[i] = k
        if r & STEP_NO_SIGNAL:
            self.blocks_no_signal += 1               # no coil field in the block (drive off): not solved
        elif r & STEP_SOLVED:
            self.quad_ratio[i] = d.quadrature_ratio()
            self.distorted[i] = dist = r & STEP_DISTORTED != 0
            if dist:
                self.blocks_distorted += 1
            dc = d._dcv
            self._earth[i].push(d.block_mid(k), dc[0], dc[1], dc[2], False, 0)

    def _assemble(self) -> None:
        """Hand block ``k`` to the tracker when every channel has solved it."""
        sk = self._skv
        k = sk[0]
        if k < 0 or k == self.block_k:
            return
        for i in range(1, len(sk)):
            if sk[i] != k:
                return
        if self.complete:
            self.blocks_skipped += 1
            self.block_k = k
            return
        self.block_k = k
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
            self.quad_sum += self.quad_ratio[i]
            if self.quad_ratio[i] > self.quad_max:
                self.quad_max = self.quad_ratio[i]
            self.resid_sum += d.residual_ratio
        self.blocks += 1
        if bad:
            self.blocks_bad += 1
        self.t_ref = mid
        self.complete = True

    def release(self) -> None:
        """The tracker is done with the block."""
        self.complete = False

    def counters(self) -> dict:
        nb = max(self.blocks * len(self.channels), 1)
        return {"ac_blocks": self.blocks, "ac_blocks_skipped": self.blocks_skipped, "ac_blocks_bad": self.blocks_bad,
                "ac_blocks_distorted": self.blocks_distorted, "ac_blocks_no_signal": self.blocks_no_signal,
                "ac_quadrature_ratio_mean": self.quad_sum / nb, "ac_quadrature_ratio_max": self.quad_max,
                "ac_residual_ratio_mean": self.resid_sum / nb}
