"""The fusion filter's prediction: the IMU samples kept for replay and the
strapdown and error-covariance step of an :class:`~coiltrack.firmware.estimate.fusion_state.InsState`.

Thesis ``002_cd7f1fdb7fc67471.txt`` sec 6.2: strapdown eqs 6.1-6.4 with the
net acceleration of eq 6.8, error transition eqs 6.10-6.17 (``A`` of eq 6.17;
``estimate.strapdown``), ``Q`` diagonal (sec 6.2.4). The numeric body of a
step is chosen once, when the filter is built: :meth:`InertialPrediction.step_python`
or the compiled core's (:meth:`InertialPrediction.step_compiled`,
``core/src/strapdown.c ct_ins_propagate``). On the compiled core the whole per-sample work
of a state is bound to it once (``core/src/fusimu.c``): the ring row a sample is kept in
(:meth:`InertialPrediction.push`), the input interpolation with the step (``ct_fus_propagate``:
:meth:`~InertialPrediction.propagate`, :meth:`~InertialPrediction.set_dt`,
:meth:`~InertialPrediction.step_python`) and the history row (``ct_fus_to_source``); the
live state's forward path of one sample (the row, the step, the history row and the queued
pose) is one call (:meth:`InertialPrediction.sample`, ``ext.FusLive``).

All buffers are created in ``__init__``; a step allocates no numpy array.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.fusion_state import IMU_F, IMU_FIELDS, IMU_FSRC, IMU_W, InsState
from coiltrack.firmware.estimate.layout import ACC, GYR, ORI, VEL
from coiltrack.firmware.estimate.strapdown import Strapdown, integrate_pv, to_nav, transition_nav, transition_static
from coiltrack.firmware.estimate.fusion_rings import KernelRing
from coiltrack.firmware.ring import Ring


class InertialPrediction:
    """IMU ring and the per-sample strapdown and covariance step (eqs 6.1-6.4, 6.8, 6.10-6.17).

    Parameters
    ----------
    params : magnetic_inertial.FusionParams
    n : int
        State dimension (``layout.fusion_layout``).
    frame : fusion_state.MovingSource or fusion_state.FixedSource
        The source frame, chosen once.
    imu_capacity : int
        IMU samples kept for replay.
    compiled : bool
        The states carry the compiled step (``InsState.ck``): use it.
    states : tuple of InsState
        The states this prediction steps (the filter's live and shadow states): on the compiled
        core each gets its bound kernel (``ext.FusPred``: its step, the step's workspace
        scalars ``dt_last, ka, kg`` in the state's ``ws``, and its history rows).
    """

    def _set_steps(self, v: int) -> None:
        self._psv[0] = v

    steps = property(lambda self: self._psv[0], _set_steps)     # forward steps run

    def __init__(self, params, n: int, frame, imu_capacity: int, compiled: bool, core=_DEFAULT_CORE,
                 states=()):
        prm = params
        # the step's constants of set_dt, as it computes them (the same values to the bit)
        self._dtk = (prm.acc_bias_tau_s, prm.gyro_bias_tau_s, prm.acc_noise ** 2 + prm.source_acc_noise ** 2,
                     prm.gyro_noise, prm.acc_bias_rw * prm.acc_bias_rw, prm.gyro_bias_rw * prm.gyro_bias_rw)
        # flat indices of the diagonals of Q that set_dt rewrites with the step
        self._q_diag = tuple(tuple((b.start + i) * (n + 1) for i in range(3)) for b in (VEL, ORI, ACC, GYR))
        self.frame = frame
        self.sd = Strapdown(core)
        self.imu = KernelRing(imu_capacity, IMU_FIELDS)     # (its head and count shared: ext.ImuSample)
        self._itv, self._idv, self._icap = self.imu.tv, self.imu.dv, self.imu.capacity
        self.ps = np.zeros(1, dtype=np.int64)    # the steps (``steps``), in place for the one-call IMU sample
        self._psv = memoryview(self.ps)
        #: the numeric body of each IMU step, chosen once (coiltrack.firmware.core)
        self._ins_step = self.step_compiled if compiled else self.step_python
        self._kern = {}
        if compiled and states:
            self._bind(core.ext, n, frame, states)

    def _bind(self, ext, n: int, frame, states) -> None:
        """The compiled per-sample path (``core/src/fusimu.c``), bound once to ``states``."""
        assert (IMU_F, IMU_W, IMU_FSRC, self.imu.width) == (0, 3, 6, ext.FUS_IMU_WIDTH)
        k = self._dtk
        moving = not frame.fixed
        assert ext.FUS_NST == 3
        for st in states:
            # (st.ws: dt_last, ka, kg, which the kernel's set_dt writes as InsState.set_step)
            self._kern[st] = ext.FusPred(n, st.p, st.v, st.Th, st.ba, st.bg, st.pred.A, st.P, st.pred.Q,
                                         st.pred._T, self.imu.t, self.imu.d, st.ws, k[0], k[1], k[2], k[3], k[4],
                                         k[5], moving)
        self._row = ext.FusRow(self.imu.d, self.imu.capacity, moving)
        self._ext = ext
        self.push = self._push_compiled
        self.propagate = self._propagate_compiled
        self.history = self._history_compiled
        self.advance = self._advance_compiled

    def bind_live(self, st: InsState, hist: Ring, out_kernel) -> None:
        """The compiled forward path of one sample (:meth:`sample`): ``st`` (one of the bound
        states), the history ``hist`` and the output kernel ``out_kernel`` (``ext.FusOutput``,
        bound to ``st``, this ring and ``hist``) in one ``ext.FusLive``."""
        self._live = self._ext.FusLive(self._kern[st], self._row, out_kernel, hist.d)

    live_kernel = property(lambda self: self._live)     # ext.FusLive (bind_live)

    def sample(self, st: InsState, hist: Ring, t0: int, t1: int, o: int, age: int, recovering: bool,
               inconsistent: bool, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi) -> None:
        """:meth:`push` of the sample at ``t1``, :meth:`advance` of ``st`` (the state given to
        :meth:`bind_live`) from ``t0`` and, when ``o >= 0``, ``PoseOutput.queue`` of its pose into
        output row ``o`` (``age``: since the last accepted update, the status flags) in one call of
        the compiled core (``ext.FusLive.sample``: ``ct_fus_propagate``, ``ct_fus_to_source``,
        ``ct_fus_status``, ``ct_fus_output``, the kernels of those three, in their order). The
        caller makes sure that the step is not split by a snapshot and that ``P`` is not
        symmetrised after it (``ekf.CovariancePredict.after_predict``), which the queued
        variances would read."""
        imu = self.imu
        k = imu.push(t1)
        self._live.sample(k, len(imu), t0, t1, hist.push(t1), o, age, recovering, inconsistent, fx, fy, fz,
                          wx, wy, wz, rx, ry, rz, Phi)
        self.sampled(st, t1)

    def sampled(self, st: InsState, t1: int) -> None:
        """The bookkeeping after a compiled forward step of ``st`` to ``t1`` (:meth:`sample`, or
        ``ext.ImuSample`` through ``FusionFilter.live_sample``: the periodic symmetrisation ran in the
        kernel; none is due after :meth:`sample`'s): the prediction's count, the steps, the time."""
        st.pred.set_count(st.pred.count + 1)
        self.steps += 1
        st.set_time(t1)

    def _push_compiled(self, t_us: int, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi) -> int:
        """:meth:`push` on the compiled core (the row written by ``ext.FusRow``)."""
        k = self.imu.push(t_us)
        self._row.store(k, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi)
        return k

    def _propagate_compiled(self, st: InsState, k: int, t0: int, t1: int) -> None:
        """:meth:`propagate` on the compiled core (``ct_fus_propagate``: the interpolation, the
        step's static blocks when the step changed, and ``ct_ins_propagate`` in one call)."""
        self._kern[st].propagate(k, len(self.imu), t0, t1)
        st.pred.after_predict(st.P)
        self.steps += 1

    def _advance_compiled(self, st: InsState, hist: Ring, k: int, t0: int, t1: int) -> None:
        """:meth:`advance` on the compiled core (one call: ``ct_fus_propagate``, ``ct_fus_to_source``)."""
        self._kern[st].advance(k, len(self.imu), t0, t1, hist.d, hist.push(t1))
        st.pred.after_predict(st.P)
        self.steps += 1
        st.set_time(t1)

    def _history_compiled(self, st: InsState, hist: Ring, k: int) -> None:
        """:meth:`history` on the compiled core (``ct_fus_to_source``)."""
        self._kern[st].history(hist.d, hist.push(st.t_us), k)

    def push(self, t_us: int, fx, fy, fz, wx, wy, wz, rx, ry, rz, Phi) -> int:
        """Keep one sample for replay (``Phi`` when the source moves); its ring slot."""
        k = self.imu.push(t_us)
        d = self._idv
        d[k, IMU_F], d[k, IMU_F + 1], d[k, IMU_F + 2] = fx, fy, fz
        d[k, IMU_W], d[k, IMU_W + 1], d[k, IMU_W + 2] = wx, wy, wz
        d[k, IMU_FSRC], d[k, IMU_FSRC + 1], d[k, IMU_FSRC + 2] = rx, ry, rz
        self.frame.store(d, k, Phi)
        return k

    def covers(self, t_us: int) -> bool:
        """The ring still holds a sample at or before ``t_us``."""
        imu = self.imu
        return len(imu) > 0 and imu.tv[imu.slot(0)] <= t_us

    def propagate(self, st: InsState, k: int, t0: int, t1: int) -> None:
        """Strapdown and covariance step of ``st`` over ``[t0, t1]`` with the IMU
        samples of ring slots ``k - 1`` and ``k`` (trapezoidal in the rate
        and in the global-frame specific force: the samples are instantaneous
        values; inputs at ``t0`` / ``t1`` interpolated linearly between the
        two entries). Strapdown and error transition: ``estimate.strapdown``
        (eqs 6.1-6.4, 6.8, 6.17)."""
        dt = (t1 - t0) * 1e-6
        d = self._idv
        tv = self._itv
        tk = tv[k]
        kp = k - 1 if k > 0 else self._icap - 1
        tp = tv[kp]
        # interpolation weights of entry k at t0 and t1 (1: entry k alone)
        if len(self.imu) > 1 and tp < tk:
            span = 1.0 / (tk - tp)
            a0 = (t0 - tp) * span
            a1 = (t1 - tp) * span
            if a0 < 0.0:
                a0 = 0.0
        else:
            kp = k
            a0 = a1 = 1.0
        b0 = 1.0 - a0
        b1 = 1.0 - a1
        ba = st._bav
        bg = st._bgv
        F, W, S = IMU_F, IMU_W, IMU_FSRC
        # the two entries, each element read once
        pfx, pfy, pfz, pwx, pwy, pwz = d[kp, F], d[kp, F + 1], d[kp, F + 2], d[kp, W], d[kp, W + 1], d[kp, W + 2]
        kfx, kfy, kfz, kwx, kwy, kwz = d[k, F], d[k, F + 1], d[k, F + 2], d[k, W], d[k, W + 1], d[k, W + 2]
        psx, psy, psz, ksx, ksy, ksz = d[kp, S], d[kp, S + 1], d[kp, S + 2], d[k, S], d[k, S + 1], d[k, S + 2]
        bax, bay, baz = ba[0], ba[1], ba[2]
        # inputs at t0 and t1 (offsets removed), the rate at mid-step
        f0x = b0 * pfx + a0 * kfx - bax
        f0y = b0 * pfy + a0 * kfy - bay
        f0z = b0 * pfz + a0 * kfz - baz
        f1x = b1 * pfx + a1 * kfx - bax
        f1y = b1 * pfy + a1 * kfy - bay
        f1z = b1 * pfz + a1 * kfz - baz
        am = 0.5 * (a0 + a1)
        bm = 1.0 - am
        wx = bm * pwx + am * kwx - bg[0]
        wy = bm * pwy + am * kwy - bg[1]
        wz = bm * pwz + am * kwz - bg[2]
        r0x, r0y, r0z = b0 * psx + a0 * ksx, b0 * psy + a0 * ksy, b0 * psz + a0 * ksz
        r1x, r1y, r1z = b1 * psx + a1 * ksx, b1 * psy + a1 * ksy, b1 * psz + a1 * ksz
        self._ins_step(st, dt, f0x, f0y, f0z, f1x, f1y, f1z, wx, wy, wz, r0x, r0y, r0z, r1x, r1y, r1z)

    def step_python(self, st: InsState, dt: float, f0x, f0y, f0z, f1x, f1y, f1z,
                    wx, wy, wz, r0x, r0y, r0z, r1x, r1y, r1z) -> None:
        """The numeric body of :meth:`propagate` (the reference of ``core/src/strapdown.c``
        ``ct_ins_propagate``): attitude, position and velocity, offset decay, eq 6.17's blocks
        and the covariance prediction."""
        ba = st._bav
        bg = st._bgv
        Th = st._Thv
        # specific force in G at t0 with the attitude at t0, at t1 with the attitude at t1
        g0x, g0y, g0z = to_nav(Th, f0x, f0y, f0z)
        self.sd.rotate(st.Th, wx * dt, wy * dt, wz * dt)
        g1x, g1y, g1z = to_nav(Th, f1x, f1y, f1z)
        integrate_pv(st._pv, st._vv, dt, g0x - r0x, g0y - r0y, g0z - r0z, g1x - r1x, g1y - r1y, g1z - r1z)
        if dt != st.dt_last:
            self.set_dt(st, dt)
        ka = st.ka
        kg = st.kg
        ba[0] *= ka
        ba[1] *= ka
        ba[2] *= ka
        bg[0] *= kg
        bg[1] *= kg
        bg[2] *= kg
        transition_nav(st._Av, dt, Th, 0.5 * (g0x + g1x), 0.5 * (g0y + g1y), 0.5 * (g0z + g1z))
        st.pred.predict(st.P)
        self.steps += 1

    def step_compiled(self, st: InsState, dt: float, f0x, f0y, f0z, f1x, f1y, f1z,
                      wx, wy, wz, r0x, r0y, r0z, r1x, r1y, r1z) -> None:
        """:meth:`step_python` on the compiled core (``InsState.ck``, bound at start-up): the
        step's static blocks written first (they depend on ``dt`` alone, not on the step's
        results), then one call does the rest."""
        if dt != st.dt_last:
            self.set_dt(st, dt)
        st.ck.propagate(dt, f0x, f0y, f0z, f1x, f1y, f1z, wx, wy, wz, r0x, r0y, r0z, r1x, r1y, r1z,
                        st.ka, st.kg)
        st.pred.after_predict(st.P)
        self.steps += 1

    def add_steps(self, n: int) -> None:
        """``n`` steps run by a compiled kernel (the replay's, ``core/src/fusion.c``)."""
        self.steps += n

    def set_dt(self, st: InsState, dt: float) -> None:
        """The parts of ``A`` and ``Q`` that depend on the step alone
        (eqs 6.10, 6.13-6.14), rewritten only when the step changes (the white
        magnetic states' noise has no step in it: :class:`InsState` writes it)."""
        k = self._dtk
        ka = math.exp(-dt / k[0]) if k[0] > 0.0 else 1.0
        kg = math.exp(-dt / k[1]) if k[1] > 0.0 else 1.0
        st.set_step(dt, ka, kg)
        transition_static(st._Av, dt, ka, kg)
        Q = st._Qf
        qv = k[2] * dt * dt
        qo = (k[3] * dt) ** 2
        qa = k[4] * dt
        qg = k[5] * dt
        v, o, a, g = self._q_diag
        Q[v[0]] = Q[v[1]] = Q[v[2]] = qv
        Q[o[0]] = Q[o[1]] = Q[o[2]] = qo
        Q[a[0]] = Q[a[1]] = Q[a[2]] = qa
        Q[g[0]] = Q[g[1]] = Q[g[2]] = qg

    def advance(self, st: InsState, hist: Ring, k: int, t0: int, t1: int) -> None:
        """:meth:`propagate` of ``st`` over ``[t0, t1]``, ``st`` then at ``t1``, and its pose appended
        to ``hist`` (:meth:`history`): a step not split by a snapshot."""
        self.propagate(st, k, t0, t1)
        st.set_time(t1)
        self.history(st, hist, k)

    def history(self, st: InsState, hist: Ring, k: int) -> None:
        """Append ``st``'s pose in the source frame to ``hist``: ``p_M = Phi^T p``,
        ``R_MS = Phi^T Theta`` (Phi of IMU slot ``k``)."""
        h = hist.push(st.t_us)
        self.frame.to_source(self._idv, k, st._pv, st._Thv, hist.dv, h)
