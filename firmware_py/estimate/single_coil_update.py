"""The iterated single-coil update of the error-state EKF (``single_coil.SchepersEKF``).

Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``): a magnetic update
takes the pulse of ONE source coil, ``y = I R^T B_c(p) + v`` (eq 5, field eqs
6-8), linearised with eqs 9-11, and corrects the error state with eq 4; the
linearisation error grows near the source (sec. 3.2). :class:`CoilMeasurement`
is the value one pulse hands the filter (amplitude, its variances, coil,
current, model error, the monitor's inflation, the gate);
:class:`SingleCoilUpdate` owns the buffers of the update and runs it on the
covariance its filter passes in (as ``ekf.KalmanUpdate.update`` does), leaving
the error estimate in ``dx`` for the filter to inject. All arrays are
allocated in ``__init__``.

The compiled core (``coiltrack.firmware.core``, chosen once by the ``core`` argument):
``core/src/single_coil.c`` follows ``_noise``, ``_pass`` up to the shared update and
:meth:`SingleCoilUpdate.run`'s bookkeeping between the passes operation by operation (the
products the Python hands to BLAS, ``P H^T``, ``H P H^T``, ``H dx`` and ``R dR``, summed in index
order with ``H``'s zeros skipped: equal to rounding); the field model's evaluation and the shared
``KalmanUpdate.update`` (its own compiled kernel, count and symmetrisation) are called as they are.
On the compiled core a whole run is one call (``SingleCoilUpdateCore.run``, :meth:`SingleCoilUpdate._run_fused`):
the same kernels (the signal model's ``ct_signal_fields`` / ``ct_signal_project_jac``, the passes',
``ct_kalman_update``) in the same order, bound once to the update's, the shared update's and the
model's buffers.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import EKF_GATED, EKF_NONFINITE, EKF_NOT_PD, SYMMETRIZE_EVERY, KalmanUpdate
from coiltrack.firmware.linalg import exp_rotvec, inv3_sym, quad3_sym

__all__ = ["CoilGains", "CoilMeasurement", "SingleCoilUpdate"]

#: margin on the linearisation error: the second-order term of an r^-3 field is 6 (d/r)^2
#: h; the iterated update removes most of it, 2 (sigma/r)^2 |h| is kept as a margin
_LIN_K = 2.0
#: the fused run's outputs (``SingleCoilUpdateCore.run``'s ``rs``): updates applied, rejected, the first
#: pass's NIS, the last pass's, the model's evaluations
_RS_APPLIED, _RS_REJECTED, _RS_NIS, _RS_NIS_LAST, _RS_EVALS = range(5)


class CoilMeasurement:
    """One pulse's amplitude as the filter takes it (a value object: its owner fills one
    preallocated instance per pulse, so the tick allocates nothing).

    ``y`` (3,) amplitude, T, sensor frame; ``var`` (3,) its variances, T^2; ``coil``;
    ``current`` A; ``rel_model``: relative error of the predicted field (model and current,
    ``R += (rel_model |h|)^2``); ``r_scale``: the NIS monitor's inflation of the whole
    covariance; ``gate``: whether the chi-square gate applies (false once the monitor has
    judged the pulses inconsistent and inflated ``R``)."""

    __slots__ = ("y", "var", "coil", "current", "rel_model", "r_scale", "gate")

    def __init__(self, y=None, var=None, coil: int = 0, current: float = 0.0, rel_model: float = 0.0,
                 r_scale: float = 1.0, gate: bool = True):
        self.y = np.zeros(3) if y is None else y
        self.var = np.zeros(3) if var is None else var
        self.coil = int(coil)
        self.current = float(current)
        self.rel_model = float(rel_model)
        self.r_scale = float(r_scale)
        self.gate = bool(gate)

    def set(self, y, var, coil: int, current: float, rel_model: float, r_scale: float, gate: bool):
        """Refill in place (the arrays are referenced, not copied); returns itself."""
        self.y = y
        self.var = var
        self.coil = coil
        self.current = current
        self.rel_model = rel_model
        self.r_scale = r_scale
        self.gate = gate
        return self


class SingleCoilUpdate:
    """The buffers and the passes of the iterated single-coil update over ``nx`` states."""

    def __init__(self, nx: int, gate_probability: float, iterations: int, core=_DEFAULT_CORE):
        self.nx = int(nx)
        self.iterations = max(1, int(iterations))
        self.upd = KalmanUpdate(nx, 3, gate_probability, core)
        self._PHt = np.zeros((nx, 3))
        self._S = np.zeros((3, 3))
        self.y_pred = np.zeros(3)
        self.nis = 0.0
        self.nis_nominal = 0.0
        self._P0 = np.zeros((nx, nx))
        self._Pprev = np.zeros((nx, nx))
        self.dx = np.zeros(nx)
        self._pi = np.zeros(3)
        self._Ri = np.eye(3)
        self._Hdx = np.zeros(3)
        self._dR = np.eye(3)
        self._k0 = np.zeros(())
        self.core = "python"
        ext = core.ext
        if ext is not None:
            self._st = np.zeros(ext.SC_NST)
            self._stv = memoryview(self._st)
            self._nis_at = ext.SC_NIS_NOMINAL
            u = self.upd
            self._ck = ext.SingleCoilUpdateCore(nx, (u.H, u.R, u.y, u.dx, self._PHt, self._S, self.y_pred, self._P0,
                                                     self._Pprev, self.dx, self._pi, self._Ri, self._Hdx, self._dR,
                                                     self._st))
            self.run = self._run_fused
            self._run_model = None       # the model the fused run is bound to (the first one run)
            self._rs = np.zeros(ext.SC_RS_N)
            self._rsv = memoryview(self._rs)
            self.core = "compiled"

    def _noise(self, P, p, cp, m: CoilMeasurement, model) -> tuple[float, float]:
        """The measurement covariance from the prior into ``upd.R`` (amplitude variances, the
        field-model error, the linearisation margin of Schepers sec. 3.2); returns ``|h|^2``
        and the squared distance to the coil."""
        yp = self.y_pred
        hn2 = float(yp[0] * yp[0] + yp[1] * yp[1] + yp[2] * yp[2])
        b = cp.start
        sp2 = max(float(P[b, b]), float(P[b + 1, b + 1]), float(P[b + 2, b + 2]))
        c = model.cs.centers[m.coil]
        ddx, ddy, ddz = float(p[0] - c[0]), float(p[1] - c[1]), float(p[2] - c[2])
        r2 = max(ddx * ddx + ddy * ddy + ddz * ddz, 1e-6)
        lin = _LIN_K * sp2 / r2
        extra = (m.rel_model * m.rel_model + lin * lin) * hn2
        Rm = self.upd.R
        Rm.fill(0.0)
        for i in range(3):
            Rm[i, i] = float(m.var[i]) + extra
        return hn2, r2

    def _pass(self, it: int, P, cp, co, m: CoilMeasurement, model, gain: int = -1, gain_current: float = 0.0) -> int:
        """One pass through the shared ``KalmanUpdate``: the pseudo-innovation
        ``y - h(x_i) + H_i dx_i``; the first pass also gives the nominal NIS (unscaled R).
        ``gain`` >= 0: the error row of the coil's gain, whose column of ``H`` is
        ``gain_current h`` (``y = (1 + g) I h``: ``single_coil`` module docstring); it is left out
        of ``H_i dx_i`` (the gain's correction enters ``h(x_i)`` and ``H_i dx_i`` alike, so it
        cancels in a Gauss-Newton pass)."""
        upd = self.upd
        H = upd.H
        cur = self._k0
        Hu = model.H[m.coil]
        H.fill(0.0)
        np.multiply(Hu[:, 0:3], cur, out=H[:, cp])
        np.multiply(Hu[:, 3:6], cur, out=H[:, co])
        np.subtract(m.y, self.y_pred, out=upd.y)
        if it:
            np.matmul(H, self.dx, out=self._Hdx)
            np.add(upd.y, self._Hdx, out=upd.y)
        if gain >= 0:
            h = model.h[m.coil]
            for i in range(3):
                H[i, gain] = float(h[i]) * gain_current
        if not it:
            np.matmul(P, upd._Ht, out=self._PHt)
            np.matmul(H, self._PHt, out=self._S)
            self._S += upd.R
            self.nis_nominal = _nis3(self._S, upd.y)
            if m.r_scale != 1.0:
                for i in range(3):
                    upd.R[i, i] *= m.r_scale
        if it:
            P[:] = self._P0
        # the gate belongs to the first pass
        return upd.update(P, math.inf if it or not m.gate else None)

    def run(self, P, p, R, cp, co, m: CoilMeasurement, model, gain: int = -1, gain_current: float = 0.0) -> int:
        """Run the update of ``m`` on the covariance ``P`` (corrected in place), linearised at
        the pose ``(p, R)`` whose error rows are ``cp``, ``co``. Returns the ``ekf.EKF_*``
        flags of the first pass; the error estimate is left in :attr:`dx` unless that pass
        was gated or failed.

        Iterated update (``iterations`` > 1): the measurement is relinearised at the
        corrected clone pose, ``dx_{i+1} = K_i (y - h(x_i) + H_i dx_i)`` (Gauss-Newton on
        the eq-4 cost), each pass from the prior covariance; the last pass gives the
        covariance. A second pass is made only when the first correction changes ``h``
        through its second-order term (``6 (dp/r)^2 |h|``, Schepers sec. 3.2) by more than
        a tenth of the amplitude noise (after an acquisition, not while tracking).

        ``gain``, ``gain_current``: the error row of the coil's gain and the current its column of
        ``H`` is taken at (``_pass``; -1: no gain state)."""
        model.evaluate(p, R)
        self._k0[()] = m.current
        np.multiply(model.h[m.coil], self._k0, out=self.y_pred)
        hn2, r2 = self._noise(P, p, cp, m, model)
        self._P0[:] = P
        dx = self.dx
        dx.fill(0.0)
        pi, Ri = self._pi, self._Ri
        pi[:] = p
        Ri[:] = R
        flags = 0
        upd = self.upd
        for it in range(self.iterations):
            if it:
                model.evaluate(pi, Ri)
                np.multiply(model.h[m.coil], self._k0, out=self.y_pred)
            f = self._pass(it, P, cp, co, m, model, gain, gain_current)
            if it == 0:
                flags = f
                self.nis = upd.nis
                if f & (EKF_GATED | EKF_NOT_PD | EKF_NONFINITE):
                    return f
            elif f & (EKF_NOT_PD | EKF_NONFINITE):
                P[:] = self._Pprev           # keep the previous pass
                break
            b = cp.start
            step = max(abs(float(upd.dx[b + i]) - float(dx[b + i])) for i in range(3))
            dx[:] = upd.dx
            if it == 0:
                dp2 = float(dx[b] * dx[b] + dx[b + 1] * dx[b + 1] + dx[b + 2] * dx[b + 2])
                so = 6.0 * dp2 / r2
                noise2 = float(m.var[0] + m.var[1] + m.var[2]) / 3.0
                if so * so * hn2 < 0.01 * noise2:
                    break
            if it + 1 < self.iterations:
                self._Pprev[:] = P
                np.add(p, dx[cp], out=pi)          # next linearisation point: the corrected pose
                o = co.start
                exp_rotvec(float(dx[o]), float(dx[o + 1]), float(dx[o + 2]), self._dR)
                np.matmul(R, self._dR, out=Ri)
                if step < 1e-6:
                    break
        return flags

    def _bind_run(self, model) -> bool:
        """Bind the fused run (``SingleCoilUpdateCore.run``) to the shared update's buffers and to
        ``model``'s, once; False (the passes one call each, :meth:`_run_compiled`) for a model
        whose evaluation is not the plain compiled signal model (a distortion map, the Python
        kernels) or once another model is bound."""
        sig = model.signal
        if self._run_model is not None or getattr(sig, "core", "python") != "compiled" or sig.distortion is not None:
            return False
        u = self.upd
        self._ck.bind_run((u.H, u.R, u.y, u.dx, u.S, u.Sinv, u.K, u._PHt, u._T, u._TH, u._X, u._KR, u._w, u._L, u._M),
                          (sig._geom, sig.B, sig.J, model.h, model.H, model.cs.centers), self._rs, SYMMETRIZE_EVERY)
        self._run_model = model
        return True

    def _run_fused(self, P, p, R, cp, co, m: CoilMeasurement, model, gain: int = -1, gain_current: float = 0.0) -> int:
        """:meth:`run` in one compiled call (``SingleCoilUpdateCore.run``: the model's evaluations, the
        passes of :meth:`_run_compiled` and the shared update's with its bookkeeping, the same kernels
        in the same order: the same bits); its counts, NISs and evaluations read back from ``_rs``."""
        if model is not self._run_model and not self._bind_run(model):
            return self._run_compiled(P, p, R, cp, co, m, model, gain, gain_current)
        upd = self.upd
        flags = self._ck.run(P, p, R, cp.start, co.start, m.coil, m.y, m.var, m.current, m.rel_model, m.r_scale,
                             upd.gate if m.gate else math.inf, self.iterations, upd.count, gain, gain_current)
        rs = self._rsv
        upd.add_counts(int(rs[_RS_APPLIED]), int(rs[_RS_REJECTED]), rs[_RS_NIS_LAST])
        self.nis_nominal = self._stv[self._nis_at]
        self.nis = rs[_RS_NIS]
        model.signal.add_evals(model.n * int(rs[_RS_EVALS]))
        return flags

    def _run_compiled(self, P, p, R, cp, co, m: CoilMeasurement, model, gain: int = -1,
                      gain_current: float = 0.0) -> int:
        """:meth:`run` through the compiled passes (``ct_scu_begin``, ``ct_scu_pass``,
        ``ct_scu_after``) around the model's evaluation and the shared update."""
        model.evaluate(p, R)
        ck, upd = self._ck, self.upd
        b, o = cp.start, co.start
        ck.begin(P, p, R, b, o, model.h, model.H, model.cs.centers, m.coil, m.y, m.var, m.current, m.rel_model,
                 m.r_scale, gain, gain_current)
        self.nis_nominal = self._stv[self._nis_at]
        flags = upd.update(P, math.inf if not m.gate else None)
        self.nis = upd.nis
        if flags & (EKF_GATED | EKF_NOT_PD | EKF_NONFINITE):
            return flags
        f, it = flags, 0
        while ck.after(it, f, self.iterations, P, p, R, b, o, m.var):
            it += 1
            model.evaluate(self._pi, self._Ri)
            ck.again(it, P, b, o, model.h, model.H, m.coil, m.y, m.current, gain, gain_current)
            f = upd.update(P, math.inf)
        return flags


class CoilGains:
    """Each coil's gain error as states of the single-coil filter (``single_coil.CoilGainEKF``:
    ``y = (1 + g_c) I R^T B_c(p)``, Schepers & Veltink 2010 eq 5 with the coil's true current):
    the nominal gains ``gain``, their error rows ``rows``, the prior std ``sigma``, the filter's
    update ``u`` (:meth:`run` runs it; :meth:`inject` adds the gain rows of its ``dx``)."""

    def __init__(self, rows: slice, sigma: float, u: SingleCoilUpdate):
        self.rows = rows
        self.n = rows.stop - rows.start
        self.sigma = float(sigma)
        self.gain = np.zeros(self.n)
        self._u = u
        self._dx = u.dx[rows]
        self._meas = CoilMeasurement()

    def restore_prior(self, P) -> None:
        """The gains' variances the prior's, their covariances 0 (a (re)started pose)."""
        for i in range(self.rows.start, self.rows.stop):
            P[i, i] = self.sigma * self.sigma

    def run(self, P, p, R, cp, co, m: CoilMeasurement, model) -> int:
        """:meth:`SingleCoilUpdate.run` of ``m`` with eq 5 at the coil's current ``(1 + g_c) I``
        and the gain's error column ``I h_c``."""
        c = m.coil
        mg = self._meas.set(m.y, m.var, c, m.current * (1.0 + float(self.gain[c])), m.rel_model, m.r_scale,
                            m.gate)
        return self._u.run(P, p, R, cp, co, mg, model, self.rows.start + c, m.current)

    def inject(self) -> None:
        """Add the update's gain corrections to the nominal gains."""
        self.gain += self._dx


def _nis3(S, r) -> float:
    """``r^T S^-1 r`` for a symmetric 3x3 ``S`` (inf if not positive definite)."""
    inv = inv3_sym(float(S[0, 0]), float(S[0, 1]), float(S[0, 2]),
                   float(S[1, 1]), float(S[1, 2]), float(S[2, 2]))
    if inv is None:
        return math.inf
    return quad3_sym(inv, float(r[0]), float(r[1]), float(r[2]))
