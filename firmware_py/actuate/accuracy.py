"""The accuracy the adaptive policy holds: the fixed cycle's own, predicted beside the filter.

Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``) sec. 2.1 and
Fig. 1 pulse when the uncertainty reaches a stated ``sigma_x,max``; which
bound gives the fixed cycle's accuracy depends on the motion and the range,
so a bound tuned on one trajectory does not hold on the next. With
``accuracy_target = "fixed"`` the bound is instead *derived*, on every run,
from the covariance the fixed X, Y, Z cycle of the ``[timing]`` section
(``pulse_us``, ``spacing_us``, ``cycle_us``, each coil at its nominal
current) would have along the same estimated trajectory with the same
filter:

* :class:`FixedCycleReference` keeps that covariance, ``P_ref`` (15, 15) over
  the inertial error state of ``coiltrack.firmware.estimate.single_coil``
  (position, velocity, orientation, accelerometer and gyroscope offsets). It
  is propagated with the live filter's own error transition and process
  noise at every IMU sample (``SchepersEKF.core_transition``, thesis
  ``002_cd7f1fdb7fc67471.txt`` eq 6.17), and at the mid instant of every
  pulse of the virtual fixed cycle it takes the eq-4 covariance update of
  that coil at its nominal current, linearised at the live estimate (eqs
  9-11). Eq 4 does not need the measured value, so no pulse is made: the
  update goes through the one Joseph-form ``KalmanUpdate`` with a zero
  innovation and no gate.
* ``avg`` (6,) is the time mean of the reference's pose variances
  ``P_ref[k, k]`` (m^2, rad^2), an exponential average over
  ``reference_avg_s``: the RMS error a consistent filter on the
  fixed cycle would show is the square root of this mean. Until the
  reference has **settled** it follows the present variances instead: after a
  start the heading and the gyroscope offsets converge over ten seconds or
  more (the offset is seen only through the orientation errors it builds up
  between pulses), and a mean taken over that convergence is several times the
  cycle's steady-state variance (0.66 against 0.33 deg on seed 1), a bound the
  policy would then hold for the rest of the run while the fixed cycle itself
  is far more accurate. Settled: at the end of a cycle, the trace of the
  reference's gyroscope-offset variance has fallen by less than
  ``settle_drop`` over that cycle (the Riccati recursion of the fixed schedule
  near its fixed point; the offsets' variance, unlike the pose's, does not
  move with the range). Until then the policy holds the fixed cycle's present
  covariance, so its convergence is the fixed cycle's.
* :func:`fixed_cycle_bounds` turns it into the policy's bounds. Between two
  adaptive pulses a variance climbs from ``sigma_min^2 = m^2 sigma_max^2``
  to ``sigma_max^2`` about linearly, so its time mean is ``(1 + m^2) / 2
  sigma_max^2``; the bound that gives the fixed cycle's mean variance times
  ``ratio^2`` is ``sigma_max^2 = 2 ratio^2 avg / (1 + m^2)``.

Work: the propagation is two 15x15 products per IMU sample; each reference
pulse evaluates the coil set once at the estimate (``n_coils`` field
evaluations, 5 reference pulses a second on the thesis cycle). All arrays
are allocated in ``__init__``.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import KalmanUpdate
from coiltrack.firmware.estimate.layout import GYR, ORI, POS, SCHEPERS_CORE as CORE

__all__ = ["FixedCycleReference", "fixed_cycle_bounds", "nis_bound_factor"]

N_CORE = CORE.stop

#: a ``settle_drop`` that settles the schepers-adaptive reference about 10 s after a start (seeds 1,
#: 10: 10.7 s; see the module docstring)
SETTLE_DROP = 0.05
#: ... or at the latest this long after its start (us): a sensor whose offsets are seen too weakly
#: to converge is held to the mean from then on
SETTLE_MAX_US = 30_000_000


def fixed_cycle_bounds(avg6, ratio: float, min_ratio: float, out_max6, out_min6, law_pos: float = 1.0,
                       law_ori: float = 1.0) -> None:
    """Bounds (std, m and rad) that hold a mean variance of ``ratio^2 avg6``.

    ``avg6`` (6,): the reference's time-mean pose variances; ``min_ratio``:
    ``sigma_min / sigma_max``; ``law_pos``, ``law_ori``: the range law at the
    present range over its own mean, ``r^(2 e) / mean(r^(2 e))`` (1: the same
    bound at every range). Writes ``sigma_max = sqrt(2 ratio^2 avg law /
    (1 + min_ratio^2))`` into ``out_max6`` and ``min_ratio sigma_max`` into
    ``out_min6`` (see the module docstring for the sawtooth mean)."""
    k = 2.0 * ratio * ratio / (1.0 + min_ratio * min_ratio)
    for i in range(6):
        v = float(avg6[i]) * (law_pos if i < 3 else law_ori)
        s = (k * v) ** 0.5 if v > 0.0 else 0.0
        out_max6[i] = s
        out_min6[i] = min_ratio * s


def nis_bound_factor(excess: float, max_factor: float) -> float:
    """Factor (>= 1) the variance bounds are divided by for a mean NIS of
    ``excess`` times its expectation: a filter whose innovations are
    ``excess`` times larger than its covariance says has errors about that
    much larger than its covariance, so it must hold a covariance that much
    smaller to reach the accuracy asked for (capped at ``max_factor``)."""
    if not excess > 1.0:          # also NaN
        return 1.0
    return excess if excess < max_factor else max_factor


class FixedCycleReference:
    """Covariance of the fixed X, Y, Z cycle along the live estimate (one sensor).

    Parameters
    ----------
    currents : sequence (n_coils,)
        Nominal current of each coil (A).
    first_cycle_us, cycle_us, spacing_us : int
        The fixed cycle's timetable (``coiltrack.firmware.actuate.fixed_cycle``).
    mid_us : int
        Mid time of a pulse's used samples from its start edge.
    var_amp : float
        Variance of one amplitude component of one fixed-cycle pulse (T^2).
    rel_model, current_sigma : float
        Relative field-model error and current std (A), as in the filter's
        own measurement covariance.
    avg_us : float
        Time constant of the mean variance (us).
    warmup_us : int
        After a start the means follow the present values for at least this long (us).
    settle_drop : float
        ... and until the gyroscope-offset variance falls by less than this fraction over a
        cycle (0: settled as soon as ``warmup_us`` has passed).
    """

    def __init__(self, currents, first_cycle_us: int, cycle_us: int, spacing_us: int, mid_us: int,
                 var_amp: float, rel_model: float, current_sigma: float, avg_us: float,
                 exp_pos: float = 0.0, exp_ori: float = 0.0, warmup_us: int = 0, core=_DEFAULT_CORE,
                 settle_drop: float = 0.0):
        self.currents = tuple(float(c) for c in currents)
        self.n = len(self.currents)
        self.first_cycle_us = int(first_cycle_us)
        self.cycle_us = int(cycle_us)
        self.spacing_us = int(spacing_us)
        self.mid_us = int(mid_us)
        self.var_amp = float(var_amp)
        self.rel_model = float(rel_model)
        self.current_sigma = float(current_sigma)
        self.avg_us = float(avg_us)
        n = N_CORE
        self.P = np.zeros((n, n))
        self._Pd = self.P.reshape(-1)[::n + 1]
        self.F = np.eye(n)
        self._Fv = memoryview(self.F)
        self._Ft = self.F.T
        self.q = np.zeros(n)
        self._T = np.zeros((n, n))
        self.upd = KalmanUpdate(n, 3, 1.0, core)
        self.avg = np.zeros(6)
        #: the running mean of ``r^(2 exp)`` (position, orientation) over the same instants as
        #: :attr:`avg`: the range law's own mean, which normalises it (``fixed_cycle_bounds``)
        self.exp = (2.0 * float(exp_pos), 2.0 * float(exp_ori))
        self.law = np.ones(2)
        self.elapsed_us = 0.0
        #: after a start the means follow the present values for this long (us): the start's
        #: large covariance is not the accuracy of the run
        self.warmup_us = float(warmup_us)
        self.settle_drop = float(settle_drop)
        #: whether the means average (True) or follow the present values (until settled)
        self.settled = False
        self._gyr_var = -1.0             # the gyroscope-offset variance trace at the last cycle's end
        self.mean_us = 0.0               # time averaged since the reference settled (us)
        self.active = False
        self.t_us = 0
        self.cycle_start = self.first_cycle_us
        self.coil = 0
        self.pulses = 0          # reference pulses taken (counted, never commanded)
        self._a = 1.0            # the weight of the latest interval in the means
        self.kernels = "python"
        if core.ext is not None:
            self._bind_compiled(core.ext)

    def _own_means(self):
        """The running means a subclass keeps beside the reference's in ``_propagate`` (None:
        none; ``accuracy_budget.MeanBudgetReference``: the live filter's variance traces)."""
        return None

    def _bind_compiled(self, ext) -> None:
        """Bind the compiled propagation (``core/src/sc_policy.c`` ``ct_scp_ref_propagate``) in
        place of :meth:`_propagate`, once, where this class's (or the mean budget's) is run."""
        if type(self)._propagate.__qualname__ not in ("FixedCycleReference._propagate",
                                                      "MeanBudgetReference._propagate"):
            return
        self._st = np.zeros(ext.REF_NST)
        self._stv = memoryview(self._st)
        self._ck = ext.FixedRefCore((self.P, self.F, self.q, self._T, self.avg, self.law, self._st), self._own_means(),
                                    self.warmup_us, self.avg_us, self.exp[0], self.exp[1])
        self._propagate = self._propagate_compiled
        if type(self)._pulse is FixedCycleReference._pulse:
            upd = self.upd
            self._ck.bind_pulse(upd.H, upd.R, upd.y, N_CORE, POS.start, ORI.start, self.var_amp, self.rel_model,
                                self.current_sigma)
            self._pulse = self._pulse_compiled
        self.kernels = "compiled"

    def held_avg(self, ratio: float):
        """The mean pose variances (6,) the policy's bounds hold (``fixed_cycle_bounds``): the
        reference's own (``accuracy_budget.MeanBudgetReference`` carries a deficit in them)."""
        return self.avg

    def held_arrays(self):
        """The arrays :meth:`held_avg` and :meth:`law_now` read, ``(avg, law, P)``, and those the
        mean budget's ``held_avg`` reads and writes, ``(own, factor, held)`` (None here): for a
        compiled decision bound to them (``single_coil_policy``'s ``ct_scp_bounds``)."""
        return (self.avg, self.law, self.P), None

    def note_pulse(self, nis_nominal: float, y, var) -> None:
        """A pulse of the live filter (nominal NIS, amplitude, white variances): nothing here;
        ``accuracy_actual`` estimates the actual model error from them."""
        return

    def set_settle(self, drop: float) -> None:
        """The ``settle_drop`` of the next start (the policy's ``reference_settle_drop``)."""
        self.settle_drop = float(drop)

    def law_now(self, r: float, g: int) -> float:
        """``r^(2 e_g) / mean(r^(2 e_g))`` for group ``g`` (0 position, 1 orientation)."""
        m = float(self.law[g])
        if not m > 0.0:
            return 1.0
        r = r if r > 1e-3 else 1e-3
        return r ** self.exp[g] / m

    def next_mid_us(self) -> int:
        return self.cycle_start + self.coil * self.spacing_us + self.mid_us

    def start(self, P_core, t_us: int) -> None:
        """Start from the live filter's core covariance ``P_core`` (15, 15) at ``t_us``."""
        self.P[:] = P_core
        for k in range(3):
            self.avg[k] = self.P[POS.start + k, POS.start + k]
            self.avg[3 + k] = self.P[ORI.start + k, ORI.start + k]
        self.t_us = int(t_us)
        self.elapsed_us = 0.0
        self.settled = False
        self._gyr_var = -1.0
        self.mean_us = 0.0
        self.law[0] = self.law[1] = -1.0          # set at the first interval
        # the cycle in phase with the timetable: the first pulse after t_us
        while self.next_mid_us() <= self.t_us:
            self._advance()
        self.active = True

    def stop(self) -> None:
        self.active = False

    def _advance(self) -> None:
        self.coil += 1
        if self.coil == self.n:
            self.coil = 0
            self.cycle_start += self.cycle_us
            if self.active:
                self._check_settled()

    def _check_settled(self) -> None:
        """At a cycle's end: settled once ``warmup_us`` has passed and the gyroscope-offset
        variance fell by less than ``settle_drop`` over the cycle (or ``SETTLE_MAX_US`` have passed)."""
        P = self.P
        g = float(P[GYR.start, GYR.start]) + float(P[GYR.start + 1, GYR.start + 1]) + float(P[GYR.start + 2, GYR.start + 2])
        prev = self._gyr_var
        self._gyr_var = g
        if self.settled or self.elapsed_us < self.warmup_us:
            return
        if (self.settle_drop <= 0.0 or (prev > 0.0 and g > (1.0 - self.settle_drop) * prev)
                or self.elapsed_us >= SETTLE_MAX_US):
            self.settled = True

    def step(self, ekf, t_us: int, model) -> None:
        """Carry the reference to ``t_us`` (the live filter's time after an IMU
        sample): propagate with the filter's transition over the interval,
        update at every reference pulse whose mid time has passed
        (``model``: a ``SingleCoilModel``, evaluated at the live estimate)."""
        if not self.active:
            return
        t_us = int(t_us)
        while True:
            t_m = self.cycle_start + self.coil * self.spacing_us + self.mid_us      # next_mid_us()
            t1 = t_m if t_m <= t_us else t_us
            d_us = t1 - self.t_us
            if d_us > 0:
                self._propagate(ekf, d_us * 1e-6, d_us)
                self.t_us = t1
            if t_m > t_us:
                break
            self._pulse(ekf, model, self.coil)
            self._advance()

    def _propagate(self, ekf, dt: float, dt_us: int) -> None:
        ekf.core_transition(self._Fv, self.q, dt)
        np.matmul(self.F, self.P, out=self._T)
        np.matmul(self._T, self._Ft, out=self.P)
        self._Pd += self.q
        # the present values until settled; then the mean since then until avg_us have passed,
        # then an exponential one over avg_us
        self.elapsed_us += dt_us
        if self.settle_drop <= 0.0:
            e = self.elapsed_us - self.warmup_us
            self.settled = e > 0.0
        else:
            if self.settled:
                self.mean_us += dt_us
            e = self.mean_us
        a = 1.0 if e <= dt_us else dt_us / (e if e < self.avg_us else self.avg_us)
        if a > 1.0:
            a = 1.0
        self._a = a
        p = ekf.p
        r = (float(p[0]) * float(p[0]) + float(p[1]) * float(p[1]) + float(p[2]) * float(p[2])) ** 0.5
        r = r if r > 1e-3 else 1e-3
        for g in range(2):
            x = r ** self.exp[g]
            self.law[g] = x if self.law[g] < 0.0 else self.law[g] + a * (x - self.law[g])
        P = self.P
        avg = self.avg
        for k in range(3):
            i = POS.start + k
            j = ORI.start + k
            avg[k] += a * (float(P[i, i]) - float(avg[k]))
            avg[3 + k] += a * (float(P[j, j]) - float(avg[3 + k]))

    def _propagate_compiled(self, ekf, dt: float, dt_us: int) -> None:
        """:meth:`_propagate` through ``ct_scp_ref_propagate`` (the live filter's compiled
        transition); the Python reference where the filter runs its own dynamics."""
        eck = getattr(ekf, "_ck", None)
        if eck is None:
            type(self)._propagate(self, ekf, dt, dt_us)
            return
        self._ck.propagate(eck, dt, dt_us, self.elapsed_us, self.mean_us, self.settled, self.settle_drop)
        st = self._stv
        self.elapsed_us = st[0]
        self.mean_us = st[1]
        self.settled = st[2] != 0.0
        self._a = st[3]

    def _pulse(self, ekf, model, coil: int) -> None:
        """Eq-4 covariance update of ``coil`` at its nominal current (Joseph form)."""
        model.evaluate(ekf.p, ekf.R)
        c = self.currents[coil]
        Hu = model.H[coil]
        hu = model.h[coil]
        upd = self.upd
        H = upd.H
        H.fill(0.0)
        for i in range(3):
            for j in range(3):
                H[i, POS.start + j] = c * float(Hu[i, j])
                H[i, ORI.start + j] = c * float(Hu[i, 3 + j])
        hn2 = float(hu[0] * hu[0] + hu[1] * hu[1] + hu[2] * hu[2])
        r = self.var_amp + (self.rel_model * self.rel_model * c * c + self.current_sigma * self.current_sigma) * hn2
        Rm = upd.R
        Rm.fill(0.0)
        for i in range(3):
            Rm[i, i] = r
        upd.y.fill(0.0)
        upd.update(self.P)
        self.pulses += 1

    def _pulse_compiled(self, ekf, model, coil: int) -> None:
        """:meth:`_pulse` with its measurement (``H``, ``R``, ``y``) filled by
        ``ct_scp_ref_pulse_fill`` (``core/src/sc_policy.c``): the same products, the same bits;
        the update is the same ``KalmanUpdate``'s."""
        model.evaluate(ekf.p, ekf.R)
        self._ck.pulse(model.h, model.H, coil, self.currents[coil])
        self.upd.update(self.P)
        self.pulses += 1
