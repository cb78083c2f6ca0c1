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
(3 x 3) is the sensor output for a unit moment along each source axis.

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
G D T`` (:meth:`RaabTracker._precondition`: Raab's detection ``G`` of the
correction's own Jacobian ``D``), which restores quadratic convergence and
changes only the rate, not the fixed point, so ``K`` is reused within
``_K_REUSE`` x range of where it was formed (it does not depend on the
sensor's orientation: the rotations of ``D``, ``T`` and ``G`` cancel). The same evaluation gives the Jacobian
of the covariance ``(H^T W H)^-1`` (``pose.covariance``, the Cramer-Rao bound
of the exact model; orientation error ``R_true = R exp([dtheta]x)``,
parameter order ``(p, dtheta)`` as ``PoseSolver``). ``correction=False``
leaves it out (its effect is measured in ``docs/raab.md``).

Work: an update evaluates no field (about 200 flops of 3 x 3 algebra and
five sines and cosines) and is charged one field evaluation; an evaluation of
the correction is ``n`` (plus Raab's dipole and its gradient in closed form,
not counted); the covariance and ``K`` evaluate no field (the covariance is
charged ``n``). ``solve_evals`` counts real evaluations, as ``PoseSolver``.
Nothing is allocated after construction (Python floats and preallocated
buffers).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.estimate.ekf import chi2_gate
from coiltrack.firmware.linalg import Rot3, atb3, flat, inv3_sym, lu_factor, lu_solve, nearest_rotation
from coiltrack.firmware.model.field import MU0
from coiltrack.firmware.model.signal import SignalModel
from coiltrack.firmware.pose.covariance import RobustInverse6
from coiltrack.firmware.pose.solver import (SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_NONFINITE, SOLVE_NOT_CONVERGED,
                                            SOLVE_OK, SOLVE_REACQUIRED, SOLVE_RUNNING)
from coiltrack.firmware.pose.staged import StagedSolve

__all__ = ["RaabTracker", "error_angles", "position_update", "orientation_update", "angles_from_pose",
           "POLE_COS", "MAX_STEP"]

#: C of eq 3 per unit moment (T m^3 / A m^2): F = (C / rho^3) A Q
C_RAAB = MU0 / (2.0 * math.pi)
_SQRT15 = math.sqrt(1.5)
#: below this |cos beta| (|cos theta|) the modified conversion (composition) replaces eq 27 (eq 31)
POLE_COS = 0.2
#: largest angle step of one update (rad): the signs of large errors are right, not their sizes (Fig. 8)
MAX_STEP = 0.5
#: an update whose angle steps are all below this (rad) ends an acquisition (small-angle regime)
_ACQUIRED_STEP = 0.01
#: the preconditioner K sets only the rate, not the fixed point: it is reused within this x range (rad)
_K_REUSE = 0.15
#: without the linear term (the pose left its neighbourhood), evaluate again once the steps are below this
_EARLY_REFRESH = 0.03
#: the preconditioner is applied to detected steps below this (rad, x range): the linear regime
_LIN_STEP = 0.05
#: the correction's linear term is used within this fraction of the range (rad) of its evaluation
_LIN_MAX = 0.1
#: a result beyond the hemisphere plane by more than this sine of its elevation is mirrored back
_HEMI_MARGIN = 0.1
_UNBOUNDED = 1 << 62
_TWO_PI = 2.0 * math.pi


def _wrap(a: float) -> float:
    """Angle into (-pi, pi]."""
    a = math.fmod(a, _TWO_PI)
    if a > math.pi:
        a -= _TWO_PI
    elif a <= -math.pi:
        a += _TWO_PI
    return a


def _clip(x: float, m: float) -> float:
    return m if x > m else (-m if x < -m else x)


def error_angles(F7, k: float):
    """Eqs 22-26: tracking-frame error angles from the post-sensed coupling
    ``F7`` (9, row-major; ``F7[3 i + c]`` = component ``i`` of excitation
    state ``c``) normalised by ``k = C / rho^3``; returns ``(d_alpha0,
    d_beta0, d_psi0, d_theta0, d_phi0)`` in rad."""
    inv = 1.0 / k
    fxy, fyx = F7[1] * inv, F7[3] * inv
    fxz, fzx = F7[2] * inv, F7[6] * inv
    fyz, fzy = F7[5] * inv, F7[7] * inv
    return ((2.0 / 3.0) * (2.0 * fxy - fyx), (2.0 / 3.0) * (fzx - 2.0 * fxz),
            2.0 * (fxy - fyx), 2.0 * (fzx - fxz), fzy - fyz)


def position_update(alpha: float, beta: float, da0: float, db0: float):
    """Eqs 27-28 and the update by addition: the new ``(alpha, beta)`` from
    the tracking-frame errors ``(d_alpha0, d_beta0)``. Near the pole
    (``|cos beta| < POLE_COS``) the modified conversion: the direction
    ``P^T (1, d_alpha0, -d_beta0)`` normalised, its angles read back."""
    cb = math.cos(beta)
    if abs(cb) >= POLE_COS:
        a, b = alpha + da0 / cb, beta + db0                     # eqs 27, 28
        if b > 0.5 * math.pi:                                   # over the pole: the same point
            b, a = math.pi - b, a + math.pi
        elif b < -0.5 * math.pi:
            b, a = -math.pi - b, a + math.pi
        return _wrap(a), b
    ca, sa, sb = math.cos(alpha), math.sin(alpha), math.sin(beta)
    # u = P^T v, v = (1, da0, -db0); P rows: (cb ca, cb sa, -sb), (-sa, ca, 0), (sb ca, sb sa, cb)
    v0, v1, v2 = 1.0, da0, -db0
    ux = cb * ca * v0 - sa * v1 + sb * ca * v2
    uy = cb * sa * v0 + ca * v1 + sb * sa * v2
    uz = -sb * v0 + cb * v2
    nrm = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / nrm, uy / nrm, uz / nrm
    rxy = math.hypot(ux, uy)
    a = math.atan2(uy, ux) if rxy > 1e-12 else alpha
    return a, math.atan2(-uz, rxy)


def _dcm(psi: float, theta: float, phi: float):
    """``A = T_phi T_theta T_psi`` (Table II), row-major 9-tuple."""
    cs, ss = math.cos(psi), math.sin(psi)
    ct, st = math.cos(theta), math.sin(theta)
    cf, sf = math.cos(phi), math.sin(phi)
    return (ct * cs, ct * ss, -st,
            sf * st * cs - cf * ss, sf * st * ss + cf * cs, sf * ct,
            cf * st * cs + sf * ss, cf * st * ss - sf * cs, cf * ct)


def _euler(a):
    """``(psi, theta, phi)`` of ``A = T_phi T_theta T_psi`` (9, row-major)."""
    s = -a[2]
    s = 1.0 if s > 1.0 else (-1.0 if s < -1.0 else s)
    return math.atan2(a[1], a[0]), math.asin(s), math.atan2(a[5], a[8])


def orientation_update(alpha, beta, psi, theta, phi, dphi0, dtheta0, dpsi0):
    """Eqs 29-31 and the update by addition: the new ``(psi, theta, phi)``
    from the tracking-frame errors. ``v = T_psi P^T d_0`` (eq 31's
    ``T_{psi-alpha} T_{-beta}``), then ``d_theta1 = v_y``,
    ``d_phi1 = v_x / cos theta``, ``d_psi1 = v_z + d_phi1 sin theta``. Near
    ``theta = +-90 deg`` (``|cos theta| < POLE_COS``) the orientation is
    composed instead, ``A <- A (I - [w]x)`` exactly as ``A exp(-[w]x)`` with
    ``w = P^T d_0``, and its angles read back."""
    ca, sa, cb, sb = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
    d0, d1, d2 = dphi0, dtheta0, dpsi0
    # w = P^T d (source frame)
    wx = cb * ca * d0 - sa * d1 + sb * ca * d2
    wy = cb * sa * d0 + ca * d1 + sb * sa * d2
    wz = -sb * d0 + cb * d2
    ct = math.cos(theta)
    if abs(ct) >= POLE_COS:
        cs, ss = math.cos(psi), math.sin(psi)
        vx = cs * wx + ss * wy                                   # T_psi w
        vy = -ss * wx + cs * wy
        vz = wz
        dphi1 = vx / ct
        return _wrap(psi + vz + dphi1 * math.sin(theta)), theta + vy, _wrap(phi + dphi1)
    A = _dcm(psi, theta, phi)
    # A exp(-[w]x) = A E^T with E = exp([w]x) (Rodrigues)
    t2 = wx * wx + wy * wy + wz * wz
    if t2 < 1e-12:
        f, g = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = math.sqrt(t2)
        f, g = math.sin(t) / t, (1.0 - math.cos(t)) / t2
    e00, e11, e22 = 1.0 - g * (wy * wy + wz * wz), 1.0 - g * (wx * wx + wz * wz), 1.0 - g * (wx * wx + wy * wy)
    e01, e10 = g * wx * wy - f * wz, g * wx * wy + f * wz
    e02, e20 = g * wx * wz + f * wy, g * wx * wz - f * wy
    e12, e21 = g * wy * wz - f * wx, g * wy * wz + f * wx
    n = [0.0] * 9
    for i in range(3):
        a0, a1, a2 = A[3 * i], A[3 * i + 1], A[3 * i + 2]
        n[3 * i] = a0 * e00 + a1 * e01 + a2 * e02
        n[3 * i + 1] = a0 * e10 + a1 * e11 + a2 * e12
        n[3 * i + 2] = a0 * e20 + a1 * e21 + a2 * e22
    return _euler(n)


def angles_from_pose(px: float, py: float, pz: float, R):
    """Raab's ``(alpha, beta, rho, psi, theta, phi)`` of a sensor at ``p`` (m,
    from the source centre) with orientation ``R`` (sensor -> source, (3, 3)
    indexable ``R[i, j]``)."""
    rho = math.sqrt(px * px + py * py + pz * pz)
    rxy = math.hypot(px, py)
    alpha = math.atan2(py, px) if rxy > 0.0 else 0.0
    beta = math.atan2(-pz, rxy)
    # A = R^T: A[i][j] = R[j, i]
    a = (R[0, 0], R[1, 0], R[2, 0], R[0, 1], R[1, 1], R[2, 1], R[0, 2], R[1, 2], R[2, 2])
    psi, theta, phi = _euler(a)
    return alpha, beta, rho, psi, theta, phi


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
        Apply the exact-model correction (module docstring).
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
                 hemisphere=(1.0, 0.0, 0.0)):
        self.signal = SignalModel(coils, model)
        n = self.signal.n
        self.n = n
        self.model = model
        self.iters = int(iters)
        self.acquire_iters = int(acquire_iters)
        self.gate = _gate(n, gate_probability)
        self.step_tol = float(step_tol)
        self.refresh = float(refresh)
        self.correction = bool(correction)
        self.max_step = float(max_step)
        self._start_p = None if start_position is None else tuple(float(v) for v in start_position)
        self._start_e = (0.0, 0.0, 0.0) if start_euler is None else tuple(float(v) for v in start_euler)
        centers = np.array([c.center for c in coils], dtype=float)
        self._cbar = tuple(float(v) for v in centers.mean(axis=0))
        # results
        self.position = np.zeros(3)
        self.rotation = np.eye(3)
        self.covariance = np.zeros((6, 6))
        self._cov = flat(self.covariance)
        self.iterations = 0
        self.cost = 0.0
        self.converged = False
        self.status = SOLVE_OK
        self.angles = memoryview(np.zeros(6))
        # inputs, signal layout [3 j + i]
        self._Sv = memoryview(np.zeros(3 * n))
        self._wn = np.zeros((3 * n, 1))              # 1 / sigma, a column for the covariance
        self._wv = flat(self._wn)
        self._curv = memoryview(np.zeros(n))
        self._pcur = memoryview(np.zeros(n))
        self._hp = memoryview(np.zeros(3 * n))
        self._h = memoryview(np.zeros(3 * n))
        self._Hn = np.zeros((3 * n, 6))              # exact-model Jacobian at the last evaluation
        self._H = flat(self._Hn)
        self._HWn = np.zeros((3 * n, 6))
        self._HWt = self._HWn.T
        self._An = np.zeros((6, 6))
        self._b = memoryview(np.zeros(3 * n))        # correction B_model - B_raab (source frame), [3 j + i]
        self._G = memoryview(np.zeros(9 * n))        # its gradient d/dp, [9 j + 3 r + c]
        self._Sc = memoryview(np.zeros(3 * n))       # corrected signals at the estimate
        self._pm = [0.0] * 3                         # point of the last evaluation
        self._Rm = np.eye(3)                         # rotation of the last evaluation
        self._mom = memoryview(np.zeros(3 * n))      # coil moments at the currents, [3 j + a]
        self._mp = memoryview(np.zeros(3 * n))       # M^+ (n, 3), [3 j + c]
        self._F = memoryview(np.zeros(9))            # corrected coupling S_c M^+, row-major
        self._A36 = flat(self._An)
        self._R = np.eye(3)                          # estimate's rotation (sensor -> source)
        self._m9 = memoryview(np.zeros(9))
        self._rot3 = Rot3()
        self._inv = RobustInverse6()
        self._x = [0.0] * 6                          # alpha, beta, rho, psi, theta, phi
        self._xm = [0.0] * 6                         # where the correction was evaluated
        self._hemi = (1.0, 0.0, 0.0)
        self._acq_hemi = tuple(float(v) for v in hemisphere)
        self._acquiring = False
        self._check_hemi = False
        self._warm = False
        self._reacquired = False
        self._limit = 1
        self._mirrored = False
        self._g = [0.0] * 9                          # scratch of an update
        self._t = [0.0] * 9
        self._v = [0.0] * (3 * n)                    # scratch of the preconditioner
        self._Fc = [0.0] * 9
        self._K = [0.0] * 36                         # K = I + G D T, LU factors
        self._perm = [0] * 6
        self._e = [0.0] * 6
        self._y = [0.0] * 6
        self._lin = False                            # the correction's linear term (and K) in use
        self._k_ok = False                           # K factored, at _pk (K does not depend on R: R G D T
        self._pk = [0.0] * 3                         #   has the sensor rotation cancelled)
        self._k = 0.0
        self.solve_evals = 0
        self.evals_last_step = 0
        self.max_evals_per_step = 0

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
        if not (self._load(S, currents, sigma) and self._load_hemisphere(hemisphere)
                and self._load_x0(x0_position, x0_rotation)):
            self.status = SOLVE_BAD_INPUT
            return SOLVE_BAD_INPUT
        self.solve_evals = 0
        self._reacquired = False
        if not self._moments():
            self.status = SOLVE_NO_START
            return SOLVE_NO_START
        self.iterations = 0
        self.converged = False
        self._mirrored = False
        self.status = SOLVE_RUNNING
        if not self._warm:
            self._acquiring = True
            self._start_acquisition()
        else:
            self._limit = self.iters
        self._then(self._unit_measure, self.n)
        return SOLVE_RUNNING

    # ------------------------------------------------------------- input
    def _load_hemisphere(self, hemisphere) -> bool:
        self._check_hemi = hemisphere is not None
        if hemisphere is None:
            self._hemi = (1.0, 0.0, 0.0)
            return True
        hx, hy, hz = hemisphere[0], hemisphere[1], hemisphere[2]
        self._hemi = (hx, hy, hz)
        return math.isfinite(hx) and math.isfinite(hy) and math.isfinite(hz) and (hx * hx + hy * hy + hz * hz) > 0.0

    def _load_x0(self, x0_position, x0_rotation) -> bool:
        self._warm = x0_position is not None
        if (x0_position is None) != (x0_rotation is None):
            return False
        if x0_position is None:
            return True
        m9 = self._m9
        for i in range(3):
            if not math.isfinite(x0_position[i]):
                return False
            for j in range(3):
                m9[3 * i + j] = x0_rotation[i, j]
                if not math.isfinite(m9[3 * i + j]):
                    return False
        nearest_rotation(m9, self._R, self._rot3)
        c = self._cbar
        px, py, pz = x0_position[0] - c[0], x0_position[1] - c[1], x0_position[2] - c[2]
        if px * px + py * py + pz * pz <= 0.0:
            return False
        x = self._x
        x[0], x[1], x[2], x[3], x[4], x[5] = angles_from_pose(px, py, pz, self._R)
        return True

    def _moments(self) -> bool:
        """``M`` at the currents and ``M^+ = M^T (M M^T)^-1``; False if the
        moments do not span 3-D."""
        n, mom, mp, cur = self.n, self._mom, self._mp, self._curv
        g00 = g01 = g02 = g11 = g12 = g22 = 0.0
        for j in range(n):
            mx, my, mz = self.signal.moment_per_amp(j)
            c = cur[j]
            mx, my, mz = mx * c, my * c, mz * c
            mom[3 * j], mom[3 * j + 1], mom[3 * j + 2] = mx, my, mz
            g00 += mx * mx
            g01 += mx * my
            g02 += mx * mz
            g11 += my * my
            g12 += my * mz
            g22 += mz * mz
        scale = g00 + g11 + g22
        if not scale > 0.0:
            return False
        a00, a01, a02, a11, a12, a22 = g00 / scale, g01 / scale, g02 / scale, g11 / scale, g12 / scale, g22 / scale
        det = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
        inv = inv3_sym(a00, a01, a02, a11, a12, a22) if det > 1e-12 else None
        if inv is None:
            return False
        i00, i01, i02, i11, i12, i22 = inv[0] / scale, inv[1] / scale, inv[2] / scale, inv[3] / scale, \
            inv[4] / scale, inv[5] / scale
        for j in range(n):
            mx, my, mz = mom[3 * j], mom[3 * j + 1], mom[3 * j + 2]
            mp[3 * j] = mx * i00 + my * i01 + mz * i02
            mp[3 * j + 1] = mx * i01 + my * i11 + mz * i12
            mp[3 * j + 2] = mx * i02 + my * i12 + mz * i22
        return True

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
            px, py, pz = self._hemi
            rho = 0.0
        rxy = math.hypot(px, py)
        x[0] = math.atan2(py, px) if rxy > 0.0 else 0.0
        x[1] = math.atan2(-pz, rxy)
        x[3], x[4], x[5] = self._start_e
        if rho <= 0.0:
            self._coupling(False)
            rho = (C_RAAB / self._k) ** (1.0 / 3.0) if self._k > 0.0 else 0.3
        x[2] = rho
        self._sync_rotation()

    # ------------------------------------------------------------- model
    def _sync_rotation(self) -> None:
        """``R = A^T`` of the current angles."""
        x = self._x
        a = _dcm(x[3], x[4], x[5])
        R = self._R
        R[0, 0], R[0, 1], R[0, 2] = a[0], a[3], a[6]
        R[1, 0], R[1, 1], R[1, 2] = a[1], a[4], a[7]
        R[2, 0], R[2, 1], R[2, 2] = a[2], a[5], a[8]

    def _point(self):
        x, c = self._x, self._cbar
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        r = x[2]
        return c[0] + r * cb * ca, c[1] + r * cb * sa, c[2] - r * sb

    def _coupling(self, corrected: bool) -> None:
        """``F = S_c M^+`` (3 x 3) into ``_F`` and ``k = |F|_F / sqrt(3/2)``
        (= ``C / rho^3``, eq 21). Corrected: ``S_c[:, j] = S[:, j] - R^T (b_j
        + G_j (p - p_m))`` with the source-frame correction ``b_j = B_model -
        B_raab`` of coil ``j`` and its gradient ``G_j`` at the last evaluation
        ``p_m`` (exact in the orientation; the linear term only within
        ``_LIN_MAX`` x range of ``p_m``: during acquisition the pose may be far
        from it). Uncorrected: ``S_c = S``."""
        n, S, Sc, mp, F = self.n, self._Sv, self._Sc, self._mp, self._F
        if corrected:
            px, py, pz = self._point()
            pm, R = self._pm, self._R
            dx, dy, dz = px - pm[0], py - pm[1], pz - pm[2]
            rho = self._x[2]
            if dx * dx + dy * dy + dz * dz > (_LIN_MAX * rho) ** 2:
                dx = dy = dz = 0.0
                self._lin = False
            b, G = self._b, self._G
            for j in range(n):
                o, g = 3 * j, 9 * j
                vx = b[o] + G[g] * dx + G[g + 1] * dy + G[g + 2] * dz
                vy = b[o + 1] + G[g + 3] * dx + G[g + 4] * dy + G[g + 5] * dz
                vz = b[o + 2] + G[g + 6] * dx + G[g + 7] * dy + G[g + 8] * dz
                Sc[o] = S[o] - (R[0, 0] * vx + R[1, 0] * vy + R[2, 0] * vz)
                Sc[o + 1] = S[o + 1] - (R[0, 1] * vx + R[1, 1] * vy + R[2, 1] * vz)
                Sc[o + 2] = S[o + 2] - (R[0, 2] * vx + R[1, 2] * vy + R[2, 2] * vz)
        else:
            for q in range(3 * n):
                Sc[q] = S[q]
        atb3(Sc, mp, n, F)
        ss = 0.0
        for q in range(9):
            ss += F[q] * F[q]
        self._k = math.sqrt(ss) / _SQRT15

    def _raab_field(self, j: int, ux: float, uy: float, uz: float, rho: float, jac: bool):
        """Raab's dipole (eq 5) of coil ``j``'s moment at the coil centroid:
        ``B = (mu0 / 4 pi rho^3)(3 (m.u) u - m)`` (T) and, if ``jac``, the six
        elements ``(xx, yy, zz, xy, xz, yz)`` of ``dB/dp = (mu0 / 4 pi rho^4)
        (3 (u m^T + (m.u) I + m u^T) - 15 (m.u) u u^T)`` (T/m; symmetric)."""
        mom = self._mom
        mx, my, mz = mom[3 * j], mom[3 * j + 1], mom[3 * j + 2]
        kd = 0.5 * C_RAAB / (rho * rho * rho)
        mu = mx * ux + my * uy + mz * uz
        b = (kd * (3.0 * mu * ux - mx), kd * (3.0 * mu * uy - my), kd * (3.0 * mu * uz - mz))
        if not jac:
            return b, None
        kj = kd / rho
        f = 15.0 * mu
        g = (kj * (6.0 * ux * mx + 3.0 * mu - f * ux * ux), kj * (6.0 * uy * my + 3.0 * mu - f * uy * uy),
             kj * (6.0 * uz * mz + 3.0 * mu - f * uz * uz), kj * (3.0 * (ux * my + mx * uy) - f * ux * uy),
             kj * (3.0 * (ux * mz + mx * uz) - f * ux * uz), kj * (3.0 * (uy * mz + my * uz) - f * uy * uz))
        return b, g

    # ------------------------------------------------------------- units
    def _unit_measure(self) -> None:
        """The exact model's signals and Jacobian at the estimate (``n``
        evaluations, ``model.signal``) and the source-frame correction ``b_j =
        B_model - B_raab`` with its gradient (Raab's dipole in closed form,
        :meth:`_raab_field`: no field evaluation)."""
        px, py, pz = self._point()
        cur, h, H, R = self._curv, self._h, self._H, self._R
        sig = self.signal
        sig.measure(px, py, pz, R, cur, h, H)
        self._xm[:] = self._x
        pm = self._pm
        pm[0], pm[1], pm[2] = px, py, pz
        np.copyto(self._Rm, R)
        self._lin = False
        if not self.correction:
            self._then(self._unit_update, 1)
            return
        x = self._x
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        ux, uy, uz = cb * ca, cb * sa, -sb
        b, G, Bv, Jv = self._b, self._G, sig.Bv, sig.Jv
        for j in range(self.n):
            (bx, by, bz), (gxx, gyy, gzz, gxy, gxz, gyz) = self._raab_field(j, ux, uy, uz, x[2], True)
            o, g = 3 * j, 9 * j
            b[o], b[o + 1], b[o + 2] = Bv[o] - bx, Bv[o + 1] - by, Bv[o + 2] - bz
            G[g], G[g + 1], G[g + 2] = Jv[g] - gxx, Jv[g + 1] - gxy, Jv[g + 2] - gxz
            G[g + 3], G[g + 4], G[g + 5] = Jv[g + 3] - gxy, Jv[g + 4] - gyy, Jv[g + 5] - gyz
            G[g + 6], G[g + 7], G[g + 8] = Jv[g + 6] - gxz, Jv[g + 7] - gyz, Jv[g + 8] - gzz
        self._coupling(True)
        if not self._k_ok or self._far(self._pk, None, _K_REUSE):
            self._precondition()
            pk = self._pk
            pk[0], pk[1], pk[2] = px, py, pz
        self._lin = self._k_ok
        self._then(self._unit_update, 1)

    def _post_sense(self, F):
        """Eqs 7 and 11: ``F_7 = P R F P^T`` (9, row-major, into the scratch
        ``_g``) for the coupling ``F`` (9) at the current estimate."""
        x = self._x
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        # P = T_beta T_alpha (eq 4), rows
        p00, p01, p02 = cb * ca, cb * sa, -sb
        p10, p11, p12 = -sa, ca, 0.0
        p20, p21, p22 = sb * ca, sb * sa, cb
        R = self._R
        g, t = self._g, self._t
        # G = R F (source-frame response to a unit source-frame moment)
        for i in range(3):
            r0, r1, r2 = R[i, 0], R[i, 1], R[i, 2]
            for c in range(3):
                g[3 * i + c] = r0 * F[c] + r1 * F[3 + c] + r2 * F[6 + c]
        # pre-excitation E = P^T (eq 7): G P^T; post-sensing P (eq 11): F7 = P G P^T
        for i in range(3):
            g0, g1, g2 = g[3 * i], g[3 * i + 1], g[3 * i + 2]
            t[3 * i] = g0 * p00 + g1 * p01 + g2 * p02
            t[3 * i + 1] = g0 * p10 + g1 * p11 + g2 * p12
            t[3 * i + 2] = g0 * p20 + g1 * p21 + g2 * p22
        for c in range(3):
            t0, t1, t2 = t[c], t[3 + c], t[6 + c]
            g[c] = p00 * t0 + p01 * t1 + p02 * t2
            g[3 + c] = p10 * t0 + p11 * t1 + p12 * t2
            g[6 + c] = p20 * t0 + p21 * t1 + p22 * t2
        return g

    def _precondition(self) -> None:
        """``K = I + G D T`` at the evaluation point and its LU factors:
        ``T`` maps Raab's tracking-frame steps ``(d_alpha0, d_beta0, d_rho,
        d_psi0, d_theta0, d_phi0)`` to ``(dp, dtheta)`` (``dp = rho P^T (0,
        d_alpha0, -d_beta0) + d_rho u``, ``dtheta = R^T P^T (d_phi0,
        d_theta0, d_psi0)``), ``D`` is the correction's Jacobian and ``G``
        the detection (eqs 7, 11, 21-26) of a signal change. With ``S_c = S
        - d - D dx`` the detected errors are ``e = K d`` to first order, so
        solving for ``d`` gives the exact model's step (Raab's own detection is
        ``K = I``, exact for the dipole) and the iteration converges
        quadratically instead of by the ratio of loop to dipole near the source."""
        x, R, mp, n = self._x, self._R, self._mp, self.n
        b, G = self._b, self._G
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        P = ((cb * ca, cb * sa, -sb), (-sa, ca, 0.0), (sb * ca, sb * sa, cb))
        rho, k = x[2], self._k
        v, Fc, K = self._v, self._Fc, self._K
        for c in range(6):
            # column c of T
            if c == 0:
                dp, dt = (rho * P[1][0], rho * P[1][1], rho * P[1][2]), (0.0, 0.0, 0.0)
            elif c == 1:
                dp, dt = (-rho * P[2][0], -rho * P[2][1], -rho * P[2][2]), (0.0, 0.0, 0.0)
            elif c == 2:
                dp, dt = P[0], (0.0, 0.0, 0.0)
            else:
                row = P[2] if c == 3 else (P[1] if c == 4 else P[0])     # d_psi0 z, d_theta0 y, d_phi0 x
                dp = (0.0, 0.0, 0.0)
                dt = (R[0, 0] * row[0] + R[1, 0] * row[1] + R[2, 0] * row[2],
                      R[0, 1] * row[0] + R[1, 1] * row[1] + R[2, 1] * row[2],
                      R[0, 2] * row[0] + R[1, 2] * row[1] + R[2, 2] * row[2])
            # v = D T_c: the signal change R^T (G_j dp) + [R^T b_j]x dt of each coil (as model.signal's H)
            for j in range(n):
                o, g = 3 * j, 9 * j
                wx = G[g] * dp[0] + G[g + 1] * dp[1] + G[g + 2] * dp[2]
                wy = G[g + 3] * dp[0] + G[g + 4] * dp[1] + G[g + 5] * dp[2]
                wz = G[g + 6] * dp[0] + G[g + 7] * dp[1] + G[g + 8] * dp[2]
                hx = R[0, 0] * b[o] + R[1, 0] * b[o + 1] + R[2, 0] * b[o + 2]
                hy = R[0, 1] * b[o] + R[1, 1] * b[o + 1] + R[2, 1] * b[o + 2]
                hz = R[0, 2] * b[o] + R[1, 2] * b[o + 1] + R[2, 2] * b[o + 2]
                v[o] = R[0, 0] * wx + R[1, 0] * wy + R[2, 0] * wz + (hy * dt[2] - hz * dt[1])
                v[o + 1] = R[0, 1] * wx + R[1, 1] * wy + R[2, 1] * wz + (hz * dt[0] - hx * dt[2])
                v[o + 2] = R[0, 2] * wx + R[1, 2] * wy + R[2, 2] * wz + (hx * dt[1] - hy * dt[0])
            atb3(v, mp, n, Fc)
            f7 = self._post_sense(Fc)
            ea, eb, epsi, eth, ephi = error_angles(f7, k)
            erho = -(rho / 3.0) * (2.0 * f7[0] - f7[4] - f7[8]) / (3.0 * k)
            col = (ea, eb, erho, epsi, eth, ephi)
            for r in range(6):
                K[6 * r + c] = col[r] + (1.0 if r == c else 0.0)
        self._k_ok = lu_factor(self._K, 6, self._perm)

    def _unit_update(self) -> None:
        """One update of eqs 7-31 (no field evaluation, charged 1)."""
        x = self._x
        self._coupling(self.correction)
        k = self._k
        if not (k > 0.0 and math.isfinite(k)):
            self._finish(SOLVE_NONFINITE)
            return
        f7 = self._post_sense(self._F)
        da0, db0, dpsi0, dth0, dphi0 = error_angles(f7, k)
        rho = (C_RAAB / k) ** (1.0 / 3.0)                       # eq 21
        drho = rho - x[2]
        if self._lin and max(abs(da0), abs(db0), abs(drho) / x[2], abs(dpsi0), abs(dth0), abs(dphi0)) < _LIN_STEP:
            # the exact model's sensitivities: solve K d = e (K = I + G D T of the last evaluation)
            e = self._e
            e[0], e[1], e[2], e[3], e[4], e[5] = da0, db0, drho, dpsi0, dth0, dphi0
            lu_solve(self._K, 6, self._perm, e, self._y)
            da0, db0, drho, dpsi0, dth0, dphi0 = e[0], e[1], e[2], e[3], e[4], e[5]
            rho = x[2] + drho
        if max(abs(da0), abs(db0), abs(dpsi0), abs(dth0), abs(dphi0)) < _ACQUIRED_STEP:
            self._acquiring = False
        m = self.max_step
        da0, db0, dpsi0, dth0, dphi0 = _clip(da0, m), _clip(db0, m), _clip(dpsi0, m), _clip(dth0, m), _clip(dphi0, m)
        drho = _clip(drho, m * x[2])
        rho = x[2] + drho
        psi, theta, phi = orientation_update(x[0], x[1], x[3], x[4], x[5], dphi0, dth0, dpsi0)
        x[0], x[1] = position_update(x[0], x[1], da0, db0)
        x[2], x[3], x[4], x[5] = rho, psi, theta, phi
        self._sync_rotation()
        self.iterations += 1
        tol = self.step_tol
        step = max(abs(da0), abs(db0), abs(dpsi0), abs(dth0), abs(dphi0), abs(drho) / rho)
        small = step <= tol
        if not (math.isfinite(rho) and math.isfinite(psi) and math.isfinite(x[0])):
            self._finish(SOLVE_NONFINITE)
        elif (small or (not self._lin and step < _EARLY_REFRESH)) and self.correction and self._moved() \
                and self.iterations < self._limit:
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
        """The estimate is more than ``refresh`` (x range; rad) from the last evaluation."""
        return self._far(self._pm, self._Rm, self.refresh)

    def _far(self, pm, Rm, r: float) -> bool:
        """The estimate is more than ``r`` x range from ``pm`` or ``r`` rad from ``Rm`` (unless None)."""
        px, py, pz = self._point()
        R = self._R
        dx, dy, dz = px - pm[0], py - pm[1], pz - pm[2]
        if Rm is None:
            return dx * dx + dy * dy + dz * dz > (r * self._x[2]) ** 2
        c = 0.5 * (Rm[0, 0] * R[0, 0] + Rm[1, 0] * R[1, 0] + Rm[2, 0] * R[2, 0] + Rm[0, 1] * R[0, 1]
                   + Rm[1, 1] * R[1, 1] + Rm[2, 1] * R[2, 1] + Rm[0, 2] * R[0, 2] + Rm[1, 2] * R[1, 2]
                   + Rm[2, 2] * R[2, 2] - 1.0)                   # cos of the rotation angle between them
        return dx * dx + dy * dy + dz * dz > (r * self._x[2]) ** 2 or c < math.cos(r)

    def _unit_finish(self) -> None:
        """Plausibility (hemisphere), the gate, the covariance (charged ``n``)."""
        x = self._x
        hx, hy, hz = self._acq_hemi if self._acquiring else self._hemi
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        ux, uy, uz = cb * ca, cb * sa, -sb
        hn = math.sqrt(hx * hx + hy * hy + hz * hz)
        if (self._check_hemi or self._acquiring or not self._warm) and not self._mirrored \
                and ux * hx + uy * hy + uz * hz < -_HEMI_MARGIN * hn:
            # footnote 3: the same coupling at -u with the same orientation; evaluated there again
            x[0], x[1] = _wrap(x[0] + math.pi), -x[1]
            self._mirrored = True
            self._limit = self.iterations + 2
            self._sync_rotation()
            self._then(self._unit_measure, self.n)
            return
        cost = 0.0
        if self.gate < math.inf and self._warm and not self._reacquired:
            cost = self._residual_cost()
            if not cost <= self.gate:
                self._reacquired = True
                self._start_acquisition()
                self.iterations = 0
                self._then(self._unit_measure, self.n)
                return
        self.cost = cost
        self._covariance()
        status = SOLVE_OK if self.converged else SOLVE_NOT_CONVERGED
        if self._mirrored or self._reacquired:
            status |= SOLVE_REACQUIRED
        self._finish(status)

    def _residual_cost(self) -> float:
        """``sum ((S_c - h_raab(x)) / sigma)^2``: the residual against the
        exact model (``S_c = S - d - D dx``) at the estimate."""
        self._coupling(self.correction)
        x = self._x
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        ux, uy, uz = cb * ca, cb * sa, -sb
        R, Sc, w = self._R, self._Sc, self._wv
        cost = 0.0
        for j in range(self.n):
            (bx, by, bz), _ = self._raab_field(j, ux, uy, uz, x[2], False)
            for i in range(3):
                o = 3 * j + i
                e = (Sc[o] - (R[0, i] * bx + R[1, i] * by + R[2, i] * bz)) * w[o]
                cost += e * e
        return cost

    def _covariance(self) -> None:
        """``(H^T W H)^-1`` with the exact model's ``H`` of the last
        evaluation (``pose.covariance``); two numpy products into
        preallocated buffers."""
        np.multiply(self._Hn, self._wn, out=self._HWn)
        np.matmul(self._HWt, self._HWn, out=self._An)
        self._inv.into(self._A36, self._cov)

    def _finish(self, status: int) -> None:
        x = self._x
        px, py, pz = self._point()
        pos = self.position
        pos[0], pos[1], pos[2] = px, py, pz
        self._sync_rotation()
        np.copyto(self.rotation, self._R)
        ang = self.angles
        for i in range(6):
            ang[i] = x[i]
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            status |= SOLVE_NONFINITE
        self.status = status
        self._then(None)
