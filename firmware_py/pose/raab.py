"""Raab's iterative tracker (Raab et al. 1979, ``seeds/004_86267342cd7488ce.txt``,
eqs 7-31), with the interface of :class:`coiltrack.firmware.pose.solver.PoseSolver`.

The tracker keeps the sensor's pose as Raab's six coordinates (Fig. 2):
position azimuth ``alpha``, elevation ``beta`` and range ``rho`` about the
source centre, and orientation azimuth ``psi``, elevation ``theta`` and roll
``phi``; with the rotations of Table II,

    ``P = T_beta T_alpha`` (source -> position/tracking frame, eq 4),
    ``A = T_phi T_theta T_psi`` (source -> sensor frame, eqs 6, 29), ``R = A^T``,

so the unit vector to the sensor is ``u = P^T e_x = (cb ca, cb sa, -sb)``
(elevation turns +x towards -z, Table II). The source is Raab's dipole
coupling (eqs 3-6): ``F = (C / rho^3) A Q``, ``Q = P^T S P``,
``S = diag(1, -1/2, -1/2)``, ``C = mu0 / 2 pi`` per unit moment, where ``F``
(3 x 3) is the sensor output for a unit moment along each source axis; the
dipole's field is the one field module's ``model.field.dipole_polar``.

One *update* (one excitation pattern of the paper) does:

1. **Pre-excitation rotation** (eq 7): the excitation states ``f_0 = e_x,
   e_y, e_z`` of the tracking frame are driven as ``f_1 = P^T f_0``; state
   S1 is the equivalent dipole pointed at the estimated sensor. The pulsed
   source here drives its coils one at a time, so by linear superposition
   the rotation is applied to the measured coupling in computation (the
   fixed source-frame pattern of the paper's *Variations*, sec. V):
   ``F = S_meas M^+`` with ``M`` (3, n) the coil moments at the measured
   currents, then ``F E`` with ``E = P^T``.
2. **Post-sensing rotation** (eq 11): ``F_7 = P A^-1 F P^T = P R F P^T``,
   which equals ``(C / rho^3) R`` of eq 16 (linear in the error angles).
3. **Range** (eq 21): the linear combination of the constant terms that
   minimises the noise, ``2 F7xx - F7yy - F7zz = 3 C / rho^3``, equals to
   first order the rotation invariant ``|F|_F = sqrt(3/2) C / rho^3``, which
   holds at any pose error; the invariant is used (it stays valid during
   acquisition, where the diagonal of ``F_7`` can change sign).
4. **Error angles** (eqs 22-26, with ``f_r = F_7 rho^3 / C``):
   ``d_alpha0 = 2/3 (2 fxy - fyx)``, ``d_beta0 = 2/3 (fzx - 2 fxz)``,
   ``d_psi0 = 2 (fxy - fyx)``, ``d_theta0 = 2 (fzx - fxz)``,
   ``d_phi0 = fzy - fyz`` (the two forms of eq 26 averaged).
5. **Frame conversion** (eqs 27-31) and **update by addition**:
   ``d_alpha1 = d_alpha0 / cos beta``, ``d_beta1 = d_beta0``;
   ``[d_phi1 cos theta, d_theta1, d_psi1 - d_phi1 sin theta] = T_psi P^T
   [d_phi0, d_theta0, d_psi0]`` (``T_{psi - alpha} T_{-beta}`` of eq 31).
   Near ``beta = +-90 deg`` (``|cos beta| < POLE_COS``), where eq 27
   divides by zero, the modified conversion rotates the direction itself,
   ``u <- P^T (1, d_alpha0, -d_beta0) / |.|``, and reads ``alpha``,
   ``beta`` back from it; near ``theta = +-90 deg`` likewise the orientation
   is composed, ``R <- exp([P^T d_0]x) R``, and its angles read back.

Large errors (Fig. 8): the magnitudes of the first-order error angles are
wrong but their signs are right, so each angle step is clipped to
``max_step`` rad and the tracker converges over a few updates.

**The 180 degree ambiguity** (footnote 3): the coupling does not change
when ``u -> -u`` (``alpha + 180 deg``, ``beta -> -beta``) with the
orientation kept; the exact loop field of co-centred coils has the same
symmetry. It is resolved by plausibility: without a prior the tracker starts
in the given hemisphere; a tracked pose continues on its own branch; a result
more than ``_HEMI_MARGIN`` beyond the hemisphere plane is mirrored back, and
the status carries ``SOLVE_REACQUIRED``.

**The exact-loop source.** Raab's model is the point dipole. The bench's
coils are finite loops (magpylib), 5.5 cm in radius and as close as 15 cm,
where the dipole is 10 % off. The measured signals are therefore corrected
through the one signal model (``model.signal``) before step 1:
``S_c[:, j] = S[:, j] - R^T (b_j + G_j (p - p_m))`` with ``b_j = B_model,j -
B_raab,j`` the source-frame difference between the exact loop of coil ``j``
and Raab's co-centred dipole (at the centroid of the coil centres) at the
point ``p_m`` of the last evaluation and ``G_j`` its gradient: exact in the
orientation, linear in the position. The fixed point of the updates is then
the pose at which Raab's detection of ``S - h_model`` vanishes, the exact
model's pose to first order. The correction is evaluated again (``n`` field
evaluations) once the estimate has moved more than ``refresh`` x range (the
second-order error of the linear term: 2 % keeps it below a tenth of the
bound at 15 cm) or left the linear term's range. With the correction the
detection's sensitivities are the dipole's, not the loop's, so near the
source the updates would converge only by the ratio of the two (~0.4 per
update at 15 cm); the detected errors are therefore solved through ``K = I +
G D T`` (``pose.raab_correction``, :meth:`LoopCorrection.precondition`: Raab's detection ``G`` of the
correction's own Jacobian ``D``), which restores quadratic convergence and
changes only the rate, not the fixed point, so ``K`` is reused within
``_K_REUSE`` x range of where it was formed (it does not depend on the
sensor's orientation: the rotations of ``D``, ``T`` and ``G`` cancel; it is formed in the tracking frame in
closed form, and taken as ``I`` where the correction's gradient is below ``K_MIN`` of the dipole's). The
same evaluation gives the information of the covariance ``(H^T W H)^-1`` (``pose.covariance``, the
Cramer-Rao bound of the exact model; orientation error ``R_true = R exp([dtheta]x)``, parameter order
``(p, dtheta)`` as ``PoseSolver``). ``correction=False`` leaves the correction out (its effect is
measured in ``docs/raab.md``).

**The cache.** Everything the evaluation gives is kept per ampere and in the
source frame, so it holds across solves, currents and orientations: a warm
start within ``refresh`` x range of the last evaluation begins with an update,
not an evaluation; a sensor at rest is tracked without evaluating the field.
The covariance is formed (one 6x6 inversion) at an evaluation and carried to
each estimate in closed form by the dipole's symmetry (rotation about the
source centre, ``rho^8 / rho^7 / rho^6`` range factors, the estimate's
orientation, the weights' common scale; ``pose.raab_covariance``), and
formed again where that carry would err by more than 2 %.

**Stopping.** Converged when the steps fall below ``step_tol``; an update
that converges only linearly (its step more than ``_LINEAR_RATE`` of the one
before: a residual from motion within the burst or a low signal) also stops
when its position and orientation steps are below ``step_sigma`` of the
smallest standard deviations of the last covariance (``[pose]
raab_step_sigma``); a refresh whose new correction moves the signals by less
than ``step_sigma`` of their noise needs no update after it.

Work: an update evaluates no field (about 150 products of 3 x 3 algebra and
eight sines and cosines) and is charged one field evaluation; an evaluation of
the correction is ``n`` (plus Raab's dipole and its gradient in closed form,
not counted); the covariance and ``K`` evaluate no field (the covariance is
charged ``n``). ``solve_evals`` counts real evaluations, as ``PoseSolver``.
Nothing is allocated after construction (Python floats and preallocated
buffers).

The modules: the arithmetic of one update (steps 1-5) in ``pose.raab_update``
(``Update``: the whole update on this tracker's buffers, Python or, on the
compiled core chosen at construction, ``ct_raab_update`` of
``core/src/raab.c``, the same to the bit);
the exact-loop correction and ``K``, chosen at construction (``correction``),
in ``pose.raab_correction``; the covariance in ``pose.raab_covariance``; here
the tracker's state, its acquisition and plausibility, the units of work and
the published results.
"""


import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.estimate.ekf import chi2_gate
from coiltrack.firmware.linalg import flat
from coiltrack.firmware.model.signal import SignalModel
from coiltrack.firmware.pose.raab_correction import K_MIN, LoopCorrection, NoCorrection
from coiltrack.firmware.pose.raab_covariance import RaabCovariance
from coiltrack.firmware.pose.raab_io import NO_START, OK, RaabIO
from coiltrack.firmware.pose.raab_update import (ACQUIRED, C_RAAB, DA0, DB0, DPHI0, DPSI0, DRHO, DTH0, K_OUT,
                                                 MAX_STEP, POLE_COS, Update, angles_from_pose, coupling,
                                                 error_angles, orientation_update, point, position_update,
                                                 sync_rotation, wrap)
from coiltrack.firmware.pose.solver import (SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_NONFINITE, SOLVE_NOT_CONVERGED,
                                            SOLVE_OK, SOLVE_REACQUIRED, SOLVE_RUNNING)
from coiltrack.firmware.pose.staged import StagedSolve, init_results

__all__ = ["RaabTracker", "error_angles", "position_update", "orientation_update", "angles_from_pose",
           "POLE_COS", "MAX_STEP"]

#: an update whose angle steps are all below this (rad) ends an acquisition (small-angle regime)
_ACQUIRED_STEP = 0.01
#: without the linear term (the pose left its neighbourhood), evaluate again once the steps are below this
_EARLY_REFRESH = 0.03
#: a result beyond the hemisphere plane by more than this sine of its elevation is mirrored back
_HEMI_MARGIN = 0.1
#: a tracking update also converges when its position and orientation steps are below this fraction
#: of the smallest standard deviations of the last covariance (``[pose] raab_step_sigma``)
STEP_SIGMA = 0.05
#: the noise-level stop applies while a step is more than this fraction of the one before (linear rate;
#: with quadratic convergence the next step is below step_tol anyway)
_LINEAR_RATE = 0.1
_UNBOUNDED = 1 << 62


def _gate(n: int, probability: float) -> float:
    dof = 3 * n - 6
    if probability >= 1.0 or dof < 1 or dof > 12:
        return math.inf
    return chi2_gate(dof, probability)


class RaabTracker(StagedSolve):
    """Raab's iterative tracker behind the ``PoseSolver`` interface.

    Parameters
    ----------
    coils : sequence of ``field.Coil``, length n >= 3 (moments spanning 3-D)
    model : {"exact", "dipole"}
        Signal model of the correction and the covariance.
    iters : int
        Updates per measurement with a prior (tracking); 1 is the paper's
        tracker (one update per excitation pattern).
    acquire_iters : int
        Updates per measurement without a prior (acquisition, Fig. 8).
    gate_probability : float
        Chi-square gate of a warm start's residual (1.0: none); a failure
        starts again from the hemisphere (``SOLVE_REACQUIRED``).
    step_tol : float
        Converged when the angle steps are below this (rad) and the range
        step below this x range.
    refresh : float
        Evaluate the correction again when the converged pose is more than
        this x range (or this, in rad, in orientation) from where it was
        evaluated.
    correction : bool
        Apply the exact-model correction (module docstring): the component
        ``corrector`` is ``raab_correction.LoopCorrection`` or ``NoCorrection``.
    start_position, start_euler : optional
        Start of an acquisition (m, source frame; ``(psi, theta, phi)`` rad);
        default: the hemisphere direction at the range of the invariant,
        zero orientation angles.
    hemisphere : (3,)
        The side the sensor is on while the tracker acquires (from an
        acquisition until an update's angle steps fall below
        ``_ACQUIRED_STEP``), whatever hemisphere a warm start passes: a start
        90 deg off is as far from the truth as from its mirror, so continuity
        alone cannot choose; afterwards the hemisphere of ``begin``
        (continuity: the last position) decides.
    step_sigma : float
        A linearly converging update also stops when its position and
        orientation steps are below this fraction of the smallest standard
        deviations of the last covariance (``[pose] raab_step_sigma``;
        0: only ``step_tol``).

    Results as ``PoseSolver``: ``position`` (3,) m, ``rotation`` (3, 3)
    sensor -> source, ``covariance`` (6, 6) of ``(p, dtheta)``,
    ``iterations`` (updates of the last solve), ``cost``, ``converged``,
    ``status`` (``SOLVE_*`` flags), ``solve_evals``, ``evals_last_step``,
    ``max_evals_per_step``; Raab's angles of the estimate in ``angles``
    (alpha, beta, rho, psi, theta, phi).
    """

    def __init__(self, coils, model: str = "exact", iters: int = 20, acquire_iters: int = 60,
                 gate_probability: float = 1.0, step_tol: float = 1e-4, refresh: float = 0.02,
                 correction: bool = True, start_position=None, start_euler=None, max_step: float = MAX_STEP,
                 hemisphere=(1.0, 0.0, 0.0), step_sigma: float = STEP_SIGMA, core=_DEFAULT_CORE):
        self.signal = SignalModel(coils, model, core)
        n = self.signal.n
        self.n = n
        self.model = model
        self.iters = int(iters)
        self.acquire_iters = int(acquire_iters)
        self.gate = _gate(n, gate_probability)
        self.step_tol = float(step_tol)
        self.refresh = float(refresh)
        self.max_step = float(max_step)
        self.step_sigma = float(step_sigma)
        self._start_p = None if start_position is None else tuple(float(v) for v in start_position)
        self._start_e = (0.0, 0.0, 0.0) if start_euler is None else tuple(float(v) for v in start_euler)
        centers = np.array([c.center for c in coils], dtype=float)
        self._cbar = tuple(float(v) for v in centers.mean(axis=0))
        init_results(self)              # position, rotation, covariance, iterations, cost, status
        self._cov = flat(self.covariance)
        self.angles = memoryview(np.zeros(6))
        #: the exact-loop correction (``correction``) or none, chosen here once (``pose.raab_correction``)
        self.corrector = LoopCorrection(n, core) if correction else NoCorrection()
        self._x = memoryview(np.zeros(6))           # alpha, beta, rho, psi, theta, phi
        self._pm = memoryview(np.zeros(3))          # point of the last evaluation
        self._buffers(n)
        #: publishes into ``covariance`` (``pose.raab_covariance``: Python or, on the compiled ``core``,
        #: ``ct_raab_cov_publish`` reading these buffers)
        self._covm = RaabCovariance(n, self._cbar, self.covariance, core,
                                    (self._x, self._Rn, self._wv, self._curv, self._pm, self.signal.Bv,
                                     self.signal.Jv))
        #: one update (eqs 7-31) on these buffers, Python or compiled as ``core`` (``raab_update.Update``)
        self._upd = Update(n, self._x, self._Rn, self._Sv, self._Sc, self._mp, self._F, self._pm, self._cbar,
                           self._curv, self.corrector, self.max_step, _ACQUIRED_STEP, core)
        self._uo = self._upd._o
        #: a solve's inputs into these buffers (``pose.raab_io``: Python or ``ct_raab_io``); its
        #: ``hemi``, ``check_hemi`` and ``warm`` are the last ``begin``'s
        self._in = RaabIO(n, self._cbar, self._Sv, self._wv, self._curv, self._x, self._Rn, self._mpa, self._mom,
                          self._Sc, self._pm, self._upd, (self.position, self.rotation, self.angles), hemisphere,
                          _HEMI_MARGIN, core)
        self._acquiring = False
        self._reacquired = False
        self._limit = 1
        self._mirrored = False
        self._cache_ok = False                       # the correction and the covariance rows hold an evaluation at _pm
        self._last_step = math.inf                   # the previous update's step (its rate)
        self._done_at_refresh = False                # the update before this evaluation had converged
        self._k = 0.0
        self.solve_evals = 0
        self.evals_last_step = 0
        self.max_evals_per_step = 0

    def _buffers(self, n: int) -> None:
        """The preallocated inputs (signal layout ``[3 j + i]``), moments and rotations."""
        self._Sv = memoryview(np.zeros(3 * n))
        self._wn = np.zeros((3 * n, 1))              # 1 / sigma, a column
        self._wv = flat(self._wn)
        self._curv = memoryview(np.zeros(n))
        self._pcur = memoryview(np.zeros(n))
        self._hp = memoryview(np.zeros(3 * n))
        self._one = memoryview(np.ones(n))           # unit currents: the cache is per ampere
        self._Sc = memoryview(np.zeros(3 * n))       # corrected signals at the estimate
        self._mom = memoryview(np.zeros(3 * n))      # coil moments at the currents, [3 j + a]
        self._mpa = memoryview(np.zeros(3 * n))      # coil moments per A, [3 j + a]
        for j in range(n):
            self._mpa[3 * j], self._mpa[3 * j + 1], self._mpa[3 * j + 2] = self.signal.moment_per_amp(j)
        self._mp = memoryview(np.zeros(3 * n))       # M^+ (n, 3), [3 j + c]
        self._F = memoryview(np.zeros(9))            # corrected coupling S_c M^+, row-major
        self._Rn = np.eye(3)                         # estimate's rotation (sensor -> source)
        self._R = memoryview(self._Rn)               # indexed R[i, j] as Python floats

    # ------------------------------------------------------------ public
    def solve(self, S, currents, sigma, hemisphere=None, x0_position=None, x0_rotation=None) -> int:
        """``begin`` and ``step`` until done; returns the status flags."""
        st = self.begin(S, currents, sigma, hemisphere, x0_position, x0_rotation)
        while st == SOLVE_RUNNING:
            st = self.step(_UNBOUNDED)
        return st

    def begin(self, S, currents, sigma, hemisphere=None, x0_position=None, x0_rotation=None) -> int:
        """Start an update from ``x0`` (tracking) or an acquisition; arguments
        as ``PoseSolver.begin`` (``S``, ``sigma`` (3, n) T; ``currents`` (n,)
        A; ``hemisphere`` (3,); ``x0_position`` (3,) m, ``x0_rotation``
        (3, 3)). ``SOLVE_BAD_INPUT`` / ``SOLVE_NO_START`` at once, else
        ``SOLVE_RUNNING``."""
        self._then(None)
        r = self._in.load(S, currents, sigma, hemisphere, x0_position, x0_rotation)    # pose.raab_io
        if r < NO_START:
            self.status = SOLVE_BAD_INPUT
            return SOLVE_BAD_INPUT
        self.solve_evals = 0
        self._reacquired = False
        if r != OK:                                  # the moments do not span 3-D (moment_pseudo_inverse)
            self.status = SOLVE_NO_START
            return SOLVE_NO_START
        self.iterations = 0
        self.converged = False
        self._mirrored = False
        self._last_step = math.inf
        self._done_at_refresh = False
        self.status = SOLVE_RUNNING
        if not self._in.warm:
            self._acquiring = True
            self._start_acquisition()
        else:
            self._limit = self.iters
            if self._cache_ok and not self._moved():
                # the cached evaluation still holds here: the first update evaluates no field
                self.corrector.resume()
                self._then(self._unit_update, 1)
                return SOLVE_RUNNING
        self._then(self._unit_measure, self.n)
        return SOLVE_RUNNING

    def _start_acquisition(self) -> None:
        """Start without a prior: the configured start, or the hemisphere
        direction at the range of the invariant ``|S M^+|_F`` with zero
        orientation angles (Fig. 8 then brings the errors down)."""
        self._limit = self.acquire_iters
        x = self._x
        c = self._cbar
        if self._start_p is not None:
            px, py, pz = self._start_p[0] - c[0], self._start_p[1] - c[1], self._start_p[2] - c[2]
            rho = math.sqrt(px * px + py * py + pz * pz)
        else:
            px, py, pz = self._in.hemi
            rho = 0.0
        rxy = math.hypot(px, py)
        x[0] = math.atan2(py, px) if rxy > 0.0 else 0.0
        x[1] = math.atan2(-pz, rxy)
        x[3], x[4], x[5] = self._start_e
        if rho <= 0.0:
            self._k = coupling(self.n, self._Sv, self._mp, self._F)         # uncorrected: S M^+
            rho = (C_RAAB / self._k) ** (1.0 / 3.0) if self._k > 0.0 else 0.3
        x[2] = rho
        self._sync_rotation()

    # ------------------------------------------------------------- model
    def _sync_rotation(self) -> None:
        """``R = A^T`` of the current angles."""
        sync_rotation(self._x, self._R)

    def _point(self):
        return point(self._x, self._cbar)

    def _coupling(self) -> None:
        """The signals corrected at the estimate (``S_c``, by the correction
        chosen at construction: ``pose.raab_correction``), then ``F = S_c M^+``
        into ``_F`` and ``k = |F|_F / sqrt(3/2)`` (= ``C / rho^3``, eq 21):
        ``raab_update.Update.couple`` (Python or compiled)."""
        self._k = self._upd.couple()

    # ------------------------------------------------------------- units
    def _unit_measure(self) -> None:
        """The exact model's source-frame fields and gradients per ampere at the
        estimate (``n`` evaluations, ``model.signal.fields``), kept until the
        estimate moves ``refresh`` x range away: the rows ``[J_j | [B_j]x]`` of
        the information (``pose.raab_covariance``) and the correction ``b_j =
        B_model - B_raab`` with its gradient, per ampere (Raab's dipole in
        closed form: no field evaluation), then ``K``."""
        px, py, pz = self._point()
        sig, corr = self.signal, self.corrector
        sig.fields(px, py, pz, self._one, True)
        pm = self._pm
        ddx, ddy, ddz = px - pm[0], py - pm[1], pz - pm[2]
        shift_ok = self._cache_ok and corr.refreshes
        if not corr.lin:
            ddx = ddy = ddz = 0.0                    # the updates used the correction without its linear term
        pm[0], pm[1], pm[2] = px, py, pz
        corr.drop_linear()
        self._cache_ok = True
        self._last_step = math.inf
        self._covm.rows(sig.Bv, sig.Jv)
        shift = corr.refresh(sig.Bv, sig.Jv, self._x, self._mpa, self._wv, self._curv, (ddx, ddy, ddz), shift_ok)
        self._coupling()
        corr.prepare((px, py, pz), self._x, self._mp, self._curv, self._k)
        if self._done_at_refresh and shift_ok and shift <= self.step_sigma * self.step_sigma:
            # converged, and the fresh correction moves the signals by less than step_sigma of their noise
            # (the estimate then by less than step_sigma standard deviations): no update for it
            self.converged = True
            self._then(self._unit_finish, self.n)
            return
        self._then(self._unit_update, 1)

    def _unit_update(self) -> None:
        """One update of eqs 7-31 (no field evaluation, charged 1): the
        detection (``raab_update.detect``), solved through ``K`` by the
        correction, clipped to ``max_step`` (Fig. 8), converted and added
        (eqs 27-31) by ``raab_update.Update`` (Python or compiled), then the
        stop (:meth:`_after_update`)."""
        x, o = self._x, self._uo
        ok = self._upd.run()
        self._k = o[K_OUT]
        if not ok:
            self._finish(SOLVE_NONFINITE)
            return
        if o[ACQUIRED]:
            self._acquiring = False
        da0, db0, drho, dpsi0, dth0, dphi0 = o[DA0], o[DB0], o[DRHO], o[DPSI0], o[DTH0], o[DPHI0]
        rho, psi = x[2], x[3]
        self.iterations += 1
        step = max(abs(da0), abs(db0), abs(dpsi0), abs(dth0), abs(dphi0), abs(drho) / rho)
        small = step <= self.step_tol
        sig_p, sig_o = self._covm.sig_p, self._covm.sig_o
        if not small and not self._acquiring and sig_p > 0.0 and step > _LINEAR_RATE * self._last_step:
            # converging linearly (a residual: motion within the burst, low signal): stop at noise level, the
            # steps below step_sigma of the smallest standard deviations (what remains is about one step)
            ks = self.step_sigma
            small = (rho * rho * (da0 * da0 + db0 * db0) + drho * drho <= (ks * sig_p) ** 2
                     and dpsi0 * dpsi0 + dth0 * dth0 + dphi0 * dphi0 <= (ks * sig_o) ** 2)
        self._last_step = step
        self._after_update(step, small, rho, psi)

    def _after_update(self, step: float, small: bool, rho: float, psi: float) -> None:
        """The next unit after an update of size ``step`` (``small``: converged):
        the correction again where the estimate moved past the refresh, the
        finish, or another update."""
        x, corr = self._x, self.corrector
        if not (math.isfinite(rho) and math.isfinite(psi) and math.isfinite(x[0])):
            self._finish(SOLVE_NONFINITE)
        elif (small or step < 0.5 * self.refresh or (not corr.lin and step < _EARLY_REFRESH and corr.rel >= K_MIN)) \
                and corr.refreshes and self._moved() and self.iterations < self._limit:
            # moved past the refresh and what remains of the steps (about the last one) is within half of it
            self._done_at_refresh = small and not self._acquiring
            self._then(self._unit_measure, self.n)          # the correction again, where the pose now is
        elif small:
            self.converged = True
            self._then(self._unit_finish, self.n)
        elif self.iterations >= self._limit:
            self.converged = False
            self._then(self._unit_finish, self.n)
        else:
            self._then(self._unit_update, 1)

    def _moved(self) -> bool:
        """The estimate is more than ``refresh`` x range from the last evaluation
        (the correction is exact in the orientation, and the covariance is
        carried to the estimate's orientation: only the position counts)."""
        return self._in.moved(self.refresh)                 # pose.raab_io

    def _unit_finish(self) -> None:
        """Plausibility (hemisphere), the gate, the covariance (charged ``n``)."""
        x = self._x
        warm = self._in.warm
        if (self._in.check_hemi or self._acquiring or not warm) and not self._mirrored \
                and self._in.behind(self._acquiring):
            # footnote 3: the same coupling at -u with the same orientation; evaluated there again
            x[0], x[1] = wrap(x[0] + math.pi), -x[1]
            self._mirrored = True
            self._limit = self.iterations + 2
            self._sync_rotation()
            self._done_at_refresh = False
            self._then(self._unit_measure, self.n)
            return
        cost = 0.0
        if self.gate < math.inf and warm and not self._reacquired:
            cost = self._residual_cost()
            if not cost <= self.gate:
                self._reacquired = True
                self._start_acquisition()
                self.iterations = 0
                self._done_at_refresh = False
                self._then(self._unit_measure, self.n)
                return
        self.cost = cost
        self._covm.publish(x, self._R, self._wv, self._curv, self._pm, self.corrector.rel, self._point())
        status = SOLVE_OK if self.converged else SOLVE_NOT_CONVERGED
        if self._mirrored or self._reacquired:
            status |= SOLVE_REACQUIRED
        self._finish(status)

    def _residual_cost(self) -> float:
        """The residual against the exact model at the estimate
        (``raab_update.residual_cost`` of the corrected signals)."""
        self._coupling()
        return self._in.residual_cost()

    def _finish(self, status: int) -> None:
        """The published results: ``position``, ``rotation``, ``angles`` of the
        estimate and ``status`` (the covariance is published by
        ``pose.raab_covariance``)."""
        if not self._in.finish_pose():                # pose.raab_io: position, rotation, angles
            status |= SOLVE_NONFINITE
        self.status = status
        self._then(None)
