"""The single-coil tracker (``actuation = "adaptive"``, or the fixed cycle with
``single_coil_fusion``): one error-state EKF per sensor, and the pulses that feed it.

Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``) sec. 2.1 and
Fig. 1, as stages of the firmware tick, each piece one job in its own module:

* actuate (:meth:`SingleCoilTracker.actuate`): the policy chosen once by
  ``schedule`` (``actuate.single_coil_policy``: :class:`AdaptiveActuation`,
  when, which coil, how strong and, with ``pulse_length = "chosen"``, how long;
  :class:`FixedActuation`, the X, Y, Z cycle), commanding through the pulses'
  book (``actuate.single_coil_pulses.PulseBook``: slots, clones, duty, quiet
  gaps), and the set/reset flips between pulses;
* measure (:meth:`SingleCoilTracker.measure`): each closed window
  (``coiltrack.firmware.measure.pulse``) updates every sensor's EKF through the
  clone taken at its measurement time (``estimate.single_coil.SchepersEKF.update_pulse``
  with a ``CoilMeasurement``), with the commanded current (the driver regulates
  it; its 1 mA readback replaces it only when the driver reports a sag) and the
  current tolerance and the field-model error in the measurement covariance;
* track (:meth:`SingleCoilTracker.track`): between pulses every ``IMU_SAMPLE``
  propagates the sensor's filter and a ``POSE`` goes out at the IMU rate;
* consistency: the NIS of every update is gated (chi-square) and monitored
  over a window (``coil_choice.NisMonitor``; on the compiled core its twin
  ``track.single_coil_nis.CompiledNisMonitor``); a ferromagnetic object that
  makes the updates inconsistent (Schepers sec. 3.3) is reported
  (``EVT_DISTORTION``, ``POSE_DISTORTED``) and, until the window is consistent
  again, the measurement covariance is inflated by the observed excess and the
  gate steps aside;
* acquisition (``track.single_coil_acquire.BurstAcquisition``): a sensor
  without a pose gets a burst of every coil, solved and refined pulse by pulse,
  which starts its filter (:meth:`SingleCoilTracker.tracking_started`).

Per-sensor state is a ``track.single_coil_sensor.SensorTrack``; the policy and
the acquisition act on it only through this class's methods (``reacquire``,
``forget``, ``tracking_started``). All arrays are allocated at start-up; the
per-tick paths, the acquisition included, write into them and create no numpy
array (``tests/adaptive/test_bench_adaptive.py`` counts).
"""
from __future__ import annotations

import numpy as np

from coiltrack.protocol.schema import (COIL_FAULT_CURRENT_SAG, CURRENT_LSB_A, EVT_DISTORTION,
                                       POSE_DEGRADED, POSE_DISTORTED, POSE_FUSED, POSE_INCONSISTENT, POSE_SATURATED,
                                       POSE_STALE, POSE_VALID)

from coiltrack.firmware.transmit import PoseReport
from coiltrack.firmware.actuate.accuracy import FixedCycleReference
from coiltrack.firmware.actuate.accuracy_budget import MeanBudgetReference
from coiltrack.firmware.actuate.accuracy_actual import actual_reference
from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
from coiltrack.firmware.actuate.single_coil_policy import AdaptiveActuation, FixedActuation
from coiltrack.firmware.actuate.pulse_length import PulseLengths, fixed_amplitude_variance
from coiltrack.firmware.actuate.single_coil_pulses import PulseBook
from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NONFINITE, EKF_NOT_PD, chi2_gate
from coiltrack.firmware.measure.pulse import PULSE_TOO_FEW, PULSE_UNUSABLE as _UNUSABLE
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.shared_baseline import next_start, pulse_gap_us, shared_baselines
from coiltrack.firmware.estimate.single_coil import CORE, POS, filter_class
from coiltrack.firmware.track.quality import PoseQuality, quality_from
from coiltrack.firmware.track.single_coil_acquire import BurstAcquisition
from coiltrack.firmware.track.single_coil_nis import nis_monitor
from coiltrack.firmware.track.single_coil_sensor import SensorTrack
from coiltrack.firmware.track.single_coil_window import update_core, window_after, window_prior, window_update
from coiltrack.firmware.track.status import COIL_FATAL as _FATAL, input_status
#: EVT_DISTORTION detail: bit 8 marks the NIS monitor as the detector, bit 31 the all-clear
_EVT_NIS = 1 << 8
_EVT_CLEAR = 1 << 31

#: the actuation policy of each ``schedule`` (chosen once, at composition)
ACTUATIONS = {"adaptive": AdaptiveActuation, "fixed": FixedActuation}


def measurement_mid_us(cfg, pulse_us: int) -> int:
    """Mid time of a pulse's used samples, from its start edge."""
    return (cfg.pulse.settle_us + pulse_us - cfg.pulse.guard_us) // 2


def pulse_lengths(cfg, pulse_us: int) -> PulseLengths:
    """``[adaptive] pulse_length``: ``"fixed"`` (``pulse_us`` at any phase) or
    ``"chosen"`` (``pulse_length.PulseLengths.chosen``, up to ``pulse_us`` plus two sample
    periods, for a pulse that must bring more than ``pulse_us`` can at the largest current)."""
    if cfg.adaptive.pulse_length == "chosen":
        return PulseLengths.chosen(cfg, pulse_us + int(2e6 / cfg.pulse.mag_rate_hz))
    return PulseLengths.fixed(cfg, pulse_us)


class SingleCoilTracker:
    """One single-coil EKF per sensor, and the pulses that feed it.

    Stages (composed by ``coiltrack.firmware.loop.Firmware``): :meth:`actuate` (the policy
    chosen by ``schedule``: ``actuate.single_coil_policy``), :meth:`measure` (close the
    windows, each an EKF update), :meth:`track` (propagate through the queued IMU samples);
    inputs :meth:`on_imu`, :meth:`on_coil_status`; :meth:`counters` for the status.
    """

    def __init__(self, cfg, coils, channels, pulses, closer, supervisor, tx, schedule: str = "adaptive",
                 distortion=None, core=_DEFAULT_CORE):
        """``distortion``: the room's map (``model.distortion``) for the acquisition's pose solver;
        ``core``: the numeric core (``coiltrack.firmware.core.Core``), chosen at composition."""
        self.core = core
        if schedule not in ACTUATIONS:
            raise ValueError("schedule must be 'adaptive' or 'fixed'")
        self.cfg = cfg
        self.closer = closer
        self.supervisor = supervisor
        self.tx = tx
        self._report = PoseReport()           # the POSE being sent (filled in place)
        self._vals_a = np.zeros(14)           # its values (SchepersEKF.pose_values)
        self._vals = memoryview(self._vals_a)
        self.now_us = 0
        self.boot_us: int | None = None
        self.updated_us = -1            # the tick of the last EKF update (the decision then waits)
        n = len(coils)
        self.n = n
        self.model = SingleCoilModel(coils, cfg.source.field_model, core)       # updates
        self.rmodel = SingleCoilModel(coils, cfg.source.field_model, core)      # the fixed-cycle reference
        self.pulse_us = cfg.adaptive.adaptive_pulse_us or cfg.timing.pulse_us
        self.sensors: dict[int, SensorTrack] = {}
        for k, tr in enumerate(channels):
            self.sensors[tr.node] = self._sensor(k, tr, schedule)
        self._sens = tuple(self.sensors.values())
        mid = measurement_mid_us(cfg, self.pulse_us)
        self.book = PulseBook(cfg, n, pulses, [s.ekf for s in self._sens], mid,
                              pulse_gap_us(cfg), cfg.timing.first_cycle_us - cfg.adaptive.adaptive_lead_us, core)
        # amplitudes sharing baseline samples with a neighbour's (estimate.shared_baseline)
        # (on the compiled core its twin, core/src/sc_window.c, bound to the channels' last windows)
        self.sharing = shared_baselines(core, cfg.pulse.fall_us, cfg.pulse.baseline_us, cfg.pulse.guard_us,
                                        cfg.pulse.mag_sigma_t, 1e6 / cfg.pulse.mag_rate_hz,
                                        cfg.adaptive.baseline_sharing != "ignore", cfg.adaptive.baseline_sharing == "apart")
        if hasattr(self.sharing, "bind_channels"):
            self.sharing.bind_channels(s.track for s in self._sens)
        self._lead_us = cfg.adaptive.adaptive_lead_us if schedule == "adaptive" else -1
        self.acquisition = BurstAcquisition(cfg, coils, self._sens, self.book, self.model, supervisor, tx, self,
                                            distortion, core)
        self.actuation = ACTUATIONS[schedule](cfg, coils, self._sens, self.book, self.acquisition, supervisor, tx,
                                              self, pulse_lengths(cfg, self.pulse_us), core)
        # POSE.quality (track.quality): a single pulse leaves no residual freedom, so the
        # consistency is the update's NIS per dimension and the quiet field's, kept per sensor
        # and applied to the filter's position covariance at each fused pose
        self.quality = PoseQuality(cfg, 0, channels)
        self.q_scale = float(cfg.quality.quality_error_scale_m)
        self.q_x = {sid: 0.0 for sid in self.sensors}
        self._s6 = [0.0] * 6                 # one popped IMU sample (f, w)
        self._consts(cfg)
        # counters
        self.updates = 0
        self.gated = 0
        self.unusable = 0
        self.distortion_events = 0
        self.reacquired = 0

    def _consts(self, cfg) -> None:
        """The configuration's numbers the per-window and per-sample paths use, read once (the
        same values and the same operations on them as read where used)."""
        a = cfg.adaptive
        self._pre_us = cfg.pulse.baseline_us + cfg.pulse.guard_us       # a window's span: start - these
        self._post_us = cfg.pulse.fall_us + cfg.pulse.baseline_us       # ... to end + these
        self._driver = cfg.link.coil_driver_id
        self._lin2 = a.nis_linear_fraction * a.nis_linear_fraction
        self._rel2 = a.field_model_rel_sigma * a.field_model_rel_sigma
        self._tol_a = cfg.limits.current_tolerance_a
        self._big = a.acquire_sigma_m * a.acquire_sigma_m
        self._reacq = a.reacquire_after
        self._imu_timeout = cfg.imu.imu_timeout_us
        self._pose_every = a.pose_every
        # each filter's covariance, flat (its diagonal read as floats: the same values as P[i, i])
        self._Pf = {s.index: memoryview(s.ekf.P.reshape(-1)) for s in self._sens}
        self._nP = self._sens[0].ekf.P.shape[1] if self._sens else 0
        # its position and its clones' (read as floats: the same products as on numpy's scalars)
        self._pv = {s.index: (memoryview(s.ekf.p), memoryview(s.ekf.clone_p)) for s in self._sens}
        self._forget_us = a.nis_forget_us
        # the update's prior and after-steps, one compiled call each (track.single_coil_window;
        # None: the reference's steps)
        self._uc = {s.index: update_core(self.core.ext, s, self.quality, self._lin2, self._rel2, self._tol_a)
                    for s in self._sens}
        # ... and the whole window update, one compiled call (single_coil_window.window_update; None: the
        # steps above around SchepersEKF.update_pulse)
        self._wu = {s.index: window_update(self.core.ext, s, self._uc[s.index], self.sharing, self.model)
                    for s in self._sens}
        self._n_model = self.model.n

    def _sensor(self, k: int, tr, schedule: str) -> SensorTrack:
        """One sensor's filter, monitor and (``accuracy_target = "fixed"``) the fixed cycle's
        predicted accuracy beside it."""
        cfg = self.cfg
        mon = nis_monitor(self.core, window=cfg.adaptive.nis_window, dof=3, gate=chi2_gate(3, cfg.adaptive.nis_gate_probability),
                         z=cfg.adaptive.nis_alarm_z, min_count=min(cfg.adaptive.nis_window, 3), min_excess=cfg.adaptive.nis_alarm_excess,
                         max_scale=cfg.adaptive.nis_max_scale, feedback_updates=cfg.adaptive.nis_feedback_updates)
        s = SensorTrack(k, tr, cfg, filter_class(cfg).from_config(cfg, core=self.core), mon)
        if cfg.adaptive.accuracy_target == "fixed" and schedule == "adaptive":
            # the fixed cycle of [timing], its pulses' amplitude variance and mid time
            # "mean": the same reference, holding the filter's running mean (actuate.accuracy_budget)
            kind = MeanBudgetReference if cfg.adaptive.reference_hold == "mean" else FixedCycleReference
            if cfg.adaptive.reference_error == "actual":       # its actual error (actuate.accuracy_actual)
                kind = actual_reference(cfg.adaptive.reference_hold)
            s.ref = kind(
                np.array([c.current for c in cfg.source.coils]), cfg.timing.first_cycle_us, cfg.timing.cycle_us, cfg.timing.spacing_us,
                measurement_mid_us(cfg, cfg.timing.pulse_us), fixed_amplitude_variance(cfg, cfg.timing.pulse_us),
                cfg.adaptive.field_model_rel_sigma, cfg.limits.current_tolerance_a, cfg.adaptive.reference_avg_s * 1e6,
                cfg.adaptive.sigma_range_exp_pos, cfg.adaptive.sigma_range_exp_ori, cfg.adaptive.reference_warmup_us, self.core)
        return s

    # ------------------------------------------------------------ inputs
    def on_mag(self, msg, lsb: float) -> None:
        """Samples of nodes that are not tracked sensors are not used."""
        return

    def on_imu(self, msg, now_us: int) -> None:
        """Queue an IMU sample; the track stage propagates it."""
        s = self.sensors.get(msg.node)
        if s is not None:
            s.imu.push(msg)

    def on_coil_status(self, msg) -> None:
        self.book.on_status(msg, CURRENT_LSB_A)       # (the firmware reports the fault event)

    # ------------------------------------------------------------ stages
    def _clock(self, now_us: int) -> None:
        if self.boot_us is None:
            self.boot_us = now_us
        self.now_us = now_us

    def actuate(self, now_us: int) -> None:
        """Decide the next pulse (or the fixed cycle's), and the flips."""
        self._clock(now_us)
        self.actuation.step(now_us)

    def measure(self, now_us: int) -> None:
        """Close the windows whose samples are in: each an EKF update."""
        self._clock(now_us)
        self._close(now_us)

    def track(self, now_us: int) -> None:
        """Propagate each sensor's EKF through its queued IMU samples."""
        s6 = self._s6
        for s in self._sens:
            while True:
                t = s.imu.pop_sample(s6)
                if t < 0:
                    break
                a, g = s.acc, s.gyr
                a[0], a[1], a[2], g[0], g[1], g[2] = s6
                self._propagate(s, t, now_us)

    def _propagate(self, s: SensorTrack, t: int, now_us: int) -> None:
        ekf = s.ekf
        if s.last_imu_us is not None:
            gap = t - s.last_imu_us
            if gap <= 0:
                return
            if gap > self._imu_timeout:
                # a hole in the stream: the state cannot be carried across it
                ekf.restart_inputs()
                if ekf.initialized:
                    self._lose(s)
        s.last_imu_us = t
        ekf.propagate(t, s.acc, s.gyr)
        if s.ref is not None and ekf.initialized:
            s.ref.step(ekf, t, self.rmodel)
        s.imu_samples += 1
        if self.acquisition.active:
            self.acquisition.note_orientation(s, t)
        if ekf.initialized and s.imu_samples % self._pose_every == 0:
            self._emit_fused(s, t, now_us)

    # ------------------------------------------------------------ windows
    def _close(self, now_us: int) -> None:
        book = self.book
        m = book.in_flight_order()         # oldest first, so the updates are applied in time order
        for k in range(m):
            sl = book.ordered(k)
            if not self.closer.ready(sl.start, sl.end, now_us):
                continue
            self._close_one(sl, now_us)
            if not sl.acq:
                book.release(sl)
        if self.acquisition.active and not book.burst_open():
            self.acquisition.finish(now_us)

    def _close_one(self, sl, now_us: int) -> None:
        # the driver regulates the commanded current; its measurement (1 mA steps, noisy)
        # replaces it only when the driver reports that it could not (supply sag)
        current = sl.current
        sag = bool(sl.faults & COIL_FAULT_CURRENT_SAG) and sl.measured != 0.0
        if sag:
            current = sl.measured
        fatal = bool(sl.faults & _FATAL) or (sl.status and sl.measured == 0.0)
        either = self.supervisor.health.suspect_either
        start, end, driver = sl.start, sl.end, self._driver
        t0 = start - self._pre_us
        t1 = end + self._post_us
        lead = self._lead_us      # adaptive: a pulse not yet commanded may start this soon
        self.sharing.close(start, end, next_start(self.book.slots, sl),
                           max(self.book.next_free_us, now_us + lead) if lead >= 0 else -1)
        close = self.closer.close_one
        for s in self._sens:
            tr = s.track
            flags = close(tr, sl.coil, sl.pid, start, end)
            suspect = either(tr.node, driver, t0, t1)         # its clock or the driver's (Health.suspect)
            if sl.acq:
                self.acquisition.record(s, sl.coil, tr.amp, tr.amp_var,
                                        flags | (PULSE_TOO_FEW if (fatal or suspect) else 0), current)
                continue
            bits = input_status(flags, sl.faults | (COIL_FAULT_CURRENT_SAG if sag else 0))
            if (flags & _UNUSABLE) or fatal or suspect or not s.ekf.initialized:
                self.unusable += 1
                s.bits = bits | (s.bits & POSE_DISTORTED)
                continue
            self._update(s, sl, current, bits, now_us)
        if sl.acq:
            self.book.close_acq(sl)
        else:
            for s in self._sens:
                if sl.clone >= 0:
                    s.ekf.release_clone(sl.clone)

    def _update(self, s: SensorTrack, sl, current: float, bits: int, now_us: int) -> None:
        self.updated_us = now_us
        wu = self._wu[s.index]
        if wu is not None:
            # the steps of _update_steps in one compiled call (single_coil_window.window_update)
            flags = wu[0].run(sl.clone, sl.coil, current)
            if flags >= 0:
                out = wu[1]
                self.model.signal.add_evals(self._n_model * int(out[2]))
                if flags & (EKF_NOT_PD | EKF_NONFINITE):
                    self.unusable += 1
                    return
                self.q_x[s.node] = out[0]
                self._updated(s, flags, out[1] != 0.0, bits, now_us)
                return
        self._update_steps(s, sl, current, bits, now_us)

    def _update_steps(self, s: SensorTrack, sl, current: float, bits: int, now_us: int) -> None:
        """:meth:`_update`'s reference: the prior, the measurement, the filter's update, the
        after-steps (each one call on the compiled core), then :meth:`_updated`."""
        ekf = s.ekf
        # one NIS monitor per sensor: inflating the pulses of single coils instead proved
        # unstable (once the state is biased, the consistent-looking coil is the disturbed one)
        mon = s.monitor
        tr = s.track
        # the NIS tests the model only where the linearisation holds (the prior position std
        # small against the range); the relative errors of the predicted field: the model, and
        # the current (single_coil_window.window_prior; compiled: one call)
        uc = self._uc[s.index]
        k = sl.clone
        if uc is None:
            p, cp = self._pv[s.index]
            linear, rel = window_prior(self._Pf[s.index], self._nP, p, cp, k, self._lin2, self._rel2, self._tol_a,
                                       current)
        else:
            rel = uc[0].prior(k, current)
        # once the monitor has judged the pulses inconsistent, the inflated covariance is the
        # protection: gating them as well would reject them all and leave the state to the IMU
        m = s.meas.set(tr.amp, self.sharing.channel_variance(s.index, tr.amp_var, tr.infov), sl.coil, current, rel, mon.r_scale,
                       not mon.inconsistent)
        flags = ekf.update_pulse(k, m, self.model)
        if flags & (EKF_NOT_PD | EKF_NONFINITE):
            self.unusable += 1
            return
        # the consistency term, and the monitor's record where linear (window_after)
        if uc is None:
            self.q_x[s.node] = window_after(self.quality, s.node, mon, ekf.nis_nominal, ekf.nis, linear)
        else:
            self.q_x[s.node] = uc[0].after(ekf.nis_nominal, ekf.nis)
            linear = uc[1][0] != 0.0
        self._updated(s, flags, linear, bits, now_us)

    def _updated(self, s: SensorTrack, flags: int, linear: bool, bits: int, now_us: int) -> None:
        """After an update of ``s`` (``flags``; ``linear``: its NIS tested the linear model): the
        fixed-cycle reference's note, the gated counts and :meth:`_verdict`."""
        ekf = s.ekf
        mon = s.monitor
        if linear:
            s.mon_t = now_us
            if s.ref is not None:
                s.ref.note_pulse(ekf.nis_nominal, s.track.amp, self.sharing.var)
        if flags & EKF_GATED:
            s.gated += 1
            self.gated += 1
            mon.note_gated()
            if not (mon.inconsistent or s.distorted):
                # rejections a flagged disturbance explains are no sign of a lost track:
                # an acquisition now would only start from a distorted solution
                s.gated_in_row += 1
            bits |= POSE_INCONSISTENT
        else:
            s.gated_in_row = 0
            s.updates += 1
            self.updates += 1
            s.last_update_us = now_us
        self._verdict(s, bits, now_us)

    def _verdict(self, s: SensorTrack, bits: int, now_us: int) -> None:
        """The update's status bits, the distortion events, and a lost track: updates rejected
        again and again, or an uncertainty beyond any use."""
        mon = s.monitor
        was = s.distorted
        hdist = self.supervisor.health.is_distorted(s.node)
        self.forget(s, now_us)
        dist = mon.inconsistent
        if dist:
            bits |= POSE_DISTORTED | POSE_INCONSISTENT
        elif hdist:
            bits |= POSE_DISTORTED
        s.bits = bits
        if dist != was:
            self.distortion_events += 1 if dist else 0
            self.tx.event(EVT_DISTORTION, (s.node | _EVT_NIS) | (0 if dist else _EVT_CLEAR))
        s.distorted = dist
        P = self._Pf[s.index]
        d = self._nP + 1
        b = POS.start * d
        big = self._big
        if s.gated_in_row >= self._reacq or P[b] > big or P[b + d] > big or P[b + 2 * d] > big:
            self.reacquire(s)

    # ------------------------------------------------------------ the track's life
    def forget(self, s: SensorTrack, now_us: int) -> None:
        """Forget a verdict that no update has tested for a while."""
        if s.monitor.count and now_us - s.mon_t > self._forget_us:
            s.monitor.reset()

    def reacquire(self, s: SensorTrack) -> None:
        """The track of ``s`` is lost: drop its filter and acquire again."""
        self.reacquired += 1
        self._lose(s)

    def _lose(self, s: SensorTrack) -> None:
        if s.ref is not None:
            s.ref.stop()
        s.ekf.reset()
        s.monitor.reset()
        s.gated_in_row = 0
        self.acquisition.request(self.now_us)

    def tracking_started(self, s: SensorTrack, status: int, now_us: int) -> None:
        """The acquisition has started the filter of ``s``."""
        if s.ref is not None:
            s.ref.start(s.ekf.P[CORE, CORE], s.ekf.t_us)
            s.ref_start_us = now_us
        s.monitor.reset()
        s.last_update_us = now_us
        s.bits = status & (POSE_DEGRADED | POSE_SATURATED)

    # ------------------------------------------------------------ output
    def _emit_fused(self, s: SensorTrack, t_us: int, now_us: int) -> None:
        ekf = s.ekf
        status = POSE_VALID | POSE_FUSED | s.bits
        if s.distorted:
            status |= POSE_DISTORTED
        if now_us - s.last_update_us > self.cfg.link.stale_us:
            status |= POSE_STALE
        v = self._vals
        ekf.pose_values(self._vals_a)         # position, quaternion, variances, position trace
        r = self._report
        r.node, r.t_us, r.status = s.node, t_us, status
        r.quality = quality_from(v[13], self.q_x[s.node], self.q_scale)
        rp, rq, rv = r.p, r.q, r.var
        rp[0], rp[1], rp[2] = v[0], v[1], v[2]
        rq[0], rq[1], rq[2], rq[3] = v[3], v[4], v[5], v[6]
        rv[0], rv[1], rv[2], rv[3], rv[4], rv[5] = v[7], v[8], v[9], v[10], v[11], v[12]
        self.tx.pose(r)

    def counters(self) -> dict:
        mons = [s.monitor for s in self._sens]
        return {
            "adaptive_pulses": self.book.pulses,
            "adaptive_acquisitions": self.acquisition.acquisitions,
            "adaptive_updates": self.updates,
            "adaptive_gated": self.gated,
            "adaptive_unusable": self.unusable,
            "adaptive_reacquired": self.reacquired,
            "adaptive_distortion_events": self.distortion_events,
            "adaptive_distorted_updates": sum(m.flagged for m in mons),
            "adaptive_no_current": self.actuation.no_current,
            "adaptive_energy_j": round(self.book.schedule.energy_j, 4),
        }
