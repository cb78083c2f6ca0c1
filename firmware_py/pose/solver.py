"""Allocation-free, resumable pose solver: the firmware's counterpart of
``coiltrack.firmware.pose.reference.solve_pose``.

:class:`PoseSolver` is built once from the source coils. A solve is
started with :meth:`PoseSolver.begin` and advanced with
:meth:`PoseSolver.step`, each call doing at most a given number of *field
evaluations* (one coil's field and gradient at one point,
``model.signal``), so a 1 kHz loop can spread a solve over ticks with a
bounded, machine-independent amount of work per tick. Every unit of work
does at most ``n`` evaluations (an LM step, a step of the invariant fit,
one of the three evaluations of a grid direction, the orientation); the
closed forms (two Kuipers units, the covariance) evaluate no field and are
charged ``n`` each. :meth:`solve` is ``begin`` plus ``step`` until done. The
result does not depend on how the work was split (``pose.staged``).

Stages (``tests/firmware/test_solver.py`` compares them with the reference):

1. acquisition without a prior (``pose.acquire``): Kuipers' closed form
   (thesis ``seeds/002_cd7f1fdb7fc67471.txt`` App. 5.A) and, with the exact
   model near the source, the fit on the rotation invariant ``S^T S`` and a
   grid search of directions; the orientation from the polar factor of
   ``B(p) S^T``;
2. Levenberg-Marquardt (``pose.lm``) on ``sum ((S - h(p, R)) / sigma)^2``
   with ``h`` and its Jacobian from ``model.signal`` (Schepers & Veltink
   ``seeds/000_e46ec0e8bf7ea271.txt`` eqs 5-11), multiplicative orientation
   step ``R = R exp([d]x)``; one unit of work = one step = ``n``
   evaluations;
3. covariance ``(H^T W H)^-1`` at the solution with the second-order margin of
   the orientation error in its position block (``pose.covariance``).

Warm start: with ``x0`` (the tracked pose) only stage 2 runs. If it does
not converge, if its cost exceeds the chi-square quantile of ``3 n - 6``
degrees of freedom at ``gate_probability`` (``estimate.ekf.chi2_gate``,
fixed at construction) or if a ``hemisphere`` was given and the solution
lies on the other side (by more than ~6 deg), the solver falls back to
acquisition and fits again; the status then carries ``SOLVE_REACQUIRED``.

Conventions of ``pose.reference``: ``S[:, j]`` is the field of coil ``j``
in the sensor frame, ``R_true = R exp([dtheta]x)``, parameter order
``(p, dtheta)``. Bad input never raises: the status flags say what happened.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import chi2_gate
from coiltrack.firmware.linalg import ORTHONORMAL_TOL, Rot3, exp_rotvec, flat, float_view, nearest_rotation
from coiltrack.firmware.model.signal import SignalModel
from coiltrack.firmware.pose.acquire import MU0_4PI, Acquisition
from coiltrack.firmware.pose.covariance import RobustInverse6, RotationMargin
from coiltrack.firmware.pose.lm import LM_CONVERGED, LM_RUNNING, LevenbergMarquardt
from coiltrack.firmware.pose.staged import SOLVE_RUNNING as _RUNNING
from coiltrack.firmware.pose.staged import StagedSolve, init_results

__all__ = ["PoseSolver", "SOLVE_OK", "SOLVE_BAD_INPUT", "SOLVE_NO_START", "SOLVE_NOT_CONVERGED",
           "SOLVE_NONFINITE", "SOLVE_RUNNING", "SOLVE_REACQUIRED"]

# status flags (bit field)
SOLVE_OK = 0
SOLVE_BAD_INPUT = 1        # bad S, sigma, currents, hemisphere or x0: nothing solved
SOLVE_NO_START = 2         # coil moments do not span 3-D and no x0: nothing solved
SOLVE_NOT_CONVERGED = 4    # LM stopped on its iteration or damping limit (result still written)
SOLVE_NONFINITE = 8        # the result is not finite
SOLVE_RUNNING = _RUNNING    # begin/step: the solve is not finished yet
SOLVE_REACQUIRED = 32      # the warm start failed its checks; solved from acquisition

# default LM convergence at noise level, not machine precision: a step below 1e-5 of the
# range (5 um at 50 cm; rad for the orientation) or a relative cost change below 1e-6 is
# three orders of magnitude below the Cramer-Rao bound anywhere in the working volume, and
# stops the solve two to three iterations (6-9 field evaluations) earlier than the
# reference's 1e-9 / 1e-12 (``pose.reference``), which ``step_tol``/``cost_tol`` can match
STEP_TOL = 1e-5
COST_TOL = 1e-6
_UNBOUNDED = 1 << 62
# a warm solution counts as on the wrong side of the hemisphere plane only
# beyond this sine of its elevation (~6 deg): near the plane both mirror
# solutions are close to it and acquisition would pick the same one
_HEMI_MARGIN = 0.1
# the compiled warm path's state (core/include/ct_solve.h: CT_SV_*, the phases CT_PH_*)
_SV_PHASE, _SV_STATUS, _SV_ITERATIONS, _SV_COST, _SV_CONVERGED = 0, 1, 2, 3, 4
_SV_WARM, _SV_REACQUIRED, _SV_SIGMA_RMS, _SV_CHECK_HEMI, _SV_HEMI = 5, 6, 7, 8, 9
_SV_SPENT, _SV_EVALS, _SV_NST = 12, 13, 14
_PH_NONE, _PH_LM_START, _PH_ACQUIRE, _PH_ACQ_UNITS = 0, 1, 4, 5


def _gate(n: int, probability: float) -> float:
    """Chi-square quantile for the ``3 n - 6`` residual degrees of freedom of
    a converged fit; ``inf`` (no cost test) without residual freedom or
    beyond the table of ``chi2_gate`` (more than six coils)."""
    dof = 3 * n - 6
    if dof < 1 or dof > 12:
        return math.inf
    return chi2_gate(dof, probability)


class _PoseFit:
    """The 6-parameter least-squares problem of the LM (``pose.lm``):
    residual ``(S - h(p, R)) w`` with ``w = 1 / sigma``, current pose
    ``p``, ``R`` and a trial pose aside."""

    def __init__(self, signal, S, w, cur, step_tol: float):
        n = signal.n
        self.signal, self.S, self.w, self.cur = signal, S, w, cur
        self.step_tol = step_tol
        self.p = memoryview(np.zeros(3))
        self.p_t = memoryview(np.zeros(3))
        self.R = np.zeros((3, 3))
        self.R_t = np.zeros((3, 3))
        self._Rm = memoryview(self.R)
        self._Rtm = memoryview(self.R_t)
        self._dR = np.zeros((3, 3))
        self._dRm = memoryview(self._dR)
        self._h = memoryview(np.zeros(3 * n))
        self._H = memoryview(np.zeros(18 * n))

    def set(self, p, R) -> None:
        self.p[0], self.p[1], self.p[2] = p[0], p[1], p[2]
        np.copyto(self.R, R)

    def evaluate(self, A, g) -> float:
        p = self.p
        return self._cost(p[0], p[1], p[2], self._Rm, A, g)

    def trial(self, d, A, g) -> float:
        p, pt = self.p, self.p_t
        pt[0], pt[1], pt[2] = p[0] + d[0], p[1] + d[1], p[2] + d[2]
        E = self._dRm
        exp_rotvec(d[3], d[4], d[5], E)
        # R_t = R E as three sums per element in this order (the compiled step's, so both cores
        # take the same LM decisions to the bit; BLAS's product may fuse multiply-adds)
        R, Rt = self._Rm, self._Rtm
        for i in range(3):
            r0, r1, r2 = R[i, 0], R[i, 1], R[i, 2]
            Rt[i, 0] = r0 * E[0, 0] + r1 * E[1, 0] + r2 * E[2, 0]
            Rt[i, 1] = r0 * E[0, 1] + r1 * E[1, 1] + r2 * E[2, 1]
            Rt[i, 2] = r0 * E[0, 2] + r1 * E[1, 2] + r2 * E[2, 2]
        return self._cost(pt[0], pt[1], pt[2], Rt, A, g)

    def accept(self) -> None:
        p, pt = self.p, self.p_t
        p[0], p[1], p[2] = pt[0], pt[1], pt[2]
        np.copyto(self.R, self.R_t)

    def small(self, d) -> bool:
        """A step this small is followed by one of ~1e-18 (quadratic
        convergence) or is below the rounding level of the cost."""
        p = self.p
        pn = math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
        tol = self.step_tol
        return (math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) <= tol * max(pn, 1e-3)
                and math.sqrt(d[3] * d[3] + d[4] * d[4] + d[5] * d[5]) <= tol)

    def _cost(self, px, py, pz, R, a, g) -> float:
        """Weighted cost and normal equations ``a = H^T W H``,
        ``g = H^T W (S - h)`` at (p, R)."""
        h, H, S, w = self._h, self._H, self.S, self.w
        self.signal.measure(px, py, pz, R, self.cur, h, H)
        # the 21 distinct elements of the upper triangle of a and g accumulated
        # in locals (the same sums in the same order as into the buffers)
        g0 = g1 = g2 = g3 = g4 = g5 = 0.0
        a00 = a01 = a02 = a03 = a04 = a05 = a11 = a12 = a13 = a14 = a15 = 0.0
        a22 = a23 = a24 = a25 = a33 = a34 = a35 = a44 = a45 = a55 = 0.0
        cost = 0.0
        for q in range(3 * self.signal.n):
            wq = w[q]
            w2 = wq * wq
            e = S[q] - h[q]
            cost += e * e * w2
            rr = e * w2
            o = 6 * q
            h0, h1, h2, h3, h4, h5 = H[o], H[o + 1], H[o + 2], H[o + 3], H[o + 4], H[o + 5]
            g0 += h0 * rr
            g1 += h1 * rr
            g2 += h2 * rr
            g3 += h3 * rr
            g4 += h4 * rr
            g5 += h5 * rr
            b0, b1, b2, b3, b4 = h0 * w2, h1 * w2, h2 * w2, h3 * w2, h4 * w2
            a00 += b0 * h0
            a01 += b0 * h1
            a02 += b0 * h2
            a03 += b0 * h3
            a04 += b0 * h4
            a05 += b0 * h5
            a11 += b1 * h1
            a12 += b1 * h2
            a13 += b1 * h3
            a14 += b1 * h4
            a15 += b1 * h5
            a22 += b2 * h2
            a23 += b2 * h3
            a24 += b2 * h4
            a25 += b2 * h5
            a33 += b3 * h3
            a34 += b3 * h4
            a35 += b3 * h5
            a44 += b4 * h4
            a45 += b4 * h5
            a55 += h5 * h5 * w2
        g[0], g[1], g[2], g[3], g[4], g[5] = g0, g1, g2, g3, g4, g5
        a[0], a[1], a[2], a[3], a[4], a[5] = a00, a01, a02, a03, a04, a05
        a[6], a[7], a[8], a[9], a[10], a[11] = a01, a11, a12, a13, a14, a15
        a[12], a[13], a[14], a[15], a[16], a[17] = a02, a12, a22, a23, a24, a25
        a[18], a[19], a[20], a[21], a[22], a[23] = a03, a13, a23, a33, a34, a35
        a[24], a[25], a[26], a[27], a[28], a[29] = a04, a14, a24, a34, a44, a45
        a[30], a[31], a[32], a[33], a[34], a[35] = a05, a15, a25, a35, a45, a55
        return cost


class _CompiledLM:
    """The compiled Levenberg-Marquardt's buffers and state (``core/src/lm.c``, run by
    ``ct_solve_run`` through the ``SolveRun`` of :meth:`_CompiledSolver._bind_run`): the
    interface of :class:`pose.lm.LevenbergMarquardt` the solver reads (``state``, ``cost``,
    ``it``, ``lam``, ``A``, ``g``, ``d``) over the arrays the kernel writes, the state in a
    small array (``LM_NST``). Allocated once at start-up."""

    def __init__(self, ext, iters: int):
        self.k = 6
        self.iters = iters
        self._st = np.zeros(ext.LM_NST)
        self._stv = memoryview(self._st)
        self._A = [memoryview(np.zeros(36)), memoryview(np.zeros(36))]
        self._g = [memoryview(np.zeros(6)), memoryview(np.zeros(6))]
        self.d = memoryview(np.zeros(6))

    @property
    def state(self) -> int:
        return int(self._stv[0])

    @property
    def cost(self) -> float:
        return self._stv[1]

    @property
    def lam(self) -> float:
        return self._stv[2]

    @property
    def it(self) -> int:
        return int(self._stv[3])

    @property
    def A(self):
        return self._A[int(self._stv[4])]

    @property
    def g(self):
        return self._g[int(self._stv[4])]


class _CompiledSolver:
    """:class:`PoseSolver`'s compiled core (``core/src/window.c``, ``finish.c``, ``solve.c``): bound
    once by :meth:`_bind_compiled`, which replaces the methods on the instance, so no call tests the
    choice. The Python methods of :class:`PoseSolver` stay the reference; each method here does the
    same operations in the same order (the same results to the bit) or hands inputs of another kind
    to them."""

    def _bind_compiled(self, ext) -> None:
        """Run the solve's bookkeeping on the compiled core (``core/src/window.c``): the inputs'
        copy and checks (``_load``, ``_load_x0``), the results' copies (``_publish``) through a
        ``SolveIO`` bound to the solver's buffers, and a budget's run of the LM's units in one call
        (``ct_solve_run``, :meth:`_bind_run`); the methods are replaced on this instance, so no call tests the
        choice. Inputs the kernels do not take (not float64 arrays of the expected shapes) go to the
        Python; a matrix that is no rotation goes through ``linalg.nearest_rotation``'s compiled
        form (``SolveFinish.nearest``, ``ct_nearest_rotation``)."""
        self._iost = np.zeros(1)
        self._iostv = memoryview(self._iost)
        self._io = ext.SolveIO(self.n, self._S, self._w, self._cur, self._m9, self._fit.p, self._fit.R,
                               self.rotation, self.position, self._iost, ORTHONORMAL_TOL)
        self._load = self._load_compiled
        self._load_x0 = self._load_x0_compiled
        self._publish_pose = self._publish_pose_compiled
        self._run = self._run_compiled
        # the finish (core/src/finish.c): warm-start checks, covariance and rotation margin
        self._fpar = np.zeros(4)                     # check_hemi, the hemisphere (set by begin)
        self._fparv = memoryview(self._fpar)
        self._fwork = np.zeros(ext.FINISH_WORK)
        cx, cy, cz = self._cbar
        self._fin = ext.SolveFinish(self.n, self.gate, cx, cy, cz, self._fpar, self._fit.p, self.covariance,
                                    self._fwork, ORTHONORMAL_TOL)
        self._load_hemisphere = self._load_hemisphere_compiled
        self._unit_finish = self._unit_finish_compiled
        self._bind_run(ext)

    def _bind_run(self, ext) -> None:
        """The warm path in two compiled calls (``core/src/solve.c``): :meth:`begin`'s checks and
        copies (``ct_solve_begin``) and a budget's run of the LM's start, its steps and the finish
        (``ct_solve_run``, :meth:`_unit_run`) through a ``SolveRun`` bound to the fit's, the
        compiled LM's and the results' buffers and its state ``_svst``; the acquisition's units
        run in the same calls (:meth:`_bind_acquire`). A model with a distortion map, or inputs
        the kernel does not take, go the units' way as before (the Python's acquisition, then the
        LM's start :meth:`_unit_lm_start_compiled`)."""
        if ext.SOLVE_NST != _SV_NST or ext.SOLVE_SPENT != _SV_SPENT or ext.SOLVE_EVALS != _SV_EVALS:
            raise RuntimeError("the compiled core's solve state does not match pose.solver's")
        self._svst = np.zeros(_SV_NST)
        self._svv = memoryview(self._svst)
        fit, lm, sig = self._fit, self._lm_c, self.signal
        cx, cy, cz = self._cbar
        lam0, lam_max, iters, cost_tol, step_sigma = self._lm_args
        self._sv = ext.SolveRun(self.n, self.gate, cx, cy, cz, ORTHONORMAL_TOL, lam0, lam_max, iters, cost_tol,
                                step_sigma, fit.step_tol,
                                (sig._geom, sig.B, sig.J, fit.S, fit.w, fit.cur, fit._h, fit._H, fit.p, fit.p_t, fit.R,
                                 fit.R_t, lm._A[0], lm._g[0], lm._A[1], lm._g[1], lm.d, lm._st, self.covariance,
                                 self.rotation, self.position, self._m9, self._fwork, self._svst))
        self._bind_acquire(ext)
        self._unit_c = self._unit_run                 # the compiled units' marker, one bound method (identity)
        self.begin = self._begin_compiled
        self.step = self._step_compiled
        self._unit_lm_start = self._unit_lm_start_compiled
        self.predict_signals = self._predict_signals_compiled

    def _bind_acquire(self, ext) -> None:
        """The acquisition's units in the same compiled run (``core/src/acquire.c``, an
        ``AcquireRun`` attached to the ``SolveRun``): :class:`Acquisition`'s units, charges and
        evaluations, its start written into the fit as :meth:`_unit_acquire` does; the Python's
        :class:`Acquisition` stays the reference and runs where the begin or the LM's start is the
        Python's (a distortion map, inputs of another kind)."""
        fit, sig, acq = self._fit, self.signal, self._acq
        cx, cy, cz = self._cbar
        n = self.n
        self._aqp = np.zeros(3)
        self._aqR = np.zeros(9)
        self._aqwork = np.zeros(ext.ACQUIRE_WORK_FIXED + n * n + 3 * n)
        self._aqst = np.zeros(ext.ACQUIRE_NST)
        self._aqrun = ext.AcquireRun(n, cx, cy, cz, acq.near, MU0_4PI, ORTHONORMAL_TOL,
                                     (sig._geom, sig.B, sig.J, fit.S, fit.cur, acq.grid, self._aqp, self._aqR,
                                      self._aqwork, self._aqst))
        self._sv.attach(self._aqrun)

    def _predict_signals_compiled(self, p, R, currents, out) -> None:
        """:meth:`predict_signals` in one compiled call (the model's fields and projection,
        ``SolveRun.predict``: the same operations, the same bits), ``n`` evaluations counted; a
        model with a distortion map or arrays of another kind: the Python."""
        if self.signal.distortion is None and self._sv.predict(p, R, currents, out):
            self.signal.charge(1)
            return
        StagedSolve.predict_signals(self, p, R, currents, out)

    def _begin_compiled(self, S, currents, sigma, hemisphere=None, x0_position=None, x0_rotation=None) -> int:
        """:meth:`begin` with its checks and copies in one compiled call (``ct_solve_begin``: the
        same decisions, the same bits); a warm solve goes on in :meth:`_unit_run`."""
        st = None
        if self.signal.distortion is None:
            st = self._sv.begin(S, sigma, currents, hemisphere, x0_position, x0_rotation)
        if st is None:
            return PoseSolver.begin(self, S, currents, sigma, hemisphere, x0_position, x0_rotation)
        return self.begun(st, x0_position is not None)

    def begun(self, st: int, warm: bool) -> int:
        """The solver's state after a compiled begin (``ct_solve_begin``, here or in a caller's
        one compiled call: ``core/src/begin.c`` ``ct_solve_start``) that returned ``st``; ``warm``:
        a warm start was given. Returns ``st``."""
        self.status = st
        if st != SOLVE_RUNNING:
            self.next_unit, self.next_cost = None, 0          # (_then, in place: a solve tick's frame fewer)
            return st
        self._reacquired = False
        self.solve_evals = 0
        if warm:
            self._warm = True
            self._lm = self._lm_c
            self.next_unit, self.next_cost = self._unit_c, self.n
        else:
            self._warm = False
            self._sync_from_run()
            if self._svv[_SV_PHASE] == _PH_ACQ_UNITS:      # the compiled acquisition, begun
                self._lm = self._lm_c
                self._then(self._unit_c, self.n)
            else:
                self._start_acquisition()
        return SOLVE_RUNNING

    def _sync_from_run(self) -> None:
        """The compiled begin's hemisphere check and ``sigma`` rms into the attributes the
        acquisition and :meth:`_unit_lm_start_compiled` read."""
        sv = self._svv
        self._sigma_rms = sv[_SV_SIGMA_RMS]
        self._check_hemi = sv[_SV_CHECK_HEMI] != 0.0
        self._hemi = (sv[_SV_HEMI], sv[_SV_HEMI + 1], sv[_SV_HEMI + 2])

    def _unit_lm_start_compiled(self) -> None:
        """:meth:`_unit_lm_start` (after an acquisition, or a begin the kernel did not take): with
        no distortion map, the solve's state into ``_svst`` and the LM's start as the first of the
        compiled units (:meth:`_unit_run`)."""
        if self.signal.distortion is not None:
            PoseSolver._unit_lm_start(self)
            return
        sv = self._svv
        sv[_SV_SIGMA_RMS] = self._sigma_rms           # (a warm start that fails acquires in the run)
        sv[_SV_WARM] = 1.0 if self._warm else 0.0
        sv[_SV_REACQUIRED] = 1.0 if self._reacquired else 0.0
        sv[_SV_CHECK_HEMI] = 1.0 if self._check_hemi else 0.0
        sv[_SV_HEMI], sv[_SV_HEMI + 1], sv[_SV_HEMI + 2] = self._hemi
        sv[_SV_PHASE] = _PH_LM_START
        self._lm = self._lm_c
        self._then(self._unit_c, self.n)
        self._unit_run()

    def _unit_run(self) -> None:
        """One compiled unit (the LM's start, a step or the finish: ``ct_solve_run`` with no
        budget runs exactly one)."""
        self._after_run(self._sv.run(0, 0))

    def _after_run(self, phase: int) -> None:
        """After a compiled run: its evaluations counted; finished, the results; the warm start
        failed its checks, the acquisition begun."""
        sv = self._svv
        self.signal.charge(int(sv[_SV_EVALS]))
        if phase == _PH_NONE:
            self.status = int(sv[_SV_STATUS])
            if not self.status & SOLVE_NO_START:          # (no start: _unit_acquire sets the status only)
                self.iterations = int(sv[_SV_ITERATIONS])
                self.cost = sv[_SV_COST]
                self.converged = sv[_SV_CONVERGED] != 0.0
            self._then(None)
        elif phase == _PH_ACQUIRE:
            self._reacquired = True
            self._sync_from_run()
            self._start_acquisition()

    def _load_compiled(self, S, currents, sigma) -> bool:
        ok = self._io.load(S, sigma, currents)
        if ok is None:
            return StagedSolve._load(self, S, currents, sigma)
        if ok:
            self._sigma_rms = self._iostv[0]
        return ok

    def _load_x0_compiled(self, x0_position, x0_rotation) -> bool:
        if x0_position is None or x0_rotation is None:
            return PoseSolver._load_x0(self, x0_position, x0_rotation)
        self._warm = True
        r = self._io.x0(x0_position, x0_rotation)
        if r is None:
            return PoseSolver._load_x0(self, x0_position, x0_rotation)
        if r == 2 and self._fin.nearest(self._m9, self._fit.R) is None:
            nearest_rotation(self._m9, self._fit.R, self._rot3)
        return r != 0

    def _publish_pose_compiled(self) -> None:
        if not self._io.publish() and self._fin.nearest(self._m9, self.rotation) is None:
            nearest_rotation(self._m9, self.rotation, self._rot3)

    def _load_hemisphere_compiled(self, hemisphere) -> bool:
        """:meth:`_load_hemisphere`, the side also into the compiled finish's parameters."""
        ok = PoseSolver._load_hemisphere(self, hemisphere)
        par = self._fparv
        hx, hy, hz = self._hemi
        par[0], par[1], par[2], par[3] = (1.0 if self._check_hemi else 0.0), hx, hy, hz
        return ok

    def _unit_finish_compiled(self) -> None:
        """:meth:`_unit_finish` with its numbers in one compiled call (``ct_solve_finish``: the
        warm-start checks, ``RobustInverse6``, ``RotationMargin``, the finiteness test), the
        same operations in the same order."""
        lm = self._lm
        r = self._fin.finish(lm.A, self._warm and not self._reacquired, lm.state, lm.cost)
        if r < 0:
            self._reacquired = True
            self._start_acquisition()
            return
        self._publish_pose()
        self.iterations = lm.it
        self.cost = lm.cost
        self.converged = lm.state == LM_CONVERGED
        status = SOLVE_OK if self.converged else SOLVE_NOT_CONVERGED
        if not r:
            status |= SOLVE_NONFINITE
        if self._reacquired:
            status |= SOLVE_REACQUIRED
        self.status = status
        self._then(None)

    def _step_compiled(self, budget_evals: int) -> int:
        """:meth:`StagedSolve.step` in one frame where the next unit is the compiled one (a warm
        solve's LM or finish): the run (``ct_solve_run``), the Python's units after it where the
        warm start failed its checks (:meth:`_run_from`), the charges and the step's counters, in
        the reference's order; other units: the reference's step."""
        if self.next_unit is not self._unit_c:
            return StagedSolve.step(self, budget_evals)
        signal = self.signal
        start = signal.evals
        phase = self._sv.run(0, budget_evals)
        spent = int(self._svv[_SV_SPENT])
        self._after_run(phase)
        if phase == _PH_ACQUIRE:
            spent = self._run_from(spent, budget_evals)
        self.units_last = spent
        used = signal.evals - start
        self.evals_last_step = used
        self.solve_evals += used
        if used > self.max_evals_per_step:
            self.max_evals_per_step = used
        return SOLVE_RUNNING if self.next_unit is not None else self.status

    def _run_compiled(self, budget: int) -> int:
        """:func:`staged.run_units` with the compiled units (:meth:`_unit_run`) run in one call
        (``ct_solve_run``) and the Python LM's steps as units: the same units, charges and
        evaluations."""
        start = self.signal.evals
        self.units_last = self._run_from(0, budget)
        return self.signal.evals - start

    def _run_from(self, spent: int, budget: int) -> int:
        """:meth:`_run_compiled`'s units from ``spent`` charged in this step; the charges after them."""
        unit_c = self._unit_c
        while self.next_unit is not None:
            if self.next_unit is unit_c:
                phase = self._sv.run(spent, budget)
                spent = int(self._svv[_SV_SPENT])
                self._after_run(phase)
                if phase != _PH_NONE and phase != _PH_ACQUIRE:
                    break                # the next unit does not fit
                continue
            cost = self.next_cost
            if spent > 0 and spent + cost > budget:
                break
            self.next_unit()
            spent += cost
        return spent


class PoseSolver(_CompiledSolver, StagedSolve):
    """Preallocated, resumable Kuipers + Levenberg-Marquardt pose solver.

    Parameters
    ----------
    coils : sequence of ``field.Coil``, length n
    model : {"exact", "dipole"}
    iters : int
        LM iteration limit (as ``solve_pose``).
    gate_probability : float
        Probability of the chi-square consistency gate of a warm start
        (a key of ``estimate.ekf.CHI2_QUANTILES``; 1.0 disables the cost test).
    core : coiltrack.firmware.core.Core
        The numeric core, chosen at composition: on the compiled one the signal model, the LM
        step with its cost (on ``_CompiledLM``'s buffers), the begin's checks, a budget's run of the
        acquisition's and the LM's units with the finish and the predicted signals
        (``_CompiledSolver``) run in C, bit-identical to the Python.

    After a solve: ``position`` (3,), ``rotation`` (3, 3), ``covariance``
    (6, 6), ``iterations``, ``cost``, ``converged``, ``status``. Work
    counters, in field evaluations: ``solve_evals`` (the last solve so
    far), ``evals_last_step`` and ``max_evals_per_step`` (the most one
    ``step`` did since :meth:`reset_step_stats`); ``signal.evals`` counts
    every evaluation of the model.
    """

    memoryless = True      # begin resets every part (the LM, the acquisition, the warm-start checks)

    def __init__(self, coils, model: str = "exact", iters: int = 20, gate_probability: float = 0.999,
                 step_tol: float = STEP_TOL, cost_tol: float = COST_TOL, step_sigma: float = 0.0,
                 core=_DEFAULT_CORE):
        self.signal = SignalModel(coils, model, core)
        n = self.signal.n
        self.n = n
        self.model = model
        self.exact = model == "exact"
        self.iters = int(iters)
        self.gate = _gate(n, gate_probability)
        init_results(self)              # position, rotation, covariance, iterations, cost, status
        self._cov = flat(self.covariance)
        # per-solve inputs in the signal layout [3 j + i]
        self._S = np.zeros((n, 3))
        self._w = np.zeros((n, 3))
        self._cur = np.zeros(n)
        self._Sv = flat(self._S)
        self._wv = flat(self._w)
        self._curv = memoryview(self._cur)
        self._pcur = memoryview(np.zeros(n))         # predict_signals' own currents
        self._hp = memoryview(np.zeros(3 * n))
        self._m9 = memoryview(np.zeros(9))
        self._rot3 = Rot3()
        centers = np.array([c.center for c in coils], dtype=float)
        cbar = centers.mean(axis=0)
        self._cbar = tuple(float(v) for v in cbar)
        reach = float(max(c.radius for c in coils)) + float(np.linalg.norm(centers - cbar, axis=1).max())
        self._fit = _PoseFit(self.signal, self._Sv, self._wv, self._curv, step_tol)
        self._lm_args = (1e-6, 1e12, self.iters, cost_tol, step_sigma)
        self._lm_py = LevenbergMarquardt(6, 1e-6, 1e12, self.iters, cost_tol, step_sigma)
        self._lm = self._lm_py
        #: the compiled LM (``core``), or None: used for every fit while the model has no
        #: distortion map (``model.distortion``, added to the field in Python)
        self._lm_c = None
        if self.signal.core == "compiled":
            self._lm_c = _CompiledLM(core.ext, self.iters)
        self._acq = Acquisition(self.signal, self._Sv, self._curv, self._cbar, reach)
        self._unit_lm_steps = self._unit_lm_step      # the LM step unit, one bound method (identity)
        self._inv = RobustInverse6()
        self._margin = RotationMargin()
        self._hemi = (1.0, 0.0, 0.0)
        self._check_hemi = False
        self._sigma_rms = 0.0
        self._warm = False
        self._reacquired = False
        self.solve_evals = 0
        self.evals_last_step = 0
        self.max_evals_per_step = 0
        if self._lm_c is not None:
            self._bind_compiled(core.ext)

    # ------------------------------------------------------------ public
    def solve(self, S, currents, sigma, hemisphere=None, x0_position=None, x0_rotation=None) -> int:
        """``begin`` and ``step`` until done; returns the status flags
        (``SOLVE_OK`` = 0). Arguments as :meth:`begin`."""
        st = self.begin(S, currents, sigma, hemisphere, x0_position, x0_rotation)
        while st == SOLVE_RUNNING:
            st = self.step(_UNBOUNDED)
        return st

    def begin(self, S, currents, sigma, hemisphere=None, x0_position=None, x0_rotation=None) -> int:
        """Start a solve; ``SOLVE_BAD_INPUT`` at once, else ``SOLVE_RUNNING``.

        Parameters
        ----------
        S : ndarray (3, n)
            Signal matrix, T, sensor frame.
        currents : ndarray (n,)
            A, finite.
        sigma : ndarray (3, n)
            Standard deviation of each element of ``S``, T (> 0).
        hemisphere : ndarray (3,), optional
            Kuipers mirror selection (default +x); with ``x0`` the side the
            warm solution must lie on (unchecked if not given).
        x0_position, x0_rotation : ndarray (3,), (3, 3), optional
            Warm start (both or neither, finite).
        """
        self._then(None)
        if not (self._load(S, currents, sigma) and self._load_hemisphere(hemisphere)
                and self._load_x0(x0_position, x0_rotation)):
            self.status = SOLVE_BAD_INPUT
            return SOLVE_BAD_INPUT
        self._reacquired = False
        self.solve_evals = 0
        self.status = SOLVE_RUNNING
        if self._warm:
            self._then(self._unit_lm_start, self.n)
        else:
            self._start_acquisition()
        return SOLVE_RUNNING

    # ------------------------------------------------------------- input
    def _load_hemisphere(self, hemisphere) -> bool:
        self._check_hemi = hemisphere is not None
        if hemisphere is None:
            self._hemi = (1.0, 0.0, 0.0)
            return True
        hx, hy, hz = hemisphere[0], hemisphere[1], hemisphere[2]
        self._hemi = (hx, hy, hz)
        return math.isfinite(hx) and math.isfinite(hy) and math.isfinite(hz)

    def _load_x0(self, x0_position, x0_rotation) -> bool:
        self._warm = x0_position is not None
        if (x0_position is None) != (x0_rotation is None):
            return False
        if x0_position is None:
            return True
        x0_position, x0_rotation = float_view(x0_position), float_view(x0_rotation)
        m9 = self._m9
        for i in range(3):
            for j in range(3):
                m9[3 * i + j] = x0_rotation[i, j]
                if not math.isfinite(m9[3 * i + j]):
                    return False
            if not math.isfinite(x0_position[i]):
                return False
        p = self._fit.p
        p[0], p[1], p[2] = x0_position[0], x0_position[1], x0_position[2]
        nearest_rotation(m9, self._fit.R, self._rot3)
        return True

    # ------------------------------------------------------------- units
    def _start_acquisition(self) -> None:
        hx, hy, hz = self._hemi
        self._acq.begin(hx, hy, hz, self._sigma_rms)
        self._then(self._unit_acquire, self._acq.next_cost)

    def _unit_acquire(self) -> None:
        acq = self._acq
        acq.next_unit()
        if not acq.finished:
            self._then(self._unit_acquire, acq.next_cost)
        elif acq.ok:
            self._fit.set(acq.p, acq.R)
            self._then(self._unit_lm_start, self.n)
        else:
            self.status = SOLVE_NO_START | (SOLVE_REACQUIRED if self._reacquired else 0)
            self._then(None)

    def _unit_lm_start(self) -> None:
        self._lm = self._lm_py          # (the compiled LM runs in the compiled units: _unit_lm_start_compiled)
        self._lm.start(self._fit)
        if self._lm.state == LM_RUNNING:
            self._then(self._unit_lm_steps, self.n)
        else:
            self._then(self._unit_finish, self.n)

    def _unit_lm_step(self) -> None:
        if self._lm.iterate() != LM_RUNNING:
            self._then(self._unit_finish, self.n)

    def _unit_finish(self) -> None:
        """The warm-start checks, then the results and covariance (no field
        evaluation; charged ``n`` for its run time)."""
        if self._warm and not self._reacquired and self._warm_start_failed():
            self._reacquired = True
            self._start_acquisition()
            return
        self._publish()
        self._then(None)

    def _warm_start_failed(self) -> bool:
        """Not converged, inconsistent cost, or on the wrong side."""
        if self.n < 3:
            return False                       # no acquisition to fall back to
        lm = self._lm
        if lm.state != LM_CONVERGED or not lm.cost <= self.gate:
            return True
        if not self._check_hemi:
            return False
        p = self._fit.p
        hx, hy, hz = self._hemi
        dx, dy, dz = p[0] - self._cbar[0], p[1] - self._cbar[1], p[2] - self._cbar[2]
        lim = _HEMI_MARGIN * math.sqrt((dx * dx + dy * dy + dz * dz) * (hx * hx + hy * hy + hz * hz))
        return dx * hx + dy * hy + dz * hz < -lim

    def _publish_pose(self) -> None:
        """The fit's pose into the results: the rotation re-orthonormalised, the position."""
        m9 = self._m9
        R = self._fit.R
        for i in range(3):
            for j in range(3):
                m9[3 * i + j] = R[i, j]
        nearest_rotation(m9, self.rotation, self._rot3)
        p = self._fit.p
        pos = self.position
        pos[0], pos[1], pos[2] = p[0], p[1], p[2]

    def _publish(self) -> None:
        """Results of the fit: re-orthonormalised rotation, covariance."""
        fit, lm = self._fit, self._lm
        self._publish_pose()
        p = fit.p
        self._inv.into(lm.A, self._cov)
        self._margin.into(self._cov)
        self.iterations = lm.it
        self.cost = lm.cost
        self.converged = lm.state == LM_CONVERGED
        status = SOLVE_OK if self.converged else SOLVE_NOT_CONVERGED
        if not (math.isfinite(p[0]) and math.isfinite(p[1]) and math.isfinite(p[2])
                and math.isfinite(self._cov[0])):
            status |= SOLVE_NONFINITE
        if self._reacquired:
            status |= SOLVE_REACQUIRED
        self.status = status
