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
sensor's orientation: the rotations of ``D``, ``T`` and ``G`` cancel; it is formed in the tracking frame in
closed form, and taken as ``I`` where the correction's gradient is below ``_K_MIN`` of the dipole's). The
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
orientation, the weights' common scale; :meth:`RaabTracker._cov_carry`), and
formed again where that carry would err by more than 2 %.

**Stopping.** Converged when the steps fall below ``step_tol``; an update
that converges only linearly (its step more than ``_LINEAR_RATE`` of the one
before: a residual from motion within the burst or a low signal) also stops
when its position and orientation steps are below ``step_sigma`` of the
smallest standard deviations of the last covariance (``[raab_cost]
raab_step_sigma``); a refresh whose new correction moves the signals by less
than ``step_sigma`` of their noise needs no update after it.

Work: an update evaluates no field (about 150 products of 3 x 3 algebra and
eight sines and cosines) and is charged one field evaluation; an evaluation of
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
from coiltrack.firmware.linalg import Rot3, flat, inv3_sym, lu_factor, lu_solve, nearest_rotation
from coiltrack.firmware.model.field import MU0
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.model.signal import SignalModel
from coiltrack.firmware.pose.covariance import RobustInverse6
from coiltrack.firmware.pose.solver import (SOLVE_BAD_INPUT, SOLVE_NO_START, SOLVE_NONFINITE, SOLVE_NOT_CONVERGED,
                                            SOLVE_OK, SOLVE_REACQUIRED, SOLVE_RUNNING)
from coiltrack.firmware.pose.staged import StagedSolve, init_results

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
#: K is taken as I (not formed) where the correction's gradient is below this fraction of the dipole's
#: (beyond ~55 cm for the thesis source): K - I is of that order, the rate of the updates without it
_K_MIN = 0.02
#: without the linear term (the pose left its neighbourhood), evaluate again once the steps are below this
_EARLY_REFRESH = 0.03
#: the preconditioner is applied to detected steps below this (rad, x range): the linear regime
_LIN_STEP = 0.15
#: the correction's linear term is used within this fraction of the range (rad) of its evaluation
_LIN_MAX = 0.1
#: a result beyond the hemisphere plane by more than this sine of its elevation is mirrored back
_HEMI_MARGIN = 0.1
#: a warm start's rotation closer than this to orthonormal (each element of R^T R - I) is used as it is
_ORTHO_TOL = 1e-9
#: a tracking update also converges when its position and orientation steps are below this fraction
#: of the smallest standard deviations of the last covariance (``[raab_cost] raab_step_sigma``)
STEP_SIGMA = 0.05
#: the noise-level stop applies while a step is more than this fraction of the one before (linear rate;
#: with quadratic convergence the next step is below step_tol anyway)
_LINEAR_RATE = 0.1
#: the covariance formed at one evaluation is carried to later estimates while its error, ~15 rel d / rho,
#: stays below this fraction of sqrt(C_ii C_kk) (then formed again at the newest evaluation) ...
_COV_TOL = 0.02
#: ... and at most this x range
_CARRY_MAX = 0.1
#: the cached covariance is scaled, not formed again, while every coil's weight x current stays within
#: this fraction of the common scale (the variances then err by at most twice this)
_Q_TOL = 0.005
#: the weights of a coil's three axes count as equal (isotropic: the orientation cancels) within this
_ISO_TOL = 1e-3
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


def _mul3(a, b):
    """``a b`` of two 3x3 (9, row-major) as a 9-tuple."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = b
    return (a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
            a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
            a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8)


def _block(c, r: int, k: int):
    """The 3x3 block at row ``r``, column ``k`` of a 6x6 (36, row-major) as a 9-tuple."""
    o = 6 * r + k
    return (c[o], c[o + 1], c[o + 2], c[o + 6], c[o + 7], c[o + 8], c[o + 12], c[o + 13], c[o + 14])


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


def _is_rotation(m) -> bool:
    """``m`` (9, row-major) is orthonormal with determinant +1 to ``_ORTHO_TOL``
    (then it is its own nearest rotation)."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8]
    t = _ORTHO_TOL
    if not (abs(a0 * a0 + a1 * a1 + a2 * a2 - 1.0) < t and abs(a3 * a3 + a4 * a4 + a5 * a5 - 1.0) < t
            and abs(a6 * a6 + a7 * a7 + a8 * a8 - 1.0) < t and abs(a0 * a3 + a1 * a4 + a2 * a5) < t
            and abs(a0 * a6 + a1 * a7 + a2 * a8) < t and abs(a3 * a6 + a4 * a7 + a5 * a8) < t):
        return False
    return a0 * (a4 * a8 - a5 * a7) - a1 * (a3 * a8 - a5 * a6) + a2 * (a3 * a7 - a4 * a6) > 0.0


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
    step_sigma : float
        A linearly converging update also stops when its position and
        orientation steps are below this fraction of the smallest standard
        deviations of the last covariance (``[raab_cost] raab_step_sigma``;
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
        self.correction = bool(correction)
        self.max_step = float(max_step)
        self.step_sigma = float(step_sigma)
        self._start_p = None if start_position is None else tuple(float(v) for v in start_position)
        self._start_e = (0.0, 0.0, 0.0) if start_euler is None else tuple(float(v) for v in start_euler)
        centers = np.array([c.center for c in coils], dtype=float)
        self._cbar = tuple(float(v) for v in centers.mean(axis=0))
        init_results(self)              # position, rotation, covariance, iterations, cost, status
        self._cov = flat(self.covariance)
        self.angles = memoryview(np.zeros(6))
        # inputs, signal layout [3 j + i]
        self._Sv = memoryview(np.zeros(3 * n))
        self._wn = np.zeros((3 * n, 1))              # 1 / sigma, a column for the covariance
        self._wv = flat(self._wn)
        self._curv = memoryview(np.zeros(n))
        self._pcur = memoryview(np.zeros(n))
        self._hp = memoryview(np.zeros(3 * n))
        self._one = memoryview(np.ones(n))           # unit currents: the cache is per ampere
        self._Kn = np.zeros((3 * n, 6))              # [J_j | [B_j]x] per A at the last evaluation (source frame)
        self._Ks = flat(self._Kn)
        self._Hn = np.zeros((3 * n, 6))              # the same in the sensor frame (anisotropic weights)
        self._H = flat(self._Hn)
        self._qn = np.zeros((3 * n, 1))              # weights x currents of the information, a column
        self._qv = flat(self._qn)
        self._qm = [0.0] * n                         # per-coil weight x current of the cached covariance
        self._HWn = np.zeros((3 * n, 6))
        self._HWt = self._HWn.T
        self._An = np.zeros((6, 6))
        self._Cs = memoryview(np.zeros(36))          # covariance at p_m, source-frame orientation error
        self._cs_ok = False                          # _Cs formed at _pc (isotropic weights _qm)
        self._pc = [0.0] * 3                         # where _Cs was formed (an evaluation point)
        self._rel = 1.0                              # the correction's gradient / the dipole's at the evaluation
        self._cache_ok = False                       # _b, _G, _Kn hold an evaluation at _pm
        self._sig_p = 0.0                            # smallest position / orientation std of the last
        self._sig_o = 0.0                            #   published covariance (m, rad): the noise-level stop
        self._b = memoryview(np.zeros(3 * n))        # correction B_model - B_raab per A (source frame), [3 j + i]
        self._G = memoryview(np.zeros(9 * n))        # its gradient d/dp per A, [9 j + 3 r + c]
        self._Sc = memoryview(np.zeros(3 * n))       # corrected signals at the estimate
        self._pm = [0.0] * 3                         # point of the last evaluation
        self._mom = memoryview(np.zeros(3 * n))      # coil moments at the currents, [3 j + a]
        self._mpa = memoryview(np.zeros(3 * n))      # coil moments per A, [3 j + a]
        for j in range(n):
            self._mpa[3 * j], self._mpa[3 * j + 1], self._mpa[3 * j + 2] = self.signal.moment_per_amp(j)
        self._mp = memoryview(np.zeros(3 * n))       # M^+ (n, 3), [3 j + c]
        self._F = memoryview(np.zeros(9))            # corrected coupling S_c M^+, row-major
        self._A36 = flat(self._An)
        self._Rn = np.eye(3)                         # estimate's rotation (sensor -> source)
        self._R = memoryview(self._Rn)               # indexed R[i, j] as Python floats
        self._m9 = memoryview(np.zeros(9))
        self._rot3 = Rot3()
        self._inv = RobustInverse6()
        self._x = [0.0] * 6                          # alpha, beta, rho, psi, theta, phi
        self._hemi = (1.0, 0.0, 0.0)
        self._acq_hemi = tuple(float(v) for v in hemisphere)
        self._acquiring = False
        self._check_hemi = False
        self._warm = False
        self._reacquired = False
        self._limit = 1
        self._mirrored = False
        self._Fk = [0.0] * 54                        # the six detected couplings of K's columns
        self._K = [0.0] * 36                         # K = I + G D T, LU factors
        self._perm = [0] * 6
        self._e = [0.0] * 6
        self._y = [0.0] * 6
        self._lin = False                            # the correction's linear term (and K) in use
        self._last_step = math.inf                   # the previous update's step (its rate)
        self._done_at_refresh = False                # the update before this evaluation had converged
        self._k_id = False                           # K taken as I (the correction's gradient below _K_MIN)
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
        self._last_step = math.inf
        self._done_at_refresh = False
        self.status = SOLVE_RUNNING
        if not self._warm:
            self._acquiring = True
            self._start_acquisition()
        else:
            self._limit = self.iters
            if self._cache_ok and not self._moved():
                # the cached evaluation still holds here: the first update evaluates no field
                self._lin = self._k_ok and self.correction
                self._then(self._unit_update, 1)
                return SOLVE_RUNNING
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
        if _is_rotation(m9):
            R = self._R                              # a rotation already (the tracked pose): its own nearest
            R[0, 0], R[0, 1], R[0, 2] = m9[0], m9[1], m9[2]
            R[1, 0], R[1, 1], R[1, 2] = m9[3], m9[4], m9[5]
            R[2, 0], R[2, 1], R[2, 2] = m9[6], m9[7], m9[8]
        else:
            nearest_rotation(m9, self._Rn, self._rot3)
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
        n, mom, mp, cur, mpa = self.n, self._mom, self._mp, self._curv, self._mpa
        g00 = g01 = g02 = g11 = g12 = g22 = 0.0
        for j in range(n):
            c = cur[j]
            mx, my, mz = mpa[3 * j] * c, mpa[3 * j + 1] * c, mpa[3 * j + 2] * c
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
        f0 = f1 = f2 = f3 = f4 = f5 = f6 = f7 = f8 = 0.0
        if corrected:
            px, py, pz = self._point()
            pm, R = self._pm, self._R
            dx, dy, dz = px - pm[0], py - pm[1], pz - pm[2]
            rho = self._x[2]
            if dx * dx + dy * dy + dz * dz > (_LIN_MAX * rho) ** 2:
                dx = dy = dz = 0.0
                self._lin = False
            b, G, cur = self._b, self._G, self._curv
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2],
                                                           R[2, 0], R[2, 1], R[2, 2])
        for j in range(n):
            o = 3 * j
            if corrected:
                g, c = 9 * j, cur[j]
                vx = (b[o] + G[g] * dx + G[g + 1] * dy + G[g + 2] * dz) * c
                vy = (b[o + 1] + G[g + 3] * dx + G[g + 4] * dy + G[g + 5] * dz) * c
                vz = (b[o + 2] + G[g + 6] * dx + G[g + 7] * dy + G[g + 8] * dz) * c
                s0 = S[o] - (r00 * vx + r10 * vy + r20 * vz)
                s1 = S[o + 1] - (r01 * vx + r11 * vy + r21 * vz)
                s2 = S[o + 2] - (r02 * vx + r12 * vy + r22 * vz)
            else:
                s0, s1, s2 = S[o], S[o + 1], S[o + 2]
            Sc[o], Sc[o + 1], Sc[o + 2] = s0, s1, s2
            m0, m1, m2 = mp[o], mp[o + 1], mp[o + 2]
            # F = S_c M^+ = sum_j s_j (M^+_j)^T
            f0 += s0 * m0
            f1 += s0 * m1
            f2 += s0 * m2
            f3 += s1 * m0
            f4 += s1 * m1
            f5 += s1 * m2
            f6 += s2 * m0
            f7 += s2 * m1
            f8 += s2 * m2
        F[0], F[1], F[2], F[3], F[4], F[5], F[6], F[7], F[8] = f0, f1, f2, f3, f4, f5, f6, f7, f8
        self._k = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2 + f3 * f3 + f4 * f4 + f5 * f5 + f6 * f6 + f7 * f7
                            + f8 * f8) / _SQRT15

    def _raab_field(self, mom, j: int, ux: float, uy: float, uz: float, rho: float, jac: bool):
        """Raab's dipole (eq 5) of coil ``j``'s moment ``mom[3 j:3 j + 3]`` at the coil centroid:
        ``B = (mu0 / 4 pi rho^3)(3 (m.u) u - m)`` (T) and, if ``jac``, the six
        elements ``(xx, yy, zz, xy, xz, yz)`` of ``dB/dp = (mu0 / 4 pi rho^4)
        (3 (u m^T + (m.u) I + m u^T) - 15 (m.u) u u^T)`` (T/m; symmetric)."""
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
        """The exact model's source-frame fields and gradients per ampere at the
        estimate (``n`` evaluations, ``model.signal.fields``), kept until the
        estimate moves ``refresh`` x range away: the rows ``[J_j | [B_j]x]`` of
        the information (:meth:`_covariance`) and the correction ``b_j =
        B_model - B_raab`` with its gradient, per ampere (Raab's dipole in
        closed form, :meth:`_raab_field`: no field evaluation)."""
        px, py, pz = self._point()
        sig = self.signal
        sig.fields(px, py, pz, self._one, True)
        pm = self._pm
        ddx, ddy, ddz = px - pm[0], py - pm[1], pz - pm[2]
        shift_ok = self._cache_ok and self.correction
        if not self._lin:
            ddx = ddy = ddz = 0.0                    # the updates used the correction without its linear term
        pm[0], pm[1], pm[2] = px, py, pz
        self._lin = False
        self._cache_ok = True
        self._rel = 1.0                              # (no correction: the covariance formed at each evaluation)
        self._last_step = math.inf
        b, G, Bv, Jv, K = self._b, self._G, sig.Bv, sig.Jv, self._Ks
        for j in range(self.n):
            o, g, k = 3 * j, 9 * j, 18 * j
            Bx, By, Bz = Bv[o], Bv[o + 1], Bv[o + 2]
            # rows [J_j | [B_j]x] (source frame; orientation error dtheta_s = R dtheta)
            K[k], K[k + 1], K[k + 2], K[k + 3], K[k + 4], K[k + 5] = Jv[g], Jv[g + 1], Jv[g + 2], 0.0, -Bz, By
            K[k + 6], K[k + 7], K[k + 8], K[k + 9], K[k + 10], K[k + 11] = Jv[g + 3], Jv[g + 4], Jv[g + 5], Bz, 0.0, -Bx
            K[k + 12], K[k + 13], K[k + 14], K[k + 15], K[k + 16], K[k + 17] = (Jv[g + 6], Jv[g + 7], Jv[g + 8],
                                                                                 -By, Bx, 0.0)
        if not self.correction:
            self._then(self._unit_update, 1)
            return
        x = self._x
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        ux, uy, uz = cb * ca, cb * sa, -sb
        mpa, w, cur = self._mpa, self._wv, self._curv
        rel = shift = 0.0
        for j in range(self.n):
            (bx, by, bz), (gxx, gyy, gzz, gxy, gxz, gyz) = self._raab_field(mpa, j, ux, uy, uz, x[2], True)
            o, g = 3 * j, 9 * j
            nx, ny, nz = Bv[o] - bx, Bv[o + 1] - by, Bv[o + 2] - bz
            if shift_ok:
                # the new correction against the last one's linear term here, in the noise of coil j's signals
                ex = nx - (b[o] + G[g] * ddx + G[g + 1] * ddy + G[g + 2] * ddz)
                ey = ny - (b[o + 1] + G[g + 3] * ddx + G[g + 4] * ddy + G[g + 5] * ddz)
                ez = nz - (b[o + 2] + G[g + 6] * ddx + G[g + 7] * ddy + G[g + 8] * ddz)
                wm = max(w[o], w[o + 1], w[o + 2]) * cur[j]
                shift += (ex * ex + ey * ey + ez * ez) * wm * wm
            b[o], b[o + 1], b[o + 2] = nx, ny, nz
            G[g], G[g + 1], G[g + 2] = Jv[g] - gxx, Jv[g + 1] - gxy, Jv[g + 2] - gxz
            G[g + 3], G[g + 4], G[g + 5] = Jv[g + 3] - gxy, Jv[g + 4] - gyy, Jv[g + 5] - gyz
            G[g + 6], G[g + 7], G[g + 8] = Jv[g + 6] - gxz, Jv[g + 7] - gyz, Jv[g + 8] - gzz
            gg = 0.0
            for q in range(g, g + 9):
                gg += G[q] * G[q]
            jj = gxx * gxx + gyy * gyy + gzz * gzz + 2.0 * (gxy * gxy + gxz * gxz + gyz * gyz)
            if gg > rel * rel * jj:
                rel = math.sqrt(gg / jj)
        self._rel = rel
        self._coupling(True)
        if rel < _K_MIN:
            self._k_id = True                       # K = I + O(rel): Raab's own detection (no LU)
            self._k_ok = True
        elif self._k_id or not self._k_ok or self._far(self._pk, None, _K_REUSE):
            self._k_id = False
            self._precondition()
            pk = self._pk
            pk[0], pk[1], pk[2] = px, py, pz
        self._lin = self._k_ok
        if self._done_at_refresh and shift_ok and shift <= self.step_sigma * self.step_sigma:
            # converged, and the fresh correction moves the signals by less than step_sigma of their noise
            # (the estimate then by less than step_sigma standard deviations): no update for it
            self.converged = True
            self._then(self._unit_finish, self.n)
            return
        self._then(self._unit_update, 1)

    def _post_sense(self, F):
        """Eqs 7 and 11 in closed form: the six off-diagonal elements ``(xy, yx,
        xz, zx, yz, zy)`` of ``F_7 = P R F P^T`` (all that eqs 22-26 read; the
        range comes from the invariant) for the coupling ``F`` (9, row-major)
        at the current estimate, as ``(P R) (F P^T)``: 45 products."""
        x, R = self._x, self._R
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        # P = T_beta T_alpha (eq 4), rows
        p00, p01, p02 = cb * ca, cb * sa, -sb
        p10, p11 = -sa, ca
        p20, p21, p22 = sb * ca, sb * sa, cb
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2],
                                                       R[2, 0], R[2, 1], R[2, 2])
        # A = P R, rows
        a00, a01, a02 = p00 * r00 + p01 * r10 + p02 * r20, p00 * r01 + p01 * r11 + p02 * r21, \
            p00 * r02 + p01 * r12 + p02 * r22
        a10, a11, a12 = p10 * r00 + p11 * r10, p10 * r01 + p11 * r11, p10 * r02 + p11 * r12
        a20, a21, a22 = p20 * r00 + p21 * r10 + p22 * r20, p20 * r01 + p21 * r11 + p22 * r21, \
            p20 * r02 + p21 * r12 + p22 * r22
        f0, f1, f2, f3, f4, f5, f6, f7, f8 = F[0], F[1], F[2], F[3], F[4], F[5], F[6], F[7], F[8]
        # H = F P^T, column b = F (row b of P)
        h0x, h1x, h2x = f0 * p00 + f1 * p01 + f2 * p02, f3 * p00 + f4 * p01 + f5 * p02, f6 * p00 + f7 * p01 + f8 * p02
        h0y, h1y, h2y = f0 * p10 + f1 * p11, f3 * p10 + f4 * p11, f6 * p10 + f7 * p11
        h0z, h1z, h2z = f0 * p20 + f1 * p21 + f2 * p22, f3 * p20 + f4 * p21 + f5 * p22, f6 * p20 + f7 * p21 + f8 * p22
        return (a00 * h0y + a01 * h1y + a02 * h2y, a10 * h0x + a11 * h1x + a12 * h2x,
                a00 * h0z + a01 * h1z + a02 * h2z, a20 * h0x + a21 * h1x + a22 * h2x,
                a10 * h0z + a11 * h1z + a12 * h2z, a20 * h0y + a21 * h1y + a22 * h2y)

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
        x, mp, n = self._x, self._mp, self.n
        b, G, cur = self._b, self._G, self._curv
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        p00, p01, p02 = cb * ca, cb * sa, -sb
        p10, p11 = -sa, ca
        p20, p21, p22 = sb * ca, sb * sa, cb
        rho, k = x[2], self._k
        # The detected coupling of column c is F7_c = P R (D T_c) M^+ P^T = sum_j y_jc (P m^+_j)^T with, in
        # the tracking frame (Gt_j = P G_j P^T, bt_j = P b_j; R cancels: R [R^T b]x R^T = [b]x):
        # d_alpha0: rho Gt_j e_y, d_beta0: -rho Gt_j e_z, d_rho: Gt_j e_x, d_psi0: bt_j x e_z,
        # d_theta0: bt_j x e_y, d_phi0: bt_j x e_x (each times the current I_j).
        Fk = self._Fk
        for i in range(54):
            Fk[i] = 0.0
        for j in range(n):
            cj, o, g = cur[j], 3 * j, 9 * j
            m0, m1, m2 = mp[o], mp[o + 1], mp[o + 2]
            q0 = p00 * m0 + p01 * m1 + p02 * m2
            q1 = p10 * m0 + p11 * m1
            q2 = p20 * m0 + p21 * m1 + p22 * m2
            bx, by, bz = b[o] * cj, b[o + 1] * cj, b[o + 2] * cj
            t0 = p00 * bx + p01 * by + p02 * bz
            t1 = p10 * bx + p11 * by
            t2 = p20 * bx + p21 * by + p22 * bz
            # G_j P^T e_k = G_j (row k of P), k = x, y, z
            cols = []
            for (e0, e1, e2) in ((p00, p01, p02), (p10, p11, 0.0), (p20, p21, p22)):
                w0 = (G[g] * e0 + G[g + 1] * e1 + G[g + 2] * e2) * cj
                w1 = (G[g + 3] * e0 + G[g + 4] * e1 + G[g + 5] * e2) * cj
                w2 = (G[g + 6] * e0 + G[g + 7] * e1 + G[g + 8] * e2) * cj
                cols.append((p00 * w0 + p01 * w1 + p02 * w2, p10 * w0 + p11 * w1, p20 * w0 + p21 * w1 + p22 * w2))
            gx, gy, gz = cols
            ys = ((rho * gy[0], rho * gy[1], rho * gy[2]), (-rho * gz[0], -rho * gz[1], -rho * gz[2]), gx,
                  (t1, -t0, 0.0), (-t2, 0.0, t0), (0.0, t2, -t1))
            for c in range(6):
                y0, y1, y2 = ys[c]
                f = 9 * c
                Fk[f] += y0 * q0
                Fk[f + 1] += y0 * q1
                Fk[f + 2] += y0 * q2
                Fk[f + 3] += y1 * q0
                Fk[f + 4] += y1 * q1
                Fk[f + 5] += y1 * q2
                Fk[f + 6] += y2 * q0
                Fk[f + 7] += y2 * q1
                Fk[f + 8] += y2 * q2
        K, inv = self._K, 1.0 / k
        for c in range(6):
            f = 9 * c
            fxy, fyx, fxz, fzx, fyz, fzy = (Fk[f + 1] * inv, Fk[f + 3] * inv, Fk[f + 2] * inv, Fk[f + 6] * inv,
                                            Fk[f + 5] * inv, Fk[f + 7] * inv)
            col = ((2.0 / 3.0) * (2.0 * fxy - fyx), (2.0 / 3.0) * (fzx - 2.0 * fxz),
                   -(rho / 9.0) * (2.0 * Fk[f] - Fk[f + 4] - Fk[f + 8]) * inv,
                   2.0 * (fxy - fyx), 2.0 * (fzx - fxz), fzy - fyz)           # eqs 21-26, as error_angles
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
        fxy, fyx, fxz, fzx, fyz, fzy = self._post_sense(self._F)
        inv = 1.0 / k                                           # eqs 22-26 (as error_angles)
        fxy, fyx, fxz, fzx, fyz, fzy = fxy * inv, fyx * inv, fxz * inv, fzx * inv, fyz * inv, fzy * inv
        da0, db0 = (2.0 / 3.0) * (2.0 * fxy - fyx), (2.0 / 3.0) * (fzx - 2.0 * fxz)
        dpsi0, dth0, dphi0 = 2.0 * (fxy - fyx), 2.0 * (fzx - fxz), fzy - fyz
        rho = (C_RAAB / k) ** (1.0 / 3.0)                       # eq 21
        drho = rho - x[2]
        if self._lin and not self._k_id \
                and max(abs(da0), abs(db0), abs(drho) / x[2], abs(dpsi0), abs(dth0), abs(dphi0)) < _LIN_STEP:
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
        if not small and not self._acquiring and self._sig_p > 0.0 and step > _LINEAR_RATE * self._last_step:
            # converging linearly (a residual: motion within the burst, low signal): stop at noise level, the
            # steps below step_sigma of the smallest standard deviations (what remains is about one step)
            ks = self.step_sigma
            small = (rho * rho * (da0 * da0 + db0 * db0) + drho * drho <= (ks * self._sig_p) ** 2
                     and dpsi0 * dpsi0 + dth0 * dth0 + dphi0 * dphi0 <= (ks * self._sig_o) ** 2)
        self._last_step = step
        if not (math.isfinite(rho) and math.isfinite(psi) and math.isfinite(x[0])):
            self._finish(SOLVE_NONFINITE)
        elif (small or step < 0.5 * self.refresh or (not self._lin and step < _EARLY_REFRESH and self._rel >= _K_MIN)) \
                and self.correction and self._moved() and self.iterations < self._limit:
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
        return self._far(self._pm, None, self.refresh)

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
            self._done_at_refresh = False
            self._then(self._unit_measure, self.n)
            return
        cost = 0.0
        if self.gate < math.inf and self._warm and not self._reacquired:
            cost = self._residual_cost()
            if not cost <= self.gate:
                self._reacquired = True
                self._start_acquisition()
                self.iterations = 0
                self._done_at_refresh = False
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
            (bx, by, bz), _ = self._raab_field(self._mom, j, ux, uy, uz, x[2], False)
            for i in range(3):
                o = 3 * j + i
                e = (Sc[o] - (R[0, i] * bx + R[1, i] * by + R[2, i] * bz)) * w[o]
                cost += e * e
        return cost

    def _covariance(self) -> None:
        """The covariance of ``(p, dtheta)`` at the estimate, (6, 6) into
        ``covariance``, without a 6x6 inversion while it can be carried.

        The information of the exact model at the last evaluation ``p_m``,
        with source-frame orientation errors ``dtheta_s = R dtheta``, is
        ``A_s = sum_j q_j^2 K_j^T K_j``, ``K_j = [J_j | [B_j]x]`` per ampere
        (the Jacobian of ``model.signal`` with ``R`` taken out: ``H_j = R^T
        K_j``), ``q_j = I_j / sigma_j`` when the three axes of coil ``j`` have
        one ``sigma_j``; then ``R`` cancels from ``H_j^T H_j``. Its robust
        inverse ``C_s`` (``pose.covariance``) is formed at an evaluation
        (:meth:`_cov_form`) and carried to each estimate in closed form
        (:meth:`_cov_carry`) while that is accurate (:meth:`_carry_too_far`). While the ``q_j`` stay proportional to those of
        ``C_s`` (within ``_Q_TOL``) only the common scale changes:
        ``C = C_s q_m^2 / q^2``. Weights that differ between the axes of a
        coil: the sensor-frame information at the current ``R`` is formed
        and inverted (the evaluation's position)."""
        n, w, cur, qm = self.n, self._wv, self._curv, self._qm
        iso = True
        for j in range(n):
            w0 = w[3 * j]
            if abs(w[3 * j + 1] - w0) > _ISO_TOL * w0 or abs(w[3 * j + 2] - w0) > _ISO_TOL * w0:
                iso = False
                break
        if not iso:
            self._cs_ok = False
            self._cov_form(False)
            self._published_sigmas()
            return
        scale = 1.0
        if self._cs_ok and self._carry_too_far():
            self._cs_ok = False
        if self._cs_ok:
            num = den = 0.0
            for j in range(n):
                q = w[3 * j] * cur[j]
                num += q * q
                den += qm[j] * qm[j]
            s2 = num / den                      # common scale of q^2
            for j in range(n):
                q = w[3 * j] * cur[j]
                r = q * q / (qm[j] * qm[j] * s2)
                if not (1.0 - 2.0 * _Q_TOL <= r <= 1.0 + 2.0 * _Q_TOL):
                    self._cs_ok = False
                    break
            scale = 1.0 / s2
        if not self._cs_ok:
            self._cov_form(True)
            scale = 1.0
        self._cov_carry(scale)
        self._published_sigmas()

    def _carry_too_far(self) -> bool:
        """The carry from ``p_c`` would err by more than ``_COV_TOL`` (of
        sqrt(C_ii C_kk)) and a newer evaluation exists: its error, measured
        against magpylib's bound, is about ``15 rel d / rho`` for a carry ``d``
        (``rel``: the correction's gradient over the dipole's, 0.3 at 15 cm,
        0.036 at 40 cm, 0.012 at 70 cm), and the dipole carry's own ``1e-3``
        up to ``_CARRY_MAX`` x range."""
        pc, pm = self._pc, self._pm
        if pc[0] == pm[0] and pc[1] == pm[1] and pc[2] == pm[2]:
            return False
        lim = min(_CARRY_MAX, _COV_TOL / (15.0 * self._rel)) if self._rel > 0.0 else _CARRY_MAX
        return self._far(pc, None, lim)

    def _cov_form(self, iso: bool) -> None:
        """The information at ``p_m`` and its robust inverse (the one 6x6 work):
        ``iso``: source-frame form into ``_Cs`` with ``q_j = I_j / sigma_j``
        kept in ``_qm``; otherwise the sensor frame of the current ``R`` with a
        weight per element, into ``covariance``. Two numpy products into
        preallocated buffers."""
        n, w, cur, q = self.n, self._wv, self._curv, self._qv
        if iso:
            for j in range(n):
                qj = w[3 * j] * cur[j]
                self._qm[j] = qj
                q[3 * j] = q[3 * j + 1] = q[3 * j + 2] = qj
            np.multiply(self._Kn, self._qn, out=self._HWn)
            np.matmul(self._HWt, self._HWn, out=self._An)
            self._inverse(self._Cs)
            pc, pm = self._pc, self._pm
            pc[0], pc[1], pc[2] = pm[0], pm[1], pm[2]
            self._cs_ok = True
            return
        R, K, H = self._R, self._Ks, self._H
        for j in range(n):
            for i in range(3):
                q[3 * j + i] = w[3 * j + i] * cur[j]
                r0, r1, r2 = R[0, i], R[1, i], R[2, i]           # row i of R^T
                o = 18 * j + 6 * i
                for c in range(6):
                    H[o + c] = r0 * K[18 * j + c] + r1 * K[18 * j + 6 + c] + r2 * K[18 * j + 12 + c]
        np.multiply(self._Hn, self._qn, out=self._HWn)
        np.matmul(self._HWt, self._HWn, out=self._An)
        self._inverse(self._cov)

    def _inverse(self, out) -> None:
        """``out = A^-1`` of the information ``_An`` (``pose.covariance.RobustInverse6``, the
        runtime solver's inverse)."""
        self._inv.into(self._A36, out)

    def _cov_carry(self, scale: float) -> None:
        """``C_s`` (at ``p_m``, source-frame orientation) carried to the
        estimate ``p`` with orientation ``R``, times ``scale``, into
        ``covariance``. For co-centred orthogonal dipoles of equal moment the
        information is covariant under a rotation ``Q`` about the source
        centre (``A_s(Q p) = diag(Q, Q) A_s(p) diag(Q, Q)^T``: it sums over an
        orthonormal set of moments) and scales with the range as ``B ~
        rho^-3``, ``J ~ rho^-4`` (Raab eqs 3-5). With ``Q`` the rotation taking
        ``u_m`` to ``u``, ``t = rho / rho_m`` and ``M = Q^T R``:
        ``C_pp = t^8 Q C_pp,s Q^T``, ``C_ptheta = t^7 Q C_ptheta,s M``,
        ``C_thetatheta = t^6 M^T C_thetatheta,s M``. The exact loops and unequal
        currents depart from the symmetry: the carry errs by about ``15 rel
        d / rho`` (:meth:`_carry_too_far`; test against magpylib's bound)."""
        c, pm, x, R = self._cbar, self._pc, self._x, self._R
        mx, my, mz = pm[0] - c[0], pm[1] - c[1], pm[2] - c[2]
        rm = math.sqrt(mx * mx + my * my + mz * mz)
        mx, my, mz = mx / rm, my / rm, mz / rm
        ca, sa, cb, sb = math.cos(x[0]), math.sin(x[0]), math.cos(x[1]), math.sin(x[1])
        ux, uy, uz = cb * ca, cb * sa, -sb
        # Q = I + [w]x + [w]x^2 / (1 + u_m.u), w = u_m x u (the shortest rotation from u_m to u)
        wx, wy, wz = my * uz - mz * uy, mz * ux - mx * uz, mx * uy - my * ux
        h = 1.0 / (1.0 + mx * ux + my * uy + mz * uz)
        q00, q11, q22 = 1.0 - h * (wy * wy + wz * wz), 1.0 - h * (wx * wx + wz * wz), 1.0 - h * (wx * wx + wy * wy)
        q01, q10 = h * wx * wy - wz, h * wx * wy + wz
        q02, q20 = h * wx * wz + wy, h * wx * wz - wy
        q12, q21 = h * wy * wz - wx, h * wy * wz + wx
        Q = (q00, q01, q02, q10, q11, q12, q20, q21, q22)
        Qt = (q00, q10, q20, q01, q11, q21, q02, q12, q22)
        # M = Q^T R
        r = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2])
        M = _mul3(Qt, r)
        Mt = (M[0], M[3], M[6], M[1], M[4], M[7], M[2], M[5], M[8])
        t = x[2] / rm
        t2 = t * t
        t6 = t2 * t2 * t2 * scale
        Cs, cov = self._Cs, self._cov
        pp = _mul3(_mul3(Q, _block(Cs, 0, 0)), Qt)
        pt = _mul3(_mul3(Q, _block(Cs, 0, 3)), M)
        tt = _mul3(_mul3(Mt, _block(Cs, 3, 3)), M)
        f8, f7 = t6 * t2, t6 * t
        for i in range(3):
            for k in range(3):
                cov[6 * i + k] = f8 * pp[3 * i + k]
                v = f7 * pt[3 * i + k]
                cov[6 * i + 3 + k] = v
                cov[6 * (3 + k) + i] = v
                cov[6 * (3 + i) + 3 + k] = t6 * tt[3 * i + k]

    def _published_sigmas(self) -> None:
        """The smallest position and orientation standard deviations of the
        published covariance (the noise level of the next solve's stop)."""
        cov = self._cov
        vp, vo = min(cov[0], cov[7], cov[14]), min(cov[21], cov[28], cov[35])
        self._sig_p = math.sqrt(vp) if vp > 0.0 and math.isfinite(vp) else 0.0
        self._sig_o = math.sqrt(vo) if vo > 0.0 and math.isfinite(vo) else 0.0

    def _finish(self, status: int) -> None:
        x = self._x
        px, py, pz = self._point()
        pos = self.position
        pos[0], pos[1], pos[2] = px, py, pz
        self._sync_rotation()
        np.copyto(self.rotation, self._Rn)
        ang = self.angles
        for i in range(6):
            ang[i] = x[i]
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            status |= SOLVE_NONFINITE
        self.status = status
        self._then(None)
