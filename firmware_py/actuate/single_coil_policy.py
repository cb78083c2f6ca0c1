"""The actuation policies of the single-coil mode: the fixed cycle, and Schepers' adaptive one.

Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``) sec. 2.1 and Fig. 1,
as the actuate stage of the single-coil tracker (``track.single_coil_tracker``),
chosen once at composition (``actuation = "adaptive"``: :class:`AdaptiveActuation`;
the fixed cycle with ``single_coil_fusion``: :class:`FixedActuation`):

* when: once per tick, when a pulse could start (``adaptive_lead_us`` ahead,
  after the quiet gap the previous window needs), the pose covariance is
  predicted for the instant that pulse would be measured, including the
  effect of a pulse still in flight (eq 4 does not need its value); if a
  position or orientation standard deviation would reach its ``sigma_max``
  (or no update was made for ``adaptive_max_interval_us``) a pulse is due
  (``coil_choice.ActuationPolicy``); a tick that has run an EKF update leaves
  the decision to the next tick, for the same start (bounded tick);
* which and how strong: the coil whose eq-4 update reduces the normalised
  uncertainty most, at the smallest candidate current that brings the
  triggering variable to its ``sigma_min``, within the driver limit, the
  magnetometer range and the coils' duty (``coil_choice.CoilChooser``,
  ``coil_choice.saturation_current_limit`` with the latest quiet field);
* the accuracy held: the stated bounds, or the fixed cycle's own predicted
  accuracy (``accuracy.fixed_cycle_bounds``; with ``reference_hold = "mean"`` the
  filter's own running mean held at the cycle's, a deficit carried:
  ``accuracy_budget``), tightened by the NIS excess;
* set/reset flips: about every 2 s no new pulse is decided until the
  windows in flight are closed, then the sensors are told to flip in the gap.

Both policies command through the ``single_coil_pulses.PulseBook`` and start
the acquisition burst (``track.single_coil_acquire``) when a sensor has no
pose. They read the tracker's sensors (``track.single_coil_sensor``) and act on
them only through the tracker's methods (``reacquire``, ``forget``). All arrays
are allocated here, at start-up.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.estimate.shared_baseline import pulse_gap_us
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.actuate.accuracy import FixedCycleReference, fixed_cycle_bounds, nis_bound_factor
from coiltrack.firmware.actuate.accuracy_budget import HOLD_MAX, HOLD_MIN, MeanBudgetReference
from coiltrack.firmware.actuate.coil_choice import (POSE_DIM, ActuationPolicy, PoseCovUpdate, SingleCoilModel,
                                                    coil_chooser, current_ladder, saturation_current_limit)
from coiltrack.firmware.actuate.fixed_cycle import FixedCycle
from coiltrack.firmware.actuate.saturation_knee import cap_at_knee
from coiltrack.firmware.estimate.layout import ORI, POS
from coiltrack.firmware.estimate.single_coil import SchepersEKF
from coiltrack.protocol.schema import CURRENT_LSB_A

__all__ = ["FixedActuation", "AdaptiveActuation", "SensorOutlook", "CompiledActuationPolicy", "actuation_policy"]


class CompiledActuationPolicy(ActuationPolicy):
    """``coil_choice.ActuationPolicy`` on the compiled core: :meth:`set_bounds`, :meth:`due` and
    :meth:`worst` are one call each (``sc_policy.c`` ``ct_scp_policy_set_bounds``, ``_due``,
    ``_worst``: the kernel's methods themselves, no Python layer), bound once to ``var_max`` and to
    the outputs ``_st`` (the reason, the worst ratio; ``worst`` also returns it); the same
    operations in the same order as the reference's: bit for bit (the decision of when to pulse
    sees the same numbers on both cores). ``reason`` is read from ``_st``."""

    def __init__(self, sigma_max, max_interval_us: int, trace: bool, ext):
        self._st = np.zeros(2)
        self._stv = memoryview(self._st)
        super().__init__(sigma_max, max_interval_us, trace)
        self._ck = ext.WhenCore(self.var_max, self._st, self.trace, self.max_interval_us)
        self.set_bounds = self._ck.set_bounds
        self.due = self._ck.due
        self.worst = self._ck.worst

    @property
    def reason(self) -> int:
        return int(self._stv[0])

    @reason.setter
    def reason(self, value: int) -> None:
        self._stv[0] = value


def actuation_policy(core, sigma_max, max_interval_us: int, trace: bool) -> ActuationPolicy:
    """The policy of when to pulse on ``core`` (``coiltrack.firmware.core``): the reference, or its
    compiled twin :class:`CompiledActuationPolicy`."""
    if core.ext is not None:
        return CompiledActuationPolicy(sigma_max, max_interval_us, trace, core.ext)
    return ActuationPolicy(sigma_max, max_interval_us, trace)


class SensorOutlook:
    """What a decision predicts for one sensor (owned by the policy)."""

    def __init__(self, sensor):
        self.sensor = sensor
        self.P6 = np.zeros((POSE_DIM, POSE_DIM))
        self.pp = np.zeros(3)
        self.Rd = np.eye(3)                        # the orientation a decision was made at
        self.quiet = np.zeros(3)
        self.have_quiet = False
        self.smax6 = np.zeros(POSE_DIM)            # the bounds of the latest decision (m, rad)
        self.smin6 = np.zeros(POSE_DIM)
        self.bounds_core = None                    # the compiled bounds bound to these arrays
        self.view_core = None                      # ... and the one-call prediction (AdaptiveActuation._bind_views)


class _SingleCoilActuation:
    """What both policies share: acquisition and loss, the fixed cycle, the flips.

    ``host``: the tracker (``reacquire(sensor)``, ``forget(sensor, now_us)``,
    ``updated_us``: the tick of its last EKF update); ``book``: the pulses; ``acquisition``:
    the burst that starts a sensor's filter."""

    def __init__(self, cfg, coils, sensors, book, acquisition, supervisor, tx, host, lengths, core=_DEFAULT_CORE):
        self.cfg = cfg
        self.n = n_coils = len(coils)
        self._sens = tuple(sensors)
        self.book = book
        self.acq = acquisition
        self.supervisor = supervisor
        self.tx = tx
        self.host = host
        #: the pulse lengths (``pulse_length.PulseLengths``); the longest bounds the timing checks
        self.lengths = lengths
        self.pulse_us = lengths.longest()
        self.lead_us = cfg.adaptive.adaptive_lead_us
        self.nominal = np.array([c.current for c in cfg.source.coils])
        self.cycle = FixedCycle(n_coils, cfg.timing.first_cycle_us, cfg.timing.cycle_us, cfg.timing.spacing_us, cfg.timing.pulse_us,
                                self.lead_us)
        self._warming = False            # the fixed cycle after a start (``reference_warmup_us``)
        self._held_start = -1            # the start a decision put off to the next tick keeps
        self._dec_phase = 0              # the decision's next part (0: none in progress)
        self.no_current = 0              # decisions no coil could carry
        # what every tick's _decide asks of the configuration, bound once: a lost track's position
        # variance and silence, the warm-up; each sensor's covariance as a flat view (its position diagonal)
        a = cfg.adaptive
        self._lost_var = a.acquire_sigma_m * a.acquire_sigma_m
        self._lost_us = 4 * a.adaptive_max_interval_us
        self._warmup_us = a.reference_warmup_us
        self._settle = a.reference_settle_drop > 0.0
        nx = len(self._sens[0].ekf.P) if self._sens else 0
        self._lost_at = tuple((s, memoryview(s.ekf.P.reshape(-1))) for s in self._sens)
        self._pos_diag = tuple(i * (nx + 1) for i in range(POS.start, POS.start + 3))

    # ------------------------------------------------------------ the stage
    def step(self, now_us: int) -> None:
        """Decide the next pulse, and the flips."""
        self._decide(now_us)
        self._flip(now_us)

    def _decide(self, now_us: int) -> None:
        if self._dec_phase:
            self._resume()
            return
        held = self._held_start
        self._held_start = -1
        if self.acq.active:
            return
        for s in self._sens:
            if not s.ekf.initialized:
                if self.book.n_active() == 0:
                    self.acq.try_start(now_us)
                return
        # lost: an uncertainty beyond any use, or no usable pulse for a long time
        big = self._lost_var
        i0, i1, i2 = self._pos_diag
        for s, P in self._lost_at:
            if (P[i0] > big or P[i1] > big or P[i2] > big
                    or now_us - s.last_update_us > self._lost_us):
                self.host.reacquire(s)
                return
        if self.book.n_active() >= 2:
            return
        # after a start the fixed cycle itself (accuracy_target "fixed"), for reference_warmup_us and
        # (reference_settle_drop > 0) until its reference has settled (``accuracy.FixedCycleReference``): its full-current
        # pulses of every coil while the errors are too large for eq 4 and the heading and the gyro
        # offsets converge; the filter's covariance understates its errors while they are large
        # (normalised orientation errors of 2-2.6 in the seconds after the warm-up on seed 10, against
        # 0.9 for the fixed cycle at the same time), so a policy holding that covariance to the
        # cycle's then converges more slowly and keeps a heading offset
        self._warming = False
        settle = self._settle
        for s in self._sens:
            if s.ref is not None and s.ref.active and (now_us - s.ref_start_us < self._warmup_us
                                                       or (settle and not s.ref.settled)):
                self._warming = True
        self._decide_own(now_us, held)

    def _resume(self) -> None:
        """The next part of a decision spread over ticks (none in the fixed cycle)."""
        self._dec_phase = 0

    def _decide_own(self, now_us: int, held: int) -> None:
        raise NotImplementedError

    def _follows_cycle(self) -> bool:
        """Whether the fixed cycle's pulses are being commanded (the flips then fit between them)."""
        return True

    def _decide_fixed(self, now_us: int) -> None:
        """The fixed X, Y, Z cycle, each pulse commanded ``adaptive_lead_us``
        before its start and used as a single-coil update."""
        cyc = self.cycle
        if not cyc.due(now_us):
            return
        start = cyc.start_us()
        if start >= now_us + self.cfg.timing.tick_us:
            j = cyc.coil
            self.book.command(j, float(self.nominal[j]), start, cyc.pulse_us, False)
        cyc.advance(now_us)      # a cycle that could not be scheduled in time is skipped

    def _flip(self, now_us: int) -> None:
        """Set/reset flips outside every pulse window (thesis sec 5.5, 7.2).

        Pulses are decided just in time, so there is no planned quiet gap as
        in the fixed cycle: every ``flip_every_us`` no new pulse is decided
        until those in flight are closed, then the sensors are told to flip
        a few milliseconds ahead and the next pulse may not start before that
        flip's trailing baseline has passed. The command also keeps the
        sensors from flipping on their own (which could land in a window)."""
        book = self.book
        if now_us - book.last_flip_cmd_us < self.cfg.adaptive.flip_every_us or book.n_active() or self._dec_phase:
            return
        cfg = self.cfg
        fl = self.supervisor.flips
        t0 = now_us + 1_000
        if self._follows_cycle() and not self.acq.active:
            nxt = self.cycle.start_us()
            if nxt - cfg.pulse.baseline_us - 2 * cfg.pulse.guard_us < t0 + fl.min_gap_us:
                return
        fl.plan(now_us, t0, t0 + fl.min_gap_us, self.tx.send, self.tx.mag_flip)
        at = fl.last_at_us
        book.hold_until(at + cfg.pulse.baseline_us + cfg.pulse.guard_us + cfg.pulse.guard_us)
        book.note_flip(now_us)


class FixedActuation(_SingleCoilActuation):
    """The fixed X, Y, Z cycle at the nominal currents (``cycle_us``, ``spacing_us``,
    ``pulse_us``), each pulse a single-coil update (``single_coil_fusion``)."""

    def _decide_own(self, now_us: int, held: int) -> None:
        self._decide_fixed(now_us)


class AdaptiveActuation(_SingleCoilActuation):
    """Schepers' policy: a pulse when the predicted uncertainty would reach its bound, the coil
    that reduces it most, the current that brings it to ``sigma_min`` (module docstring).

    ``lengths`` (``pulse_length.PulseLengths``): one length (``pulse_length = "fixed"``), or
    the lengths the chooser weighs against the current (``"chosen"``: ``CoilChooser.choose_length``),
    their starts aligned to the sensor's sample clock."""

    def __init__(self, cfg, coils, sensors, book, acquisition, supervisor, tx, host, lengths, core=_DEFAULT_CORE):
        super().__init__(cfg, coils, sensors, book, acquisition, supervisor, tx, host, lengths, core)
        n = self.n
        self.pmodel = SingleCoilModel(coils, cfg.source.field_model, core)      # decisions
        d2r = math.pi / 180.0
        smax = (cfg.adaptive.sigma_max_pos_m,) * 3 + (cfg.adaptive.sigma_max_ori_deg * d2r,) * 3
        smin = (cfg.adaptive.sigma_min_pos_m,) * 3 + (cfg.adaptive.sigma_min_ori_deg * d2r,) * 3
        currents = cfg.adaptive.adaptive_currents_a or current_ladder(
            min(cfg.adaptive.adaptive_min_current_a, cfg.adaptive.adaptive_max_current_a), cfg.adaptive.adaptive_max_current_a,
            cfg.adaptive.adaptive_current_levels)
        trace = cfg.adaptive.bound_on == "trace"
        # a ladder made here is a search grid, not the driver's levels: with adaptive_current_step_a
        # the current is refined between its rungs (``CoilChooser`` ``step_a``), never finer than the
        # command's resolution; given levels are kept as given
        step = 0.0 if cfg.adaptive.adaptive_currents_a else cfg.adaptive.adaptive_current_step_a
        if 0.0 < step < CURRENT_LSB_A:
            step = CURRENT_LSB_A
        self.chooser = coil_chooser(core, n, currents, smax, smin, cfg.adaptive.field_model_rel_sigma, cfg.limits.current_tolerance_a,
                                   trace, step, cfg.adaptive.unreached_share)
        self.policy = actuation_policy(core, smax, cfg.adaptive.adaptive_max_interval_us, trace)
        self.pending_update = PoseCovUpdate()
        self.var_amp = lengths.var_amp[-1]
        self.mid_us = lengths.mid_us[-1]
        self._vars = [0.0] * lengths.n        # the lengths' amplitude variances, inflated
        self.gap_us = pulse_gap_us(cfg)
        self.views = tuple(SensorOutlook(s) for s in self._sens)
        for s in self._sens:
            if s.ref is not None:
                s.ref.set_settle(cfg.adaptive.reference_settle_drop)
        self._lim = np.zeros(n)
        self._zero3 = np.zeros(3)
        self._knee_on = cfg.adaptive.saturation_knee > 0.0
        #: where the decision's numeric parts run (the chooser runs its own)
        self.kernels = "python"
        if core.ext is not None:
            self._pk = core.ext.PolicyCore(n, self.pmodel.h, self.pmodel.H, self._lim)
            # the configuration the compiled steps pass, bound once
            self._rel_model, self._tol_a = cfg.adaptive.field_model_rel_sigma, cfg.limits.current_tolerance_a
            self._range_cfg = (cfg.adaptive.saturation_sigmas, cfg.pulse.mag_range_t, cfg.pulse.saturation_margin,
                               cfg.pulse.earth_field_max_t)
            self._in_flight = self._in_flight_compiled
            self._range_limits = self._range_limits_compiled
            if self._bind_bounds(core.ext):
                self._bounds = self._bounds_compiled
            self._bind_views(core.ext)
            self.kernels = "compiled"
        self._decided_stamp = -1
        self._decided_us = 0
        self._dec_start = 0
        self._dec_ws: SensorOutlook | None = None
        self._dec_var = 0.0
        self._dec_coil = -1
        self._pm_for = None              # the sensor pmodel was last evaluated for, in this decision

    def _follows_cycle(self) -> bool:
        return self._warming

    def _resume(self) -> None:
        if self._dec_phase == 2:
            self._decide_choose()
        else:
            self._decide_command()

    def _decide_own(self, now_us: int, held: int) -> None:
        cfg = self.cfg
        book = self.book
        if self._warming:
            n0 = book.pulses
            self._decide_fixed(now_us)
            if book.pulses != n0 or book.n_active() >= 2:
                return
            # between the cycle's pulses, a pulse on demand only where the filter is far behind the
            # fixed cycle's present covariance (see _bounds), ending before the cycle's next pulse
        elif now_us - book.last_flip_cmd_us >= cfg.adaptive.flip_every_us:
            return      # a flip is due: let the pulses in flight close first (see _flip)
        start = max(now_us + self.lead_us, book.next_free_us)
        if held >= 0:           # put off from the last tick: the start it had (lead less one tick)
            start = max(held, book.next_free_us, now_us + cfg.timing.tick_us)
        if start - now_us > self.lead_us + cfg.timing.tick_us:
            return
        if self._warming and start + self.pulse_us + self.gap_us + cfg.timing.tick_us > self.cycle.start_us():
            return
        # the prediction changes only when an IMU sample (or an update) has moved a filter
        stamp = 0
        for s in self._sens:
            stamp += s.stamp()
        if stamp == self._decided_stamp and now_us - self._decided_us < cfg.adaptive.decision_refresh_us:
            return
        if self.host.updated_us == now_us and held < 0 and start - now_us > 2 * cfg.timing.tick_us:
            # bounded tick: this tick has run an EKF update (the heaviest matrix work of the mode);
            # the decision (a prediction per sensor and pulse in flight, the coil choice) runs in
            # the next one, for the same start
            self._held_start = start
            return
        self._decided_stamp = stamp
        self._decided_us = now_us
        if self.lengths.aligned:
            ring = self._sens[0].track.ring
            if len(ring):
                start = self.lengths.align(start, ring.latest_t_us)
        self._decide_predict(start, now_us)
        if self._dec_phase == 1:
            self._decide_limits()

    # A decision runs in three ticks (bounded tick): the prediction at the measurement time
    # (``_decide_predict``) with the current limits (``_decide_limits``), the coil choice
    # (``_decide_choose``), and its command (``_decide_command``). The first reads everything the
    # others use of the filters (covariance, orientation, quiet sample, NIS verdict) in its own
    # tick, so the decision is the one a single tick would make; its command leaves two ticks
    # later, for the same start (``adaptive_lead_us`` ahead). No flip and no other decision runs in
    # between.
    def _decide_predict(self, start: int, now_us: int) -> None:
        """Predicted covariance at the measurement time, with the pulses in flight; which sensor
        is worst off, and whether a pulse is due."""
        t_m = start + self.mid_us
        self._pm_for = None
        worst = -1.0
        ws = None
        due = False
        policy, slots, L = self.policy, self.book.slots, self.lengths
        for v in self.views:
            s = v.sensor
            self._predict_view(v, t_m, now_us)
            for sl in slots:
                if sl.active and not sl.acq:
                    if self._pm_for is not v:
                        self._model_at(v)
                    var = self.host.sharing.chained(L.var_amp[L.index_of(sl.end - sl.start)])
                    self._in_flight(v, sl, var * s.monitor.r_scale)
            if policy.due(v.P6, now_us, s.last_update_us):
                due = True
            u = policy.worst(v.P6)
            if u > worst:
                worst = u
                ws = v
        if not due or ws is None:
            return
        for v in self.views:
            self._refresh_quiet(v)
        # the expected amplitude variance, inflated while the pulses prove inconsistent
        self.host.forget(ws.sensor, now_us)
        # ... and the share of a baseline the previous pulse's window also used (estimate.shared_baseline)
        # (the longest length's is the decision's: asked once)
        sh, prev = self.host.sharing, self.book.last_pulse_end
        r_scale = ws.sensor.monitor.r_scale
        L = self.lengths
        if L.n > 1:
            for k in range(L.n):
                self._vars[k] = sh.predicted(L.var_amp[k], start, prev) * r_scale
            self._dec_var = self._vars[-1]
        else:
            self._dec_var = sh.predicted(self.var_amp, start, prev) * r_scale
        self._dec_ws = ws
        self._dec_start = start
        self._dec_phase = 1

    def _predict_view(self, v: SensorOutlook, t_m: int, now_us: int) -> None:
        """The filter's orientation (``v.Rd``), pose covariance and position predicted at ``t_m``
        (``v.P6``, ``v.pp``), the bounds there (:meth:`_bounds`) and the policy's (``set_bounds``)."""
        ekf = v.sensor.ekf
        np.copyto(v.Rd, ekf.R)
        ekf.predict_pose(t_m - (ekf.t_us if ekf.t_us is not None else now_us), v.P6, v.pp)
        self._bounds(v)
        self.policy.set_bounds(v.smax6)

    def _predict_view_compiled(self, v: SensorOutlook, t_m: int, now_us: int) -> None:
        """:meth:`_predict_view` in one call (``ViewCore.predict``: ``ct_sc_predict_pose``, ``ct_scp_bounds``,
        ``ct_scp_policy_set_bounds``, the kernels the calls it replaces run), bit for bit."""
        s = v.sensor
        ekf = s.ekf
        v.view_core.predict(t_m - (ekf.t_us if ekf.t_us is not None else now_us), s.ref is not None and s.ref.active,
                            self._warming, s.monitor.excess)

    def _bind_views(self, ext) -> None:
        """Bind each view's one-call prediction (``ViewCore``) where its parts are all compiled: the
        filter's own prediction (a subclass keeping ``SchepersEKF``'s), the bounds and the policy."""
        if self._bounds != self._bounds_compiled or not isinstance(self.policy, CompiledActuationPolicy):
            return
        for v in self.views:
            ekf = v.sensor.ekf
            if ekf.kernels != "compiled" or type(ekf).predict_pose is not SchepersEKF.predict_pose:
                return
        for v in self.views:
            v.view_core = ext.ViewCore(v.sensor.ekf._ck, v.bounds_core, self.policy._ck, v.P6, v.pp, v.Rd)
        self._predict_view = self._predict_view_compiled

    def _decide_limits(self) -> None:
        """Current limits: the driver's, every sensor's magnetometer range, the coils' duty (in the
        prediction's tick: nothing they read moves between the decision's ticks)."""
        cfg = self.cfg
        lim = self._lim
        lim.fill(cfg.adaptive.adaptive_max_current_a)
        for v in self.views:
            if self._pm_for is not v:
                self._model_at(v)
            self._range_limits(v)
        for c in range(self.n):
            if not self.book.duty_ok(c, self._dec_start, self.pulse_us):
                lim[c] = 0.0
        ws = self._dec_ws
        if self._pm_for is not ws:          # (a call that would find it evaluated skipped)
            self._model_at(ws)
        # the knee of the worst-off sensor's information per joule (actuate.saturation_knee), for the
        # shortest length's white noise (the length least energy mostly takes); no call where it is
        # off (saturation_knee <= 0: cap_at_knee leaves the limits)
        if self._knee_on:
            cap_at_knee(lim, self.pmodel.h, self._vars[0] if self.lengths.n > 1 else self._dec_var,
                        cfg.adaptive.field_model_rel_sigma, cfg.limits.current_tolerance_a, cfg.adaptive.saturation_knee)
        self.policy.set_bounds(ws.smax6)
        self.chooser.set_bounds(ws.smax6, ws.smin6)
        self._dec_phase = 2

    def _range_limits(self, v: SensorOutlook) -> None:
        """Each coil's limit (``_lim``) lowered to the current that keeps the magnetometer of
        ``v``'s sensor in range (``coil_choice.saturation_current_limit``; ``pmodel`` at its pose)."""
        cfg = self.cfg
        lim = self._lim
        # the field grows as r^-3: allow for the sensor being saturation_sigmas stds closer
        r = math.sqrt(float(v.pp[0] * v.pp[0] + v.pp[1] * v.pp[1] + v.pp[2] * v.pp[2]))
        sp = math.sqrt(max(float(v.P6[0, 0] + v.P6[1, 1] + v.P6[2, 2]), 0.0))
        gain = (r / max(r - cfg.adaptive.saturation_sigmas * sp, 0.5 * r)) ** 3 if r > 0.0 else 8.0
        for c in range(self.n):
            if v.have_quiet:
                i = saturation_current_limit(self.pmodel.h[c], v.quiet, cfg.pulse.mag_range_t,
                                             cfg.pulse.saturation_margin, gain)
            else:       # no quiet sample yet: assume the largest earth field on every axis
                i = saturation_current_limit(self.pmodel.h[c], self._zero3,
                                             cfg.pulse.mag_range_t - cfg.pulse.earth_field_max_t / cfg.pulse.saturation_margin,
                                             cfg.pulse.saturation_margin, gain)
            if i < lim[c]:
                lim[c] = i

    def _range_limits_compiled(self, v: SensorOutlook) -> None:
        """:meth:`_range_limits` in one call (``ct_scp_range_limits``), bit for bit."""
        sigmas, mag_range, margin, earth = self._range_cfg
        self._pk.range_limits(v.pp, v.P6, v.quiet, v.have_quiet, sigmas, mag_range, margin, earth)

    def _in_flight(self, v: SensorOutlook, sl, var: float) -> None:
        """The eq-4 covariance update of pulse ``sl`` in flight (amplitude variance ``var``) on
        ``v.P6`` (``coil_choice.PoseCovUpdate``; ``pmodel`` at ``v``'s pose)."""
        cfg = self.cfg
        self.pending_update.apply(v.P6, self.pmodel.H[sl.coil], self.pmodel.h[sl.coil], sl.current, var,
                                  cfg.adaptive.field_model_rel_sigma, cfg.limits.current_tolerance_a)

    def _in_flight_compiled(self, v: SensorOutlook, sl, var: float) -> None:
        """:meth:`_in_flight` through ``ct_scp_pose_cov_update`` (the products to rounding)."""
        self._pk.pose_cov_update(v.P6, sl.coil, sl.current, var, self._rel_model, self._tol_a)

    def _decide_choose(self) -> None:
        """The coil and current of the pulse (``actuate.coil_choice``); its command in the next tick."""
        self._dec_phase = 0
        ws = self._dec_ws
        L = self.lengths
        gains = getattr(ws.sensor.ekf, "gains", None)
        if gains is not None and self.cfg.adaptive.gain_in_choice:
            self.chooser.set_gain_var(ws.sensor.ekf.P, gains.rows.start)
        if L.n == 1:
            coil = self.chooser.choose(ws.P6, self.pmodel, self._dec_var, self._lim)
        else:
            coil = self.chooser.choose_length(ws.P6, self.pmodel, self._vars, L.lengths_us, self._lim)
        if coil < 0:
            self.no_current += 1
            return
        self._dec_coil = coil
        self._dec_phase = 3

    def _decide_command(self) -> None:
        """The chosen pulse's command (``single_coil_pulses.PulseBook``), for the decision's start."""
        self._dec_phase = 0
        L = self.lengths
        k = self.chooser.length if L.n > 1 else 0
        self.book.command(self._dec_coil, self.chooser.current, self._dec_start, L.lengths_us[k], False,
                          L.mid_us[k] if L.n > 1 else -1)

    def _model_at(self, v: SensorOutlook) -> None:
        """``pmodel`` at the predicted pose (``v.pp``, and ``v.Rd``: the filter's orientation in
        the decision's first tick), evaluated once per decision and sensor: nothing in a decision
        moves the pose it is evaluated at (3 coil field evaluations saved per pulse in flight
        and per decision)."""
        if self._pm_for is not v:
            self.pmodel.evaluate(v.pp, v.Rd)
            self._pm_for = v

    def _bounds(self, v: SensorOutlook) -> None:
        """The bounds (``v.smax6``, ``v.smin6``; m, rad) the decision holds for a sensor at its
        predicted position ``v.pp``.

        ``accuracy_target = "stated"``: ``sigma_max_*`` and ``sigma_min_*``, scaled as
        ``(r / sigma_range_ref_m)^exp`` when ``sigma_range_ref_m`` > 0. ``"fixed"``: from the
        fixed cycle's predicted mean variance (``accuracy.fixed_cycle_bounds``; the stated
        bounds until the reference has started). With ``nis_feedback`` the variance bounds are
        then divided by the NIS excess (``accuracy.nis_bound_factor``): the accuracy is asked
        of the errors, not of the covariance."""
        cfg = self.cfg
        s = v.sensor
        mx, mn = v.smax6, v.smin6
        if s.ref is not None and s.ref.active:
            ref = s.ref
            r = math.sqrt(float(v.pp[0] * v.pp[0] + v.pp[1] * v.pp[1] + v.pp[2] * v.pp[2]))
            fixed_cycle_bounds(ref.held_avg(cfg.adaptive.fixed_accuracy_ratio), cfg.adaptive.fixed_accuracy_ratio, cfg.adaptive.adaptive_min_ratio, mx, mn,
                               ref.law_now(r, 0), ref.law_now(r, 1))
            if self._warming:
                # the fixed cycle runs; a pulse between its pulses only when the filter's variance
                # would pass reference_catchup times the fixed cycle's present one
                Pr = ref.P
                k2 = cfg.adaptive.reference_catchup * cfg.adaptive.fixed_accuracy_ratio ** 2
                for k, i in ((0, POS.start), (1, POS.start + 1), (2, POS.start + 2),
                             (3, ORI.start), (4, ORI.start + 1), (5, ORI.start + 2)):
                    x = float(Pr[i, i]) * k2
                    mx[k] = math.sqrt(x) if x > 0.0 else 0.0
                    mn[k] = cfg.adaptive.adaptive_min_ratio * float(mx[k])
        else:
            self._stated_bounds(v)
        if cfg.adaptive.nis_feedback:
            f = math.sqrt(nis_bound_factor(s.monitor.excess, cfg.adaptive.nis_feedback_max))
            if f != 1.0:
                for k in range(POSE_DIM):
                    mx[k] = float(mx[k]) / f
                    mn[k] = float(mn[k]) / f

    def _bind_bounds(self, ext) -> bool:
        """Bind each view's compiled bounds (``sc_policy.c`` ``ct_scp_bounds``) to its arrays and its
        reference's; False (the Python reference kept) where a reference is of another kind."""
        a = self.cfg.adaptive
        cores = []
        for v in self.views:
            ref = v.sensor.ref
            refs = mean = None
            if ref is not None:
                if type(ref) not in (FixedCycleReference, MeanBudgetReference):
                    return False
                refs, mean = ref.held_arrays()
            params = np.array([a.fixed_accuracy_ratio, a.adaptive_min_ratio, a.reference_catchup,
                               1.0 if a.nis_feedback else 0.0, a.nis_feedback_max, HOLD_MIN, HOLD_MAX,
                               a.sigma_max_pos_m, a.sigma_min_pos_m, a.sigma_max_ori_deg, a.sigma_min_ori_deg,
                               a.sigma_range_ref_m, a.sigma_range_exp_pos, a.sigma_range_exp_ori,
                               ref.exp[0] if ref is not None else 0.0, ref.exp[1] if ref is not None else 0.0])
            cores.append(ext.BoundsCore((v.pp, v.smax6, v.smin6), refs, mean, params))
        for v, c in zip(self.views, cores):
            v.bounds_core = c
        return True

    def _bounds_compiled(self, v: SensorOutlook) -> None:
        """:meth:`_bounds` in one call (``ct_scp_bounds``), bit for bit."""
        s = v.sensor
        v.bounds_core.bounds(s.ref is not None and s.ref.active, self._warming, s.monitor.excess)

    def _stated_bounds(self, v: SensorOutlook) -> None:
        """``sigma_max_*``, ``sigma_min_*``, scaled by ``(r / sigma_range_ref_m)^exp`` when set."""
        cfg = self.cfg
        sp = so = 1.0
        if cfg.adaptive.sigma_range_ref_m > 0.0:
            r = math.sqrt(float(v.pp[0] * v.pp[0] + v.pp[1] * v.pp[1] + v.pp[2] * v.pp[2]))
            x = max(r, 1e-3) / cfg.adaptive.sigma_range_ref_m
            sp = x ** cfg.adaptive.sigma_range_exp_pos
            so = x ** cfg.adaptive.sigma_range_exp_ori
        d2r = math.pi / 180.0
        mx, mn = v.smax6, v.smin6
        for k in range(3):
            mx[k] = cfg.adaptive.sigma_max_pos_m * sp
            mn[k] = cfg.adaptive.sigma_min_pos_m * sp
            mx[3 + k] = cfg.adaptive.sigma_max_ori_deg * d2r * so
            mn[3 + k] = cfg.adaptive.sigma_min_ori_deg * d2r * so

    def _refresh_quiet(self, v: SensorOutlook) -> None:
        """The newest magnetometer sample, if no pulse was on when it was taken."""
        ring = v.sensor.track.ring
        nn = len(ring)
        if nn == 0:
            return
        last = self.book.last_pulse_us if self.lengths.n > 1 else self.pulse_us
        if not self.book.quiet_at(ring.latest_t_us, last):
            return
        p = ring.slot(nn - 1)
        v.quiet[0] = ring.b[p, 0]
        v.quiet[1] = ring.b[p, 1]
        v.quiet[2] = ring.b[p, 2]
        v.have_quiet = True
