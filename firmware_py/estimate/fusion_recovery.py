"""The fusion filter's (re)start from a magnetic solution, and the offsets kept across it.

Recovery (docs/faults.md): the filter restarts from a magnetic solution when
``reinit_after`` solutions in a row fail the gate (``RECOVER_DISAGREE``), when
the last accepted update is older than ``dead_reckon_limit_us``
(``RECOVER_GAP``) or after the IMU stream broke off (``RECOVER_STREAM``). The
offsets ``b_a``, ``b_g`` and their covariance block survive a restart while
credible: decayed by eqs 6.13-6.14 of the thesis (``002_cd7f1fdb7fc67471.txt``)
and with their random-walk variance added for the time between.

All buffers are created in ``__init__``; nothing here allocates after.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.estimate.fusion_state import InsState
from coiltrack.firmware.estimate.layout import ACC, GYR, POS, POSE_POS, VEL
from coiltrack.firmware.linalg import congruence3


class Recovery:
    """Starts ``InsState`` copies from a magnetic solution and keeps the offsets across restarts.

    Counters: ``recoveries`` (restarts after the first start), ``biases_kept`` (of which kept
    the offsets); ``recovering`` (restarted, no update accepted since), ``recovery_reason``
    (``RECOVER_*`` of the pending or last restart), ``kept`` / ``kept_t`` (offsets kept, when).
    """

    def _set_recovering(self, v: bool) -> None:
        self._rsv[0] = 1 if v else 0

    # 0/1 in an int64 array (``rs``) the compiled one-call IMU sample reads
    recovering = property(lambda self: self._rsv[0] != 0, _set_recovering)

    def __init__(self, params, measurement):
        self.rs = np.zeros(1, dtype=np.int64)
        self._rsv = memoryview(self.rs)
        self.prm = params
        self.meas = measurement
        #: the white states' blocks and their prior variances (the measurement model's)
        self._white = tuple(zip(*measurement.white(params)))
        self._kb = np.zeros(6)
        self._kP = np.zeros((6, 6))
        self._kbv = memoryview(self._kb)
        self._kPv = memoryview(self._kP)
        self.kept = False
        self.kept_t = 0
        self.ever_initialised = False
        self.recovering = False
        self.recovery_reason = 0
        self.recoveries = 0
        self.biases_kept = 0

    def keep(self, st: InsState, reason: int) -> None:
        """A restart is coming for ``reason``: keep ``st``'s offsets when credible."""
        self.keep_biases(st)
        self.recovery_reason = reason

    def accepted(self) -> None:
        """An update was accepted: no longer recovering."""
        self.recovering = False

    def initialize(self, st: InsState, t_ref_us: int, snap, q, R_ms, C) -> None:
        """``st`` at ``t_ref``: position from the magnetic solution, velocity zero, orientation
        from the measurement model (Xi for models 2, 3, the magnetic one for model 1), the
        diagonal priors of the other states; the kept offsets restored on a restart."""
        prm = self.prm
        Phi = snap.Phiv
        p = st._pv
        for i in range(3):
            p[i] = Phi[i, 0] * q[0] + Phi[i, 1] * q[1] + Phi[i, 2] * q[2]
        st.v.fill(0.0)
        st.ba.fill(0.0)
        st.P.fill(0.0)
        P = st._Pv
        self.meas.start_orientation(st, snap, R_ms, C)
        congruence3(Phi, C, POSE_POS.start, P, POS.start)
        for i in range(3):
            P[VEL.start + i, VEL.start + i] = prm.velocity0_sigma ** 2
            P[ACC.start + i, ACC.start + i] = prm.acc_bias_sigma ** 2
            P[GYR.start + i, GYR.start + i] = prm.gyro_bias_sigma ** 2
            for blk, var in self._white:
                P[blk.start + i, blk.start + i] = var
        if self.ever_initialised:
            self.recoveries += 1
            self.recovering = True
            if self.kept and self.restore_biases(st, t_ref_us):
                self.biases_kept += 1
        self.kept = False
        self.ever_initialised = True
        st.set_time(t_ref_us)

    def keep_biases(self, st: InsState) -> None:
        """Remember ``st``'s offsets and their covariance block (rows ``ACC``,
        ``GYR``) for the next restart, when credible: every offset within
        ``bias_gate_sigmas`` of its prior (a diverged state has run them off)."""
        prm = self.prm
        self.kept = False
        if not prm.keep_biases:
            return
        ga = prm.bias_gate_sigmas * prm.acc_bias_sigma
        gg = prm.bias_gate_sigmas * prm.gyro_bias_sigma
        ba, bg = st._bav, st._bgv
        for i in range(3):
            if not (abs(ba[i]) <= ga and abs(bg[i]) <= gg):
                return
        kb, kP, P = self._kbv, self._kPv, st._Pv
        a0, g0 = ACC.start, GYR.start
        for i in range(3):
            kb[i] = ba[i]
            kb[3 + i] = bg[i]
        for i in range(6):
            ri = a0 + i if i < 3 else g0 + i - 3
            for j in range(6):
                kP[i, j] = P[ri, a0 + j if j < 3 else g0 + j - 3]
        self.kept = True
        self.kept_t = st.t_us

    def restore_biases(self, st: InsState, t_us: int) -> bool:
        """The kept offsets into ``st`` (just initialised at ``t_us``): the
        nominal values decayed by eqs 6.13-6.14 over the time since they were
        kept, the variances grown by the random walk (``sigma_rw^2 dt``); not
        used (False) when a grown variance is no smaller than the prior's."""
        prm = self.prm
        dt = max(0, t_us - self.kept_t) * 1e-6
        qa = prm.acc_bias_rw * prm.acc_bias_rw * dt
        qg = prm.gyro_bias_rw * prm.gyro_bias_rw * dt
        kP = self._kPv
        for i in range(3):
            if kP[i, i] + qa >= prm.acc_bias_sigma ** 2 or kP[3 + i, 3 + i] + qg >= prm.gyro_bias_sigma ** 2:
                return False
        ka = math.exp(-dt / prm.acc_bias_tau_s) if prm.acc_bias_tau_s > 0.0 else 1.0
        kg = math.exp(-dt / prm.gyro_bias_tau_s) if prm.gyro_bias_tau_s > 0.0 else 1.0
        kb, P = self._kbv, st._Pv
        ba, bg = st._bav, st._bgv
        a0, g0 = ACC.start, GYR.start
        for i in range(3):
            ba[i] = ka * kb[i]
            bg[i] = kg * kb[3 + i]
        for i in range(6):
            ri = a0 + i if i < 3 else g0 + i - 3
            si = ka if i < 3 else kg
            for j in range(6):
                sj = ka if j < 3 else kg
                P[ri, a0 + j if j < 3 else g0 + j - 3] = si * sj * kP[i, j]
            P[ri, ri] += qa if i < 3 else qg
        return True
