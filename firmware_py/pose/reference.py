"""Pose solvers: Kuipers closed form and least-squares refinement.

Conventions
-----------
* ``S`` is the signal matrix, shape (3, ncoils): ``S[:, j]`` is the field
  measured in the SENSOR frame while source coil ``j`` carries its current
  (earth field already removed), T.
* ``position`` (3,) is the sensor position in the source frame, m.
* ``rotation`` (3, 3) maps sensor-frame vectors to the source frame
  (``v_source = rotation @ v_sensor``), so the measurement model is
  ``S[:, j] = rotation.T @ B_j(position)`` (Schepers & Veltink
  ``000_e46ec0e8bf7ea271.txt`` eq 5).
* Orientation errors are rotation vectors in the SENSOR frame, applied on the
  right: ``R_true = R_est @ exp([dtheta]x)``.  Parameter and covariance order
  is ``(px, py, pz, dtheta_x, dtheta_y, dtheta_z)`` (m, rad).

With that error definition the measurement Jacobian is Schepers & Veltink
eq 9: ``dh_j/dp = R^T J_j(p)`` (``J_j`` the source-frame field gradient of
coil j) and ``dh_j/dtheta = [h_j]x`` (eq 11, the skew matrix of the
sensor-frame field).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.model.field import MU0, CoilSet
from coiltrack.firmware.linalg import exp_rotvec
from coiltrack.firmware.linalg import skew_into as _skew_into
from coiltrack.firmware.pose.acquire import GRID_CANDIDATES, GRID_DIRECTIONS, NEAR_FIELD, fibonacci_directions
from coiltrack.firmware.pose.covariance import EIG_FLOOR, MARGIN_MAX_ORI_VAR, MAX_VARIANCE

__all__ = [
    "kuipers",
    "solve_pose",
    "crlb",
    "crlb_position_rms",
    "measurement_model",
    "measurement_jacobian",
    "measurement_model_and_jacobian",
    "so3_exp",
    "rotation_margin",
    "MAX_VARIANCE",
]

_MU0_4PI = MU0 / (4.0 * math.pi)
# LM stopping: relative step (position relative to |p|, rotation in rad)
# and relative cost decrease
_STEP_TOL = 1e-9
_COST_TOL = 1e-12
# The parameters of the algorithm are shared with the runtime solver (one
# definition): the eigenvalue floor and largest variance of the robust
# inverse, and the near-field start (exact model: below NEAR_FIELD coil
# radii the Kuipers start is replaced by a search on the rotation
# invariants over a grid of directions, half of them per hemisphere).
_EIG_FLOOR = EIG_FLOOR
_NEAR_FIELD = NEAR_FIELD
_GRID_DIRECTIONS = GRID_DIRECTIONS
_GRID_CANDIDATES = GRID_CANDIDATES


# ---------------------------------------------------------------------------
# small rotation helpers
# ---------------------------------------------------------------------------
def so3_exp(w, out=None):
    """Rotation matrix ``exp([w]x)`` of a rotation vector (Rodrigues).

    Parameters
    ----------
    w : array_like, shape (3,)
        Rotation vector, rad.
    out : ndarray, shape (3, 3), optional

    Returns
    -------
    ndarray, shape (3, 3)
    """
    R = np.empty((3, 3)) if out is None else out
    exp_rotvec(float(w[0]), float(w[1]), float(w[2]), R)
    return R


def _nearest_rotation(A):
    """Closest proper rotation to ``A`` in the Frobenius norm (SVD, det +1)."""
    U, _, Vt = np.linalg.svd(A)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        U[:, 2] = -U[:, 2]
    return U @ Vt


# ---------------------------------------------------------------------------
# Kuipers closed form
# ---------------------------------------------------------------------------
def kuipers(S, moment, hemisphere=(1.0, 0.0, 0.0)):
    """Closed-form pose from an orthogonal dipole source (thesis App. 5.A).

    Roetenberg thesis (``002_cd7f1fdb7fc67471.txt``) eqs 5.9-5.34, after
    Kuipers, written with the source-to-sensor unit vector ``u`` instead of
    the tracking angles.  The dipole field of the three unit excitations
    (eq 5.9) is ``B = k (3 u u^T - I)`` with ``k = mu0 m / (4 pi r^3)``
    (eqs 5.13-5.14 and 5.20-5.24: ``Upsilon^T C_m Upsilon = 3 u u^T - I``),
    so ``S = k R^T (3 u u^T - I)`` and

    * ``U = S^T S = k^2 (I + 3 u u^T)`` (eq 5.15), ``tr U = 6 k^2`` (eq 5.16),
      ``k = sqrt(tr U / 6)`` (eq 5.17);
    * ``u`` is the eigenvector of the largest eigenvalue (``4 k^2``) of ``U``
      (eqs 5.22-5.28: ``X = u u^T = (M^T M - I)/3``), defined up to sign: the
      two mirror positions ``+-r u`` give the same ``S``;
    * ``r = (mu0 m / (4 pi k))^(1/3)`` replaces the calibration of eq 5.18;
    * ``(3 u u^T - I)^-1 = 1.5 u u^T - I`` (footnote to eq 5.29), so
      ``R = (1.5 u u^T - I) S^T / k`` (eqs 5.29-5.31), projected onto the
      nearest rotation by an SVD (det +1).  The rotation does not depend on
      the sign of ``u``.

    Parameters
    ----------
    S : array_like, shape (3, 3)
        ``S[:, j]``: field in the sensor frame while source coil j (axis x, y,
        z for j = 0, 1, 2) carries the dipole moment ``moment``, T.
    moment : float
        Dipole moment of each source coil, A m^2 (sign: direction along
        +x, +y, +z).
    hemisphere : array_like, shape (3,)
        Of the two mirror positions the one with ``position . hemisphere >= 0``
        is returned.

    Returns
    -------
    position : ndarray, shape (3,)
        Sensor position in the source frame, m.
    rotation : ndarray, shape (3, 3)
        Sensor-to-source rotation.

    Raises
    ------
    ValueError
        If ``S`` is not (3, 3) or not finite, or ``moment`` is zero.

    Notes
    -----
    A zero signal matrix has no finite solution; ``k`` is floored at
    1e-300 T, which returns a very distant position and the identity-like
    projection, never NaN.
    """
    S = np.asarray(S, dtype=float)
    if S.shape != (3, 3):
        raise ValueError("kuipers needs a (3, 3) signal matrix")
    if not np.all(np.isfinite(S)):
        raise ValueError("signal matrix is not finite")
    moment = float(moment)
    if moment == 0.0 or not math.isfinite(moment):
        raise ValueError("moment must be finite and non-zero")
    U = S.T @ S
    k = math.sqrt(max(float(np.trace(U)) / 6.0, 0.0))
    k = max(k, 1e-300)
    _, V = np.linalg.eigh(U)
    u = V[:, 2].copy()
    h = np.asarray(hemisphere, dtype=float)
    if float(u @ h) < 0.0:
        u = -u
    r = (_MU0_4PI * abs(moment) / k) ** (1.0 / 3.0)
    ks = math.copysign(k, moment)
    A = 1.5 * np.outer(u, u)
    A[0, 0] -= 1.0
    A[1, 1] -= 1.0
    A[2, 2] -= 1.0
    rotation = _nearest_rotation((A @ S.T) / ks)
    return r * u, rotation


# ---------------------------------------------------------------------------
# measurement model
# ---------------------------------------------------------------------------
def _as_coilset(coils):
    return coils if isinstance(coils, CoilSet) else CoilSet(coils)


def measurement_model_and_jacobian(position, rotation, coils, currents, model="exact",
                                   out_h=None, out_H=None):
    """Predicted signal matrix and its Jacobian wrt the 6 pose parameters.

    ``h[:, j] = R^T B_j(p)`` (Schepers & Veltink eq 5) and
    ``H[:, j, :] = [R^T J_j(p), [h_j]x]`` (eqs 9 and 11; error state
    ``(dp, dtheta)`` with ``R_true = R exp([dtheta]x)``).

    Parameters
    ----------
    position : array_like, shape (3,)
        Sensor position in the source frame, m.
    rotation : array_like, shape (3, 3)
        Sensor-to-source rotation.
    coils : sequence of Coil or CoilSet, length n
    currents : array_like, shape (n,)
        Current of each coil, A.
    model : {"exact", "dipole"}
    out_h : ndarray, shape (3, n), optional
    out_H : ndarray, shape (3, n, 6), optional

    Returns
    -------
    h : ndarray, shape (3, n)
        T, sensor frame.
    H : ndarray, shape (3, n, 6)
        ``H[:, j, :3]`` in T/m, ``H[:, j, 3:]`` in T/rad.  Flattened with
        ``H.reshape(3 * n, 6)`` it matches ``h.reshape(3 * n)``.
    """
    cs = _as_coilset(coils)
    n = cs.n
    h = np.empty((3, n)) if out_h is None else out_h
    H = np.empty((3, n, 6)) if out_H is None else out_H
    R = np.asarray(rotation, dtype=float)
    B, J = cs.fields(position, currents, model, out_j=cs._jout)
    # h = R^T B_j for all j: (3, n)
    np.matmul(R.T, B.T, out=h)
    # position block: R^T J_j  -> H[:, j, :3]
    np.einsum("ik,jil->kjl", R, J, out=H[:, :, :3])
    for j in range(n):
        _skew_into(h[:, j], H[:, j, 3:])
    return h, H


def measurement_model(position, rotation, coils, currents, model="exact", out=None):
    """Predicted signal matrix ``h[:, j] = R^T B_j(p)``, shape (3, n), T.

    Schepers & Veltink (``000_e46ec0e8bf7ea271.txt``) eq 5, one column per
    coil.  See ``measurement_model_and_jacobian`` for the parameters.
    """
    cs = _as_coilset(coils)
    h = np.empty((3, cs.n)) if out is None else out
    B, _ = cs.fields(position, currents, model)
    R = np.asarray(rotation, dtype=float)
    np.matmul(R.T, B.T, out=h)
    return h


def measurement_jacobian(position, rotation, coils, currents, model="exact", out=None):
    """Jacobian of ``measurement_model`` wrt ``(p, dtheta)``, shape (3, n, 6).

    Schepers & Veltink eqs 9-11.  See ``measurement_model_and_jacobian``.
    """
    return measurement_model_and_jacobian(position, rotation, coils, currents, model,
                                          out_H=out)[1]


# ---------------------------------------------------------------------------
# information / covariance
# ---------------------------------------------------------------------------
def _sigma_array(sigma, n):
    s = np.asarray(sigma, dtype=float)
    if s.ndim == 0:
        s = np.full((3, n), float(s))
    elif s.shape != (3, n):
        raise ValueError(f"sigma must be a scalar or have shape (3, {n})")
    if not np.all(np.isfinite(s)) or np.any(s <= 0.0):
        raise ValueError("sigma must be finite and positive")
    return s


def _robust_inverse(A):
    """Inverse of a symmetric PSD information matrix that never raises.

    Eigenvalues below ``1e-15 * max`` or below ``1 / MAX_VARIANCE``
    (unobservable directions) are floored there, so the variance along them
    is large but finite (at most ``MAX_VARIANCE``).  A non-finite matrix
    gives ``MAX_VARIANCE * I``.
    """
    n = A.shape[0]
    if not np.all(np.isfinite(A)):
        return np.eye(n) * MAX_VARIANCE
    A = 0.5 * (A + A.T)
    w, V = np.linalg.eigh(A)
    top = float(w[-1]) if w[-1] > 0.0 else 0.0
    w = np.maximum(w, max(_EIG_FLOOR * top, 1.0 / MAX_VARIANCE))
    return (V / w) @ V.T


def rotation_margin(cov):
    """``cov`` (6, 6) with its position block plus the second-order margin of the orientation
    error (``pose.covariance.RotationMargin``, whose allocation-free form follows this one):
    ``1/4 K (tr(C_tt) C_tt + 2 C_tt^2) K^T``, ``K = C_pt C_tt^-1``, with ``C_tt`` scaled down to
    a trace of ``MARGIN_MAX_ORI_VAR`` when larger. A copy; ``cov`` unchanged."""
    out = np.array(cov, dtype=float)
    Ct, Cpt = out[3:, 3:], out[:3, 3:]
    tr = float(np.trace(Ct))
    if not (tr > 0.0 and math.isfinite(tr)):
        return out
    try:
        np.linalg.cholesky(Ct)
    except np.linalg.LinAlgError:
        return out
    s = min(1.0, MARGIN_MAX_ORI_VAR / tr)
    K = Cpt @ np.linalg.inv(Ct)
    Cs = s * Ct
    M = 0.25 * K @ (np.trace(Cs) * Cs + 2.0 * Cs @ Cs) @ K.T
    out[:3, :3] += 0.5 * (M + M.T)
    return out


def crlb(position, rotation, coils, currents, sigma, model="exact"):
    """Cramer-Rao lower bound of the 6-DOF pose for one signal matrix.

    Inverse Fisher information ``(H^T W H)^-1`` of the Gaussian model
    ``S = h(p, R) + v``, ``v_ij ~ N(0, sigma_ij^2)`` independent, with ``H``
    from ``measurement_model_and_jacobian``.

    Parameters
    ----------
    position : array_like, shape (3,)
        m, source frame.
    rotation : array_like, shape (3, 3)
        Sensor-to-source rotation.
    coils : sequence of Coil or CoilSet, length n
    currents : array_like, shape (n,)
        A.
    sigma : float or array_like, shape (3, n)
        Noise standard deviation of each element of ``S``, T.
    model : {"exact", "dipole"}

    Returns
    -------
    ndarray, shape (6, 6)
        Covariance bound of ``(p, dtheta)`` in m and rad (``dtheta`` in the
        sensor frame, ``R_true = R exp([dtheta]x)``).  Unobservable
        directions get a very large finite variance instead of raising.
    """
    cs = _as_coilset(coils)
    s = _sigma_array(sigma, cs.n)
    _, H = measurement_model_and_jacobian(position, rotation, cs, currents, model)
    Hw = (H / s[:, :, None]).reshape(3 * cs.n, 6)
    return _robust_inverse(Hw.T @ Hw)


def crlb_position_rms(position, rotation, coils, currents, sigma, model="exact"):
    """Square root of the trace of the position block of ``crlb``, m."""
    C = crlb(position, rotation, coils, currents, sigma, model)
    return math.sqrt(max(float(C[0, 0] + C[1, 1] + C[2, 2]), 0.0))


# ---------------------------------------------------------------------------
# least-squares solver
# ---------------------------------------------------------------------------
def _initial_guess(S, cs, currents, hemisphere):
    """Kuipers start for an arbitrary source of >= 3 coils.

    With the dipole model and all coils at a common centre,
    ``S = R^T D(p) M`` where ``M`` (3, n) holds the coil moments and
    ``D(p) = mu0/(4 pi r^3) (3 u u^T - I)``.  ``S M^+`` is then exactly the
    signal matrix of an orthogonal source of unit moments, which
    ``kuipers`` inverts.  For three equal orthogonal moments this equals
    calling ``kuipers(S, |m|)``.  Positions are taken relative to the mean
    coil centre.
    """
    M = cs.moments(currents).T  # (3, n)
    sv = np.linalg.svd(M, compute_uv=False)
    if sv.size < 3 or sv[2] <= 1e-9 * sv[0]:
        raise ValueError("the coil moments do not span 3-D: pass x0")
    S3 = S @ np.linalg.pinv(M)
    p, R = kuipers(S3, 1.0, hemisphere)
    return p + cs.centers.mean(axis=0), R


def _fields_at(cs, cur, pts, model):
    """Fields of every coil at many points: (n_coils, n_pts, 3), source frame."""
    out = np.empty((cs.n, len(pts), 3))
    for j, c in enumerate(cs.coils):
        c.field(pts, float(cur[j]), model=model, out=out[j])
    return out


def _invariant_misfit(Um, B):
    """``|U_meas - B^T B|_F / tr(U_meas)`` for stacks of field matrices.

    ``B`` has shape (n_coils, k, 3) (k candidate positions)."""
    U = np.einsum("ika,jka->kij", B, B)
    U -= Um
    return np.sqrt(np.einsum("kij,kij->k", U, U)) / float(np.trace(Um))


_GRID = fibonacci_directions(_GRID_DIRECTIONS)


def _refine_position_invariants(Um, cs, cur, p, model, iters):
    """Position from the rotation-invariant ``U = S^T S = B(p)^T B(p)``.

    ``S = R^T B(p)`` with ``B(p)`` (3, n) the source-frame fields, so
    ``S^T S`` does not depend on the orientation (thesis eq 5.15 without the
    dipole assumption).  A small Levenberg-Marquardt on the upper triangle of
    ``U`` fits the 3 position coordinates alone.  Returns ``(p, misfit)``.
    """
    n = cs.n
    iu = np.triu_indices(n)
    scale = 1.0 / float(np.trace(Um))
    Jbuf = np.empty((n, 3, 3))

    def residual(pp):
        B, J = cs.fields(pp, cur, model, out_j=Jbuf)
        U = B @ B.T  # U_ij = B_i . B_j
        # dU_ij/dp_k = (J_i[:, k]) . B_j + B_i . J_j[:, k]
        G = np.einsum("ilk,jl->ijk", J, B)
        dU = G + np.swapaxes(G, 0, 1)
        return (Um - U)[iu] * scale, -dU[iu] * scale

    r, Jr = residual(p)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iters):
        A = Jr.T @ Jr
        dA = np.diag(A).copy()
        dA[dA <= 0.0] = 1.0
        try:
            d = np.linalg.solve(A + lam * np.diag(dA), -(Jr.T @ r))
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(d)):
            break
        rt, Jt = residual(p + d)
        ct = float(rt @ rt)
        if math.isfinite(ct) and ct < cost:
            p = p + d
            r, Jr, cost = rt, Jt, ct
            lam = max(lam * 0.1, 1e-12)
            if float(np.linalg.norm(d)) <= 1e-9 * float(np.linalg.norm(p)):
                break
        else:
            lam *= 10.0
            if lam > 1e8:
                break
    return p, math.sqrt(cost)


def _initial_pose(S, cs, cur, hemisphere, model, sigma_rms):
    """Start for the LM.

    Kuipers (``_initial_guess``) is exact for the dipole model.  With the
    exact model close to the source (within ``_NEAR_FIELD`` times the
    largest coil radius plus the centre spread) the dipole picture fails: on
    a coil axis at 1.8 radii the eigenvalues of ``U`` are no longer
    ``(4, 1, 1) k^2`` and the Kuipers direction can be 70 degrees off.
    There the Kuipers position is first refined on the rotation-invariant
    ``U = S^T S`` alone (``_refine_position_invariants``).  If the misfit of
    ``U`` stays well above its noise level (``~2 sigma / |S|_F``), the
    position is searched instead: a grid of directions in the requested
    hemisphere, each at the radius that matches ``tr U`` (power law
    ``tr U ~ r^-6``), and the best candidates are refined on ``U``.  The
    orientation then follows in closed form (orthogonal Procrustes:
    ``R = polar(B(p) S^T)``).
    """
    p, R = _initial_guess(S, cs, cur, hemisphere)
    if model != "exact":
        return p, R
    cbar = cs.centers.mean(axis=0)
    reach = float(cs.radii.max()) + float(np.linalg.norm(cs.centers - cbar, axis=1).max())
    r0 = float(np.linalg.norm(p - cbar))
    Um = S.T @ S
    if r0 >= _NEAR_FIELD * reach or not np.all(np.isfinite(p)):
        return p, R
    best_p, best_m = _refine_position_invariants(Um, cs, cur, p, model, 15)
    tol = 20.0 * sigma_rms / math.sqrt(max(float(np.trace(Um)), 1e-300)) + 1e-9
    if best_m <= tol:
        B, _ = cs.fields(best_p, cur, model)
        return best_p, _nearest_rotation(B.T @ S.T)
    h = np.asarray(hemisphere, dtype=float)
    dirs = _GRID[_GRID @ h >= 0.0] if np.any(h) else _GRID
    # radius per direction from the trace (two power-law steps)
    rad = np.full(len(dirs), r0)
    tr_m = float(np.trace(Um))
    with np.errstate(all="ignore"):
        for _ in range(2):
            B = _fields_at(cs, cur, cbar + dirs * rad[:, None], model)
            tr = np.einsum("ika,ika->k", B, B)
            rad *= (tr / tr_m) ** (1.0 / 6.0)
            rad = np.clip(rad, 0.25 * r0, 4.0 * r0)
        B = _fields_at(cs, cur, cbar + dirs * rad[:, None], model)
        mis = _invariant_misfit(Um, B)
    mis[~np.isfinite(mis)] = np.inf
    order = np.argsort(mis)[:_GRID_CANDIDATES]
    for start in [cbar + dirs[i] * rad[i] for i in order]:
        pc, mc = _refine_position_invariants(Um, cs, cur, start, model, 15)
        if mc < best_m:
            best_p, best_m = pc, mc
    B, _ = cs.fields(best_p, cur, model)
    return best_p, _nearest_rotation(B.T @ S.T)


def solve_pose(S, coils, currents, sigma, hemisphere=(1.0, 0.0, 0.0), model="exact",
               iters=20, x0=None, info=None):
    """Pose from one signal matrix: Kuipers start, then Levenberg-Marquardt.

    Minimises ``sum_ij ((S_ij - h_ij(p, R)) / sigma_ij)^2`` over position and
    orientation, ``h`` from ``measurement_model`` with the chosen field model.
    Each step solves ``(A + lambda diag A) delta = g`` with
    ``A = H^T W H``, ``g = H^T W (S - h)`` and updates
    ``p += delta[:3]``, ``R = R exp([delta[3:]]x)`` (multiplicative, sensor
    frame).  ``lambda`` starts at 1e-6 (nearly Gauss-Newton, since the
    start is close) and is raised tenfold on a rejected step.  It stops
    converged on a step below 1e-9 (relative position, rad) or a relative
    cost change below 1e-12, whether the step was accepted or rejected.

    The start is the Kuipers closed form (``kuipers`` applied to
    ``S M^+``, ``M`` the coil moments; for three equal orthogonal coils this
    is ``kuipers(S, |m|)``), except with the exact model within four coil
    radii of the source, where the dipole picture fails and the position is
    first fitted to the rotation invariant ``S^T S`` (see ``_initial_pose``).

    Parameters
    ----------
    S : array_like, shape (3, n)
        ``S[:, j]``: field in the sensor frame while coil j carries
        ``currents[j]``, T.
    coils : sequence of Coil or CoilSet, length n (n >= 3 unless ``x0``)
    currents : array_like, shape (n,)
        A.
    sigma : float or array_like, shape (3, n)
        Standard deviation of each element of ``S``, T.
    hemisphere : array_like, shape (3,)
        Selects the Kuipers mirror solution (``position . hemisphere >= 0``).
    model : {"exact", "dipole"}
    iters : int
        Maximum number of accepted or rejected LM steps.
    x0 : tuple (position (3,), rotation (3, 3)), optional
        Start instead of the Kuipers solution (e.g. the previous pose).
    info : dict, optional
        If given, filled with ``iterations``, ``cost`` (chi-square at the
        solution), ``converged`` (bool) and ``x0`` (the start).

    Returns
    -------
    position : ndarray, shape (3,)
        m, source frame.
    rotation : ndarray, shape (3, 3)
        Sensor-to-source rotation.
    covariance : ndarray, shape (6, 6)
        ``(H^T W H)^-1`` at the solution for ``(p, dtheta)``, m and rad, with
        ``R_true = R_est exp([dtheta]x)`` (sensor-frame rotation error), its
        position block plus the second-order margin of the orientation error
        (:func:`rotation_margin`).
        Near-singular geometry gives large variances, never an exception.

    Raises
    ------
    ValueError
        Bad shapes, non-finite ``S``, non-positive ``sigma``, or fewer than
        three independent coil moments without ``x0``.
    """
    cs = _as_coilset(coils)
    S, cur, w = _solve_inputs(S, cs, currents, sigma)
    p, R = _solve_start(S, cs, cur, w, hemisphere, model, x0)
    start = (p.copy(), R.copy())
    p, R, H, cost, it, converged = _lm_iterate(S, cs, cur, w, model, p, R, iters)
    # re-orthonormalise once: products of exp() drift at the 1e-16 level
    R = _nearest_rotation(R)
    Jw = (H * w[:, :, None]).reshape(3 * cs.n, 6)
    cov = rotation_margin(_robust_inverse(Jw.T @ Jw))
    if info is not None:
        info["iterations"] = it
        info["cost"] = cost
        info["converged"] = converged
        info["x0"] = start
    return p, R, cov


def _solve_inputs(S, cs, currents, sigma):
    """:func:`solve_pose`'s inputs checked: ``S`` (3, n) finite, the currents
    (n,) and the weights ``w = 1 / sigma`` (3, n); ValueError otherwise."""
    n = cs.n
    S = np.asarray(S, dtype=float)
    if S.shape != (3, n):
        raise ValueError(f"S must have shape (3, {n})")
    if not np.all(np.isfinite(S)):
        raise ValueError("signal matrix is not finite")
    cur = np.asarray(currents, dtype=float).reshape(n)
    w = 1.0 / _sigma_array(sigma, n)  # (3, n)
    return S, cur, w


def _solve_start(S, cs, cur, w, hemisphere, model, x0):
    """:func:`solve_pose`'s start ``(p, R)``: ``x0`` (its rotation made the
    nearest rotation) or, without it, :func:`_initial_pose`."""
    if x0 is None:
        return _initial_pose(S, cs, cur, hemisphere, model, math.sqrt(float(np.mean(w ** -2))))
    p = np.array(x0[0], dtype=float).reshape(3)
    R0 = np.asarray(x0[1], dtype=float).reshape(3, 3)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(R0))):
        raise ValueError("x0 is not finite")
    return p, _nearest_rotation(R0)


class _Residual:
    """The weighted residual of :func:`solve_pose` at a pose: ``h``, ``H``
    (``measurement_model_and_jacobian``) into the given buffers and the cost
    ``sum ((S - h) w)^2``."""

    def __init__(self, S, cs, cur, w, model):
        self.S, self.cs, self.cur, self.w, self.model = S, cs, cur, w, model
        self.r = np.empty(S.shape)

    def cost(self, pp, RR, hh, HH):
        measurement_model_and_jacobian(pp, RR, self.cs, self.cur, self.model, out_h=hh, out_H=HH)
        r = self.r
        np.subtract(self.S, hh, out=r)
        np.multiply(r, self.w, out=r)
        return float(np.dot(r.ravel(), r.ravel()))


def _lm_iterate(S, cs, cur, w, model, p, R, iters):
    """The Levenberg-Marquardt steps of :func:`solve_pose` from ``(p, R)``;
    returns ``(p, R, H, cost, iterations, converged)`` with ``H`` the
    Jacobian at the returned pose."""
    n = cs.n
    m = 3 * n
    h = np.empty((3, n))
    H = np.empty((3, n, 6))
    h_t = np.empty((3, n))
    H_t = np.empty((3, n, 6))
    dR = np.empty((3, 3))
    res = _Residual(S, cs, cur, w, model)
    cost = res.cost(p, R, h, H)
    lam = 1e-6
    converged = False
    it = 0
    for it in range(1, iters + 1):
        Jw = (H * w[:, :, None]).reshape(m, 6)
        rw = ((S - h) * w).reshape(m)
        A = Jw.T @ Jw
        g = Jw.T @ rw
        dA = np.diag(A).copy()
        dA[dA <= 0.0] = 1.0
        try:
            delta = np.linalg.solve(A + lam * np.diag(dA), g)
        except np.linalg.LinAlgError:  # exactly singular: damp harder
            lam *= 10.0
            if lam > 1e12:
                break
            continue
        if not np.all(np.isfinite(delta)):
            break
        p_t = p + delta[:3]
        R_t = R @ so3_exp(delta[3:], out=dR)
        cost_t = res.cost(p_t, R_t, h_t, H_t)
        # a step this small is followed by one of ~1e-18 (quadratic
        # convergence) or is below the rounding level of the cost
        small = (float(np.linalg.norm(delta[:3])) <= _STEP_TOL * max(float(np.linalg.norm(p)), 1e-3)
                 and float(np.linalg.norm(delta[3:])) <= _STEP_TOL)
        if math.isfinite(cost_t) and cost_t <= cost:
            p, R = p_t, R_t
            h, h_t = h_t, h
            H, H_t = H_t, H
            rel = (cost - cost_t) / max(cost, 1e-300)
            cost = cost_t
            lam = max(lam * 0.1, 1e-12)
            if small or rel < _COST_TOL:
                converged = True
                break
        # rejected: converged if the step is tiny or the cost is flat to
        # its rounding level (otherwise the damping climbs for nothing)
        elif small or (cost_t - cost) < _COST_TOL * max(cost, 1e-300):
            converged = True
            break
        else:
            lam *= 10.0
            if lam > 1e12:
                break
    return p, R, H, cost, it, converged
