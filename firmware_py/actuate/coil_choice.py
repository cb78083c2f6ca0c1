"""Adaptive single-coil actuation: when to pulse, which coil, how strong.

After Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``), sec. 2.1
and Fig. 1: between magnetic updates the inertial sensors carry the state
and its uncertainty ``sigma_x`` grows; "an actuation is required if the
estimated uncertainty reaches a predefined maximum sigma_x,max. Only the coil
yielding the largest uncertainty reduction is actuated and the current
applied is chosen such that the uncertainty decreases to a predefined minimum
sigma_x,min". The reduction is predicted with the covariance update of the
extended Kalman filter, eq 4, using the linearised single-coil measurement
model, eqs 9-11.

Pieces (all buffers are allocated in ``__init__``; the per-decision paths
write into them and create no numpy arrays):

:class:`SingleCoilModel`
    ``y_c = I_c R^T B_c(p)`` for every coil ``c`` of the source at unit
    current (Schepers eq 5) with the exact loop field (eqs 6-7) or the dipole
    (eq 8), and its Jacobian with respect to the pose error
    ``(dp, dtheta)``: ``H_c = [R^T dB_c/dp, [h_c]x]`` (eqs 9-11). The
    orientation error is the sensor-frame rotation vector with
    ``R_true = R_est exp([dtheta]x)`` (``coiltrack.firmware.pose.reference``), so eq 11 reads
    ``+[h]x``; Schepers' eq 2 defines the error with the opposite sign
    (``R_est = R_true (I + [dtheta]x)``), which flips both the error and the
    sign of eq 11 and leaves eq 4 unchanged. Each coil is a pose plus radius
    and turns (``coiltrack.firmware.model.field.Coil``), so coils that are not orthogonal
    or do not share an origin use the same code.
:func:`posterior_pose_variances`
    Diagonal of the a-posteriori pose covariance of eq 4,
    ``P+ = P- - P- H^T (H P- H^T + R_v)^-1 H P-``, for one coil at one
    current; the measurement covariance ``R_v`` is the pulse-amplitude
    variance (``sigma_v^2 / n`` plus the baseline term, Schepers sec. 3.1
    and ``coiltrack.firmware.measure.pulse``) plus a relative field-model error.
:class:`CoilChooser`
    "Which": the coil whose update reduces the normalised uncertainty
    ``J(P) = sum_k P_kk / sigma_max_k^2`` over the six pose variables the
    most, each coil at the largest current it may carry (driver limit,
    magnetometer range). "How strong": the smallest candidate current for
    which the predicted standard deviation of the variable that triggered the
    pulse falls to its ``sigma_min``; the largest allowed current if none does.
:class:`ActuationPolicy`
    "When": a pulse is due when the uncertainty predicted for the time the
    pulse would be measured exceeds ``sigma_max`` in any pose variable
    (position or orientation thresholds), or when no update has been made
    for ``max_interval_us``.
:class:`NisMonitor`
    Consistency: the normalised innovation squared (NIS) of every single-coil
    update is gated (chi-square, 3 degrees of freedom) and its mean over a
    window is tested against the chi-square bound of the window. A
    ferromagnetic object near the sensor or the source adds a field the model
    does not know (Schepers sec. 3.3: the state update goes wrong while "the
    reduction of the covariance P_k is updated equally, yielding
    inconsistent behaviour"); the monitor then reports the disturbance and
    inflates the measurement covariance by the observed excess, so the
    filter keeps using the (biased) pulses with honest weights instead of
    diverging on them or drifting on the IMU alone.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.linalg import flat
from coiltrack.firmware.model.field import CoilSet
from coiltrack.firmware.linalg import inv3_sym
from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.model.signal import SignalModel

__all__ = [
    "POSE_DIM",
    "SingleCoilModel",
    "posterior_pose_variances",
    "add_gain_term",
    "PoseCovUpdate",
    "saturation_current_limit",
    "CoilChooser",
    "CompiledCoilChooser",
    "coil_chooser",
    "ActuationPolicy",
    "NisMonitor",
    "chi2_upper",
    "current_ladder",
]

#: pose error (dp, dtheta): the columns of the single-coil Jacobian
POSE_DIM = 6


def chi2_upper(dof: float, z: float) -> float:
    """Upper quantile of chi-square with ``dof`` degrees of freedom.

    Wilson-Hilferty: ``dof (1 - 2/(9 dof) + z sqrt(2/(9 dof)))^3`` with ``z``
    the standard-normal quantile (2.326 for 99 %, 3.09 for 99.9 %). Within
    2 % of the exact quantile from 3 degrees of freedom up (1 % from 6);
    no scipy on a board.
    """
    c = 2.0 / (9.0 * dof)
    return dof * (1.0 - c + z * math.sqrt(c)) ** 3


def current_ladder(i_min: float, i_max: float, levels: int) -> tuple[float, ...]:
    """``levels`` currents from ``i_min`` to ``i_max`` in equal ratios (A).

    Information grows with ``I^2`` and the coil energy too, so a geometric
    ladder gives the same relative step in both.
    """
    if levels < 2 or not (0.0 < i_min < i_max):
        return (float(i_max),)
    r = (i_max / i_min) ** (1.0 / (levels - 1))
    return tuple(round(i_min * r ** k, 4) for k in range(levels - 1)) + (float(i_max),)


class SingleCoilModel:
    """Per-ampere measurement model of every source coil at one pose.

    A view of ``coiltrack.firmware.model.signal.SignalModel`` at 1 A per
    coil. After :meth:`evaluate` ``(p, R)``:

    * ``h[c]`` (3,): ``R^T B_c(p)`` for 1 A in coil ``c``, sensor frame, T/A
      (Schepers eq 5; ``B_c`` from eqs 6-7 with ``model="exact"``, eq 8 with
      ``model="dipole"``);
    * ``H[c]`` (3, 6): ``[R^T J_c(p), [h_c]x]`` per ampere, the Jacobian wrt
      ``(dp, dtheta)`` (eqs 9-11; ``J_c = dB_c/dp`` in the source frame,
      analytic for both models, see ``coiltrack.firmware.model.field``);
    * ``B[c]``, ``J[c]``: the source-frame field and gradient per ampere.

    The field is linear in the current, so the model for current ``I`` is
    ``I h[c]`` and ``I H[c]``.

    Parameters
    ----------
    coils : sequence of ``coiltrack.firmware.model.field.Coil`` or a ``CoilSet``
        Any geometry: each coil has its own centre, axis, radius and turns.
    model : {"exact", "dipole"}
    core : ``coiltrack.firmware.core.Core``, the numeric core (chosen at composition)
    """

    def __init__(self, coils, model: str = "exact", core=_DEFAULT_CORE):
        self.cs = coils if isinstance(coils, CoilSet) else CoilSet(coils)
        self.signal = SignalModel(self.cs.coils, model, core)
        n = self.cs.n
        self.n = n
        self.model = model
        self._ones = memoryview(np.ones(n))
        self.B = self.signal.B
        self.J = self.signal.J
        self.h = np.zeros((n, 3))
        self.H = np.zeros((n, 3, POSE_DIM))
        self._hv = flat(self.h)
        self._Hv = flat(self.H)

    def evaluate(self, p, R) -> None:
        """Fill ``h``, ``H``, ``B``, ``J`` for position ``p`` (3,) (source
        frame, m) and rotation ``R`` (3, 3) (sensor to source)."""
        self.signal.measure(float(p[0]), float(p[1]), float(p[2]), R, self._ones, self._hv, self._Hv)


def posterior_pose_variances(P6, A, M, hnorm2, current, var_amp, rel_model, out,
                             current_sigma: float = 0.0) -> bool:
    """Diagonal of the eq-4 posterior pose covariance for one coil and current.

    With ``H = I Hu`` (``Hu`` the per-ampere Jacobian (3, 6)), ``A = Hu P6``
    (3, 6) and ``M = Hu P6 Hu^T`` (3, 3) precomputed for the coil,

        S   = I^2 M + R_v,
        R_v = (var_amp + (rel_model I |hu|)^2 + (current_sigma |hu|)^2) I3
        P+  = P6 - I^2 A^T S^-1 A                       (Schepers eq 4)

    (``current_sigma``: the std of the coil current, A). Only ``diag(P+)``
    is written to ``out`` (6,). ``hnorm2 = |hu|^2``
    (T/A)^2. Pure float arithmetic on the 3x3 system; no arrays created.
    Returns False (``out`` = ``diag(P6)``) if ``S`` is not positive definite.
    """
    i2 = current * current
    r = var_amp + (rel_model * rel_model * i2 + current_sigma * current_sigma) * hnorm2
    inv = inv3_sym(i2 * M[0, 0] + r, i2 * M[0, 1], i2 * M[0, 2],
                    i2 * M[1, 1] + r, i2 * M[1, 2], i2 * M[2, 2] + r)
    if inv is None:
        for k in range(POSE_DIM):
            out[k] = P6[k, k]
        return False
    s00, s01, s02, s11, s12, s22 = inv
    for k in range(POSE_DIM):
        a0 = A[0, k]
        a1 = A[1, k]
        a2 = A[2, k]
        q = (a0 * (s00 * a0 + s01 * a1 + s02 * a2)
             + a1 * (s01 * a0 + s11 * a1 + s12 * a2)
             + a2 * (s02 * a0 + s12 * a1 + s22 * a2))
        out[k] = P6[k, k] - i2 * q
    return True


def add_gain_term(M, g: float, h0: float, h1: float, h2: float) -> None:
    """A coil's constant gain error in its eq-4 posterior: ``M += g hu hu^T`` (``g = s_g^2``).

    With the gain error ``g_c`` (variance ``s_g^2``) the pulse is ``y = (1 + g_c) I R^T B_c(p)``
    (Schepers & Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt``, eq 5 at the coil's true current),
    so its linearised error is ``I Hu dx + g_c I hu + v``; the pose's posterior with ``g_c`` left out
    of the state is eq 4 with ``R_v + s_g^2 (I hu)(I hu)^T``: a rank-one term along the field, the
    part of the error repeated pulses of the coil do not average (white noise falls as ``1/n``,
    ``g_c`` does not). ``S = I^2 M + R_v`` becomes ``I^2 (M + s_g^2 hu hu^T) + R_v``: the term
    folded into ``M`` (3, 3). Exact for a gain uncorrelated with the pose (the dense eq 4 of the
    state augmented by ``g_c``, ``tests/firmware/core/test_core_sc_choose.py``); the filter's
    cross-covariance is left out. Each entry ``M[i, j] + (g hu_i) hu_j``: ``ct_gain_term``'s order."""
    for i, hi in ((0, h0), (1, h1), (2, h2)):
        gh = g * hi
        M[i, 0] = M[i, 0] + gh * h0
        M[i, 1] = M[i, 1] + gh * h1
        M[i, 2] = M[i, 2] + gh * h2


class PoseCovUpdate:
    """Full eq-4 covariance update of a 6x6 pose covariance, in place.

    ``apply(P6, Hu, current, var_amp, rel_model)`` replaces ``P6`` by
    ``P6 - P6 H^T (H P6 H^T + R_v)^-1 H P6`` with ``H = current Hu``: the
    expected effect of a pulse already commanded (the covariance update does
    not depend on the measured value), so the next decision can be made
    while that pulse is still in flight. Buffers allocated here.
    """

    def __init__(self):
        self._A = np.zeros((3, POSE_DIM))
        self._M = np.zeros((3, 3))
        self._G = np.zeros((3, POSE_DIM))
        self._Si = np.zeros((3, 3))
        self._T = np.zeros((POSE_DIM, POSE_DIM))
        self._T2 = np.zeros((POSE_DIM, POSE_DIM))
        self._c0 = np.zeros(())             # 0-d operand: no temporary for a Python float
        self._half = np.full((), 0.5)

    def apply(self, P6, Hu, hu, current: float, var_amp: float, rel_model: float,
              current_sigma: float = 0.0) -> bool:
        A = self._A
        c0 = self._c0
        c0[()] = current
        np.matmul(Hu, P6, out=A)
        np.multiply(A, c0, out=A)
        np.matmul(A, Hu.T, out=self._M)
        np.multiply(self._M, c0, out=self._M)
        hn2 = float(hu[0] * hu[0] + hu[1] * hu[1] + hu[2] * hu[2])
        r = var_amp + (rel_model * rel_model * current * current + current_sigma * current_sigma) * hn2
        M = self._M
        inv = inv3_sym(M[0, 0] + r, M[0, 1], M[0, 2], M[1, 1] + r, M[1, 2], M[2, 2] + r)
        if inv is None:
            return False
        Si = self._Si
        Si[0, 0], Si[0, 1], Si[0, 2], Si[1, 1], Si[1, 2], Si[2, 2] = inv
        Si[1, 0], Si[2, 0], Si[2, 1] = inv[1], inv[2], inv[4]
        np.matmul(Si, A, out=self._G)
        np.matmul(A.T, self._G, out=self._T)
        np.subtract(P6, self._T, out=P6)
        # symmetrise
        np.copyto(self._T2, P6)
        np.add(self._T2, self._T2.T, out=P6)
        np.multiply(P6, self._half, out=P6)
        return True


def saturation_current_limit(hu, quiet, range_t: float, margin: float, gain: float) -> float:
    """Largest current (A) whose pulse keeps every magnetometer axis in range.

    ``hu`` (3,) is the predicted per-ampere coil field in the sensor frame,
    ``quiet`` (3,) the field without a pulse (earth field and any static
    disturbance, the latest quiet sample), ``range_t`` the magnetometer range,
    ``margin`` (< 1) the usable fraction of it and ``gain`` (>= 1) a factor on
    the predicted coil field for the position uncertainty (the field grows as
    ``r^-3`` towards the source). Per axis ``|quiet_k| + I gain |hu_k| <=
    margin range_t``, so either polarity and any orientation error within the
    predicted field is covered. Returns ``inf`` if no axis constrains it and 0
    if the quiet field alone is beyond the margin.
    """
    lim = margin * range_t
    best = math.inf
    for k in range(3):
        a = gain * abs(float(hu[k]))
        room = lim - abs(float(quiet[k]))
        if room <= 0.0:
            return 0.0
        if a > 0.0:
            i = room / a
            if i < best:
                best = i
    return best


class CoilChooser:
    """Which coil to pulse and with which current (Schepers sec. 2.1, eq 4).

    Parameters
    ----------
    n_coils : int
    currents : sequence of float
        Candidate currents in A (the driver's settable levels), any order;
        sorted ascending here.
    sigma_max, sigma_min : array_like (6,)
        Thresholds on the standard deviation of the pose variables
        ``(px, py, pz, theta_x, theta_y, theta_z)`` in m and rad.
    rel_model : float
        Relative field-model error added to the measurement covariance
        (``R_v += (rel_model |y|)^2``).
    current_sigma : float
        Std of the coil current (A): ``R_v += (current_sigma |hu|)^2``.
    step_a : float
        The driver's current resolution (A). 0: only the candidate currents are
        commanded. > 0 (the candidates are a ladder the firmware made, not the
        driver's only levels): the smallest current reaching ``sigma_min`` is
        refined between the ladder's rungs by bisection to this resolution
        (rounded up). A rung reached overshoots the goal by up to the ladder's
        step in ``I^2`` (47 % for 16 rungs from 0.05 to 0.91 A): the variance
        falls below ``sigma_min`` and the time mean below the bound held, an
        accuracy nobody asked for, paid in energy.

    After :meth:`choose`:

    ``coil``, ``current``
        the choice (``coil = -1`` if no coil may carry any current);
    ``target``
        index (0..5) of the pose variable whose uncertainty is the largest
        fraction of its ``sigma_max`` (the one that triggered the pulse);
    ``reduction`` (n_coils,)
        ``J(P-) - J(P+)`` of each coil at its reference current, with
        ``J(P) = sum_k P_kk / sigma_max_k^2``; ``-1`` for a coil that may
        carry no current;
    ``i_ref`` (n_coils,)
        the reference current of each coil: the largest candidate not above
        its limit;
    ``var_after`` (6,)
        predicted posterior pose variances of the choice;
    ``reached``
        whether the target variable is predicted to reach ``sigma_min``.
    """

    def __init__(self, n_coils: int, currents, sigma_max, sigma_min, rel_model: float = 0.0,
                 current_sigma: float = 0.0, trace: bool = False, step_a: float = 0.0, unreached_share: float = 0.0):
        #: bounds on the trace of the position and of the orientation block instead of each
        #: variable (the RMS of a position or orientation error is the root of its trace)
        self.trace = bool(trace)
        cur = sorted(float(c) for c in currents)
        if not cur or cur[0] <= 0.0:
            raise ValueError("candidate currents must be positive")
        self.n = int(n_coils)
        self.currents = np.array(cur)
        self.sigma_max = np.array(sigma_max, dtype=float).reshape(POSE_DIM)
        self.sigma_min = np.array(sigma_min, dtype=float).reshape(POSE_DIM)
        if np.any(self.sigma_min <= 0.0) or np.any(self.sigma_min > self.sigma_max):
            raise ValueError("need 0 < sigma_min <= sigma_max")
        self.weight = 1.0 / (self.sigma_max * self.sigma_max)
        self._smax0 = self.sigma_max.copy()
        self._smin0 = self.sigma_min.copy()
        self.rel_model = float(rel_model)
        self.current_sigma = float(current_sigma)
        self.step_a = float(step_a)
        #: > 0: when no allowed current reaches ``sigma_min``, the least current giving this share of
        #: the largest one's reduction (``unreached_goal``); 0: the largest allowed current
        self.unreached_share = float(unreached_share)
        self._A = np.zeros((self.n, 3, POSE_DIM))
        self._M = np.zeros((self.n, 3, 3))
        self.gain_var = np.zeros(self.n)      # each coil's gain variance (0: no term, add_gain_term)
        self._gvv = memoryview(self.gain_var)
        self._At = np.zeros((3, POSE_DIM))
        self._hn2 = np.zeros(self.n)
        self._var = np.zeros(POSE_DIM)
        self.reduction = np.zeros(self.n)
        self.i_ref = np.zeros(self.n)
        self.var_after = np.zeros(POSE_DIM)
        # memoryviews of the same buffers: their elements read as Python floats, whose
        # arithmetic costs a fifth of numpy scalars' (the same IEEE operations, the same bits)
        self._Av = tuple(memoryview(self._A[c]) for c in range(self.n))
        self._Mv = tuple(memoryview(self._M[c]) for c in range(self.n))
        self._wv = memoryview(self.weight)
        self._varv = memoryview(self._var)
        self._vav = memoryview(self.var_after)
        self.coil = -1
        self.current = 0.0
        self.length = 0           # choose_length: the index of the chosen pulse length
        self.target = 0
        self.reached = False

    def set_scale(self, pos: float, ori: float) -> None:
        """Scale the position and orientation thresholds (range-dependent
        accuracy, see ``ActuationPolicy.set_scale``)."""
        for k in range(3):
            self.sigma_max[k] = self._smax0[k] * pos
            self.sigma_min[k] = self._smin0[k] * pos
            self.sigma_max[3 + k] = self._smax0[3 + k] * ori
            self.sigma_min[3 + k] = self._smin0[3 + k] * ori
        for k in range(POSE_DIM):
            self.weight[k] = 1.0 / (self.sigma_max[k] * self.sigma_max[k])

    def set_bounds(self, sigma_max6, sigma_min6) -> None:
        """Set the thresholds (6,) directly (m, rad), e.g. from the fixed
        cycle's predicted accuracy (``coiltrack.firmware.actuate.accuracy``)."""
        for k in range(POSE_DIM):
            smax = float(sigma_max6[k])
            if not smax > 0.0:
                smax = 1e-12
            smin = float(sigma_min6[k])
            self.sigma_max[k] = smax
            self.sigma_min[k] = smin if 0.0 < smin <= smax else smax
            self.weight[k] = 1.0 / (smax * smax)
        if self.trace:
            for g in (0, 3):
                sm = self.sigma_max
                w = 1.0 / (sm[g] * sm[g] + sm[g + 1] * sm[g + 1] + sm[g + 2] * sm[g + 2])
                for k in range(g, g + 3):
                    self.weight[k] = w

    def _ref_index(self, limit: float) -> int:
        """Index of the largest candidate current <= limit, or -1."""
        cur = self.currents
        k = -1
        for j in range(cur.shape[0]):
            if cur[j] <= limit * (1.0 + 1e-12):
                k = j
            else:
                break
        return k

    def choose(self, P6, model: SingleCoilModel, var_amp: float, i_limit) -> int:
        """Choose the coil and the current for the next pulse.

        Parameters
        ----------
        P6 : ndarray (6, 6)
            Pose covariance predicted for the time of the measurement.
        model : SingleCoilModel
            Evaluated at the predicted pose.
        var_amp : float or ndarray (n_coils,)
            Variance of one pulse-amplitude component, T^2 (per coil: e.g.
            inflated where a coil's pulses proved inconsistent).
        i_limit : ndarray (n_coils,)
            Largest current each coil may carry now (A).

        Returns the chosen coil (also in ``self.coil``), or -1.
        """
        w = self._wv
        P6 = memoryview(P6)
        self._pick_target(P6)
        j0 = 0.0
        for k in range(POSE_DIM):
            j0 += P6[k, k] * w[k]
        best_c = -1
        best_red = -math.inf
        var = self._varv
        scalar = isinstance(var_amp, float)
        Hf = memoryview(model.H.reshape(-1))        # a view: coil c's row i from 18 c + 6 i
        for c in range(self.n):
            va = var_amp if scalar else float(var_amp[c])
            self._products(c, Hf, P6)
            hc = model.h[c]
            if self._gvv[c] > 0.0:
                self._gain_term(c, hc)
            self._hn2[c] = float(hc[0] * hc[0] + hc[1] * hc[1] + hc[2] * hc[2])
            k = self._ref_index(float(i_limit[c]))
            if k < 0:
                self.reduction[c] = -1.0
                self.i_ref[c] = 0.0
                continue
            i = float(self.currents[k])
            self.i_ref[c] = i
            posterior_pose_variances(P6, self._Av[c], self._Mv[c], float(self._hn2[c]), i, va, self.rel_model, var,
                                     self.current_sigma)
            j1 = 0.0
            for kk in range(POSE_DIM):
                j1 += var[kk] * w[kk]
            red = j0 - j1
            self.reduction[c] = red
            if red > best_red:
                best_red = red
                best_c = c
        self.reached = False
        self.coil = best_c
        if best_c < 0:
            self.current = 0.0
            for k in range(POSE_DIM):
                self.var_after[k] = P6[k, k]
            return -1
        return self._strength(P6, best_c, var_amp, i_limit)

    def _products(self, c: int, Hf, P6) -> None:
        """``A = Hu P6`` (3, 6) and ``M = A Hu^T`` (3, 3) of coil ``c`` (``Hu`` its per-ampere
        Jacobian, rows ``Hf[18 c + 6 i:]``), each sum over ``k`` in increasing order from its first
        term: the compiled chooser's order (``ct_products``), so the scores it compares are these to
        the bit (a product through numpy goes to the machine's BLAS, whose order is its own)."""
        A = self._Av[c]
        M = self._Mv[c]
        o = 18 * c
        u0, u1, u2, u3, u4, u5, v0, v1, v2, v3, v4, v5, w0, w1, w2, w3, w4, w5 = Hf[o:o + 18]   # Hu's rows
        for j in range(6):
            p0, p1, p2, p3, p4, p5 = P6[0, j], P6[1, j], P6[2, j], P6[3, j], P6[4, j], P6[5, j]
            A[0, j] = u0 * p0 + u1 * p1 + u2 * p2 + u3 * p3 + u4 * p4 + u5 * p5
            A[1, j] = v0 * p0 + v1 * p1 + v2 * p2 + v3 * p3 + v4 * p4 + v5 * p5
            A[2, j] = w0 * p0 + w1 * p1 + w2 * p2 + w3 * p3 + w4 * p4 + w5 * p5
        for i in range(3):
            a0, a1, a2, a3, a4, a5 = A[i, 0], A[i, 1], A[i, 2], A[i, 3], A[i, 4], A[i, 5]
            M[i, 0] = a0 * u0 + a1 * u1 + a2 * u2 + a3 * u3 + a4 * u4 + a5 * u5
            M[i, 1] = a0 * v0 + a1 * v1 + a2 * v2 + a3 * v3 + a4 * v4 + a5 * v5
            M[i, 2] = a0 * w0 + a1 * w1 + a2 * w2 + a3 * w3 + a4 * w4 + a5 * w5

    def set_gain_var(self, P, start: int) -> None:
        """:attr:`gain_var` from a ``CoilGainEKF``'s ``P`` (gain rows from ``start``: constant states)."""
        for c in range(self.n):
            v = float(P[start + c, start + c])
            self._gvv[c] = v if v > 0.0 else 0.0

    def _gain_term(self, c: int, hc) -> None:
        """Coil ``c``'s gain variance in its ``M`` (:func:`add_gain_term`)."""
        add_gain_term(self._Mv[c], self._gvv[c], float(hc[0]), float(hc[1]), float(hc[2]))

    def _pick_target(self, P6) -> None:
        """The pose variable (trace: the group, 0 or 3) furthest beyond its bound."""
        w = self._wv
        best_u = -1.0
        if self.trace:
            for g in (0, 3):
                u = (P6[g, g] + P6[g + 1, g + 1] + P6[g + 2, g + 2]) * w[g]
                if u > best_u:
                    best_u = u
                    self.target = g
        else:
            for k in range(POSE_DIM):
                u = P6[k, k] * w[k]
                if u > best_u:
                    best_u = u
                    self.target = k

    def _strength(self, P6, best_c: int, var_amp, i_limit) -> int:
        """How strong: the smallest current bringing the target variable to ``sigma_min``
        (the largest allowed if none does); sets ``current``, ``reached``, ``var_after``."""
        if not isinstance(var_amp, float):
            var_amp = float(var_amp[best_c])
        kmax = self._ref_index(float(i_limit[best_c]))
        goal = self._goal()
        j = self._smallest_current(P6, best_c, var_amp, kmax, goal)
        if j >= 0:
            self.current = self._refine(P6, best_c, var_amp, j, goal)
            self.reached = True
            return best_c
        if self.unreached_share > 0.0:
            # out of reach: the share of the largest current's reduction, at the least current
            # (``unreached_goal``); _smallest_current left the largest current's posterior in var_after
            g2 = self.unreached_goal(self._prior(P6), self._group_after())
            j = self._smallest_current(P6, best_c, var_amp, kmax, g2)
            if j >= 0:
                self.current = self._refine(P6, best_c, var_amp, j, g2)
                return best_c
        self.current = float(self.currents[kmax])
        posterior_pose_variances(P6, self._Av[best_c], self._Mv[best_c], float(self._hn2[best_c]), self.current,
                                 var_amp, self.rel_model, self._vav, self.current_sigma)
        return best_c

    def unreached_goal(self, prior: float, best: float) -> float:
        """The target's variance asked of a pulse when no allowed current brings it to
        ``sigma_min``: ``best + (1 - share) (prior - best)``, i.e. ``unreached_share`` of the
        reduction the largest allowed current gives (``best`` its posterior). The eq-4
        information of a pulse, ``I^2 / (a + b I^2)`` per ``I^2`` of energy, falls as the current
        grows (the field model's error ``b``, ``estimate.single_coil``), and where one coil's
        pulse cannot reach the goal at all (directions it does not see) the last amperes buy
        almost nothing: the reduction's last part costs the most."""
        return best + (1.0 - self.unreached_share) * (prior - best)

    def _prior(self, P6) -> float:
        t = self.target
        v = 0.0
        for k in range(t, t + 3 if self.trace else t + 1):
            v += P6[k, k]
        return v

    def _group_after(self) -> float:
        t = self.target
        v = 0.0
        for k in range(t, t + 3 if self.trace else t + 1):
            v += self._vav[k]
        return v

    def _goal(self) -> float:
        """``sigma_min^2`` of the target variable (trace: summed over its group)."""
        t = self.target
        goal = 0.0
        for k in range(t, t + 3 if self.trace else t + 1):
            goal += self.sigma_min[k] * self.sigma_min[k]
        return goal

    def _smallest_current(self, P6, c: int, var_amp: float, kmax: int, goal: float) -> int:
        """Index of the smallest candidate current up to ``kmax`` whose eq-4 update of coil
        ``c`` (amplitude variance ``var_amp``) brings the target variable to ``sigma_min``
        (``var_after`` holds its posterior), or -1."""
        t = self.target
        t1 = t + 3 if self.trace else t + 1
        A = self._Av[c]
        M = self._Mv[c]
        hn2 = float(self._hn2[c])
        for j in range(kmax + 1):
            i = float(self.currents[j])
            posterior_pose_variances(P6, A, M, hn2, i, var_amp, self.rel_model, self._vav,
                                     self.current_sigma)
            va = 0.0
            for k in range(t, t1):
                va += self._vav[k]
            if va <= goal:
                return j
        return -1

    def _target_after(self, P6, c: int, var_amp: float, i: float) -> float:
        """The target's posterior variance (trace: summed over its group) after coil ``c`` at
        ``i`` A; ``var_after`` holds the posterior."""
        posterior_pose_variances(P6, self._Av[c], self._Mv[c], float(self._hn2[c]), i, var_amp, self.rel_model,
                                 self._vav, self.current_sigma)
        t = self.target
        va = 0.0
        for k in range(t, t + 3 if self.trace else t + 1):
            va += self._vav[k]
        return va

    def _refine(self, P6, c: int, var_amp: float, j: int, goal: float) -> float:
        """The smallest current (to ``step_a``, rounded up) between rung ``j - 1`` (0 A for the
        first) and rung ``j``, which reaches the goal, of coil ``c``; ``var_after`` holds its
        posterior. Bisection: the posterior variance falls monotonically with the current (eq 4:
        ``S^-1`` shrinks as the information ``I^2 / (a + b I^2)`` grows). Rung ``j`` itself
        without a resolution."""
        hi = float(self.currents[j])
        step = self.step_a
        if not step > 0.0:
            return hi
        lo = float(self.currents[j - 1]) if j > 0 else 0.0
        while hi - lo > step:
            mid = 0.5 * (lo + hi)
            if self._target_after(P6, c, var_amp, mid) <= goal:
                hi = mid
            else:
                lo = mid
        i = math.ceil(hi / step - 1e-9) * step
        if i > float(self.currents[j]):
            i = float(self.currents[j])
        self._target_after(P6, c, var_amp, i)
        return i

    def choose_length(self, P6, model: SingleCoilModel, var_amps, lengths_us, i_limit) -> int:
        """:meth:`choose` with the pulse length as a lever too (``pulse_length = "chosen"``).

        ``var_amps`` (one per length, T^2, already scaled by the NIS inflation) and
        ``lengths_us``, shortest first. The coil is the one whose update at its largest
        current and the longest length (the most information it can bring) reduces the
        normalised uncertainty most; then, over every length, the smallest current bringing
        the target variable to its goal, and of those the pair of least energy ``I^2 L``
        (the coil's resistance is common to all). The goal is ``sigma_min``; where the
        longest length at the largest current does not reach it, with ``unreached_share``
        the share of that pulse's reduction (``unreached_goal``, as :meth:`choose` asks of
        the longest), so an unreached pulse is as short as the goal allows too; without it,
        the longest length at the largest current (the most a pulse can bring). The
        information of each pair is eq 4 (Schepers & Veltink 2010,
        ``seeds/000_e46ec0e8bf7ea271.txt``) with the length's amplitude variance and the
        model error ``(rel_model I |h|)^2``, which saturates it near the source: the current
        a goal needs then obeys ``I^2 = k var / (1 - k rel^2)``, still proportional to
        ``var(L)``, so the energies of the lengths keep the ratios of ``L var(L)``;
        saturation decides only whether the goal is reachable. Sets ``length`` (an index of
        ``lengths_us``) beside ``coil`` and ``current``; returns the coil or -1."""
        last = len(lengths_us) - 1
        c = self.choose(P6, model, float(var_amps[last]), i_limit)
        self.length = last
        if c < 0:
            return c
        P6v = memoryview(P6)
        kmax = self._ref_index(float(i_limit[c]))
        if self.reached:
            goal = self._goal()
        elif self.unreached_share > 0.0 and kmax >= 0:
            goal = self.unreached_goal(self._prior(P6v), self._target_after(P6v, c, float(var_amps[last]),
                                                                           float(self.currents[kmax])))
        else:
            return c
        best_e = self.current * self.current * lengths_us[last]
        for k in range(last):
            j = self._smallest_current(P6v, c, float(var_amps[k]), kmax, goal)
            if j < 0:
                continue
            i = self._refine(P6v, c, float(var_amps[k]), j, goal)
            e = i * i * lengths_us[k]
            if e < best_e:
                best_e = e
                self.length = k
                self.current = i
        posterior_pose_variances(P6v, self._Av[c], self._Mv[c], float(self._hn2[c]), self.current,
                                 float(var_amps[self.length]), self.rel_model, self._vav, self.current_sigma)
        return c


class CompiledCoilChooser(CoilChooser):
    """:class:`CoilChooser` through the compiled kernels (``sc_choose.c``: ``ct_choose``,
    ``ct_choose_length``, ``ct_set_bounds``), bit for bit: the same products, scores, comparisons and bisection, so
    the same coil, current and length. The reference's arrays are bound once; the choice's state
    (``coil``, ``current``, ``length``, ``target``, ``reached``) lives in one array read and written
    through properties under the reference's names. A per-coil ``var_amp`` (an array), or more than ``CH_MAXLEN`` (64) pulse
    lengths, take the reference's path. ``ext``: the extension module (``coiltrack.firmware.core.Core.ext``)."""

    def __init__(self, ext, n_coils: int, currents, sigma_max, sigma_min, rel_model: float = 0.0,
                 current_sigma: float = 0.0, trace: bool = False, step_a: float = 0.0, unreached_share: float = 0.0):
        self._st = np.zeros(ext.CH_NST)
        self._stv = memoryview(self._st)
        self._maxlen = ext.CH_MAXLEN             # more pulse lengths: the reference's path
        super().__init__(n_coils, currents, sigma_max, sigma_min, rel_model, current_sigma, trace, step_a,
                         unreached_share)
        self._ck = ext.ChooserCore(self.n, (self.currents, self.sigma_max, self.sigma_min, self.weight, self._A, self._M, self._hn2,
                                            self.reduction, self.i_ref, self._var, self.var_after, self._st,
                                            self.gain_var),
                                   self.rel_model, self.current_sigma, self.step_a, self.unreached_share, self.trace)
        self.set_bounds = self._ck.set_bounds        # one call, no Python layer

    @property
    def coil(self) -> int:
        return int(self._stv[0])

    @coil.setter
    def coil(self, v) -> None:
        self._stv[0] = float(v)

    @property
    def current(self) -> float:
        return self._stv[1]

    @current.setter
    def current(self, v) -> None:
        self._stv[1] = float(v)

    @property
    def length(self) -> int:
        return int(self._stv[2])

    @length.setter
    def length(self, v) -> None:
        self._stv[2] = float(v)

    @property
    def target(self) -> int:
        return int(self._stv[3])

    @target.setter
    def target(self, v) -> None:
        self._stv[3] = float(v)

    @property
    def reached(self) -> bool:
        return self._stv[4] != 0.0

    @reached.setter
    def reached(self, v) -> None:
        self._stv[4] = 1.0 if v else 0.0

    def choose(self, P6, model: SingleCoilModel, var_amp: float, i_limit) -> int:
        if not isinstance(var_amp, float):
            return super().choose(P6, model, var_amp, i_limit)
        return self._ck.choose(P6, model.h, model.H, i_limit, var_amp)

    def choose_length(self, P6, model: SingleCoilModel, var_amps, lengths_us, i_limit) -> int:
        if len(lengths_us) > self._maxlen:
            return super().choose_length(P6, model, var_amps, lengths_us, i_limit)
        return self._ck.choose_length(P6, model.h, model.H, i_limit, var_amps, lengths_us)


def coil_chooser(core, n_coils: int, currents, sigma_max, sigma_min, rel_model: float = 0.0,
                 current_sigma: float = 0.0, trace: bool = False, step_a: float = 0.0,
                 unreached_share: float = 0.0) -> CoilChooser:
    """The chooser on the numeric core ``core`` (chosen at composition): :class:`CompiledCoilChooser`
    where the extension is built, else the reference :class:`CoilChooser`."""
    if core.ext is not None:
        return CompiledCoilChooser(core.ext, n_coils, currents, sigma_max, sigma_min, rel_model, current_sigma, trace,
                                   step_a, unreached_share)
    return CoilChooser(n_coils, currents, sigma_max, sigma_min, rel_model, current_sigma, trace, step_a,
                       unreached_share)


class ActuationPolicy:
    """When to pulse (Schepers sec. 2.1, Fig. 1).

    A pulse is due when, for the covariance predicted at the time the pulse
    would be measured, some pose variable has ``sqrt(P_kk) >= sigma_max_k``,
    or when the last magnetic update is older than ``max_interval_us``
    (regular updates limit the linearisation error, Schepers sec. 4).
    """

    def __init__(self, sigma_max, max_interval_us: int, trace: bool = False):
        #: bound the trace of the position and of the orientation block (sum of the three
        #: variances against the sum of the three bounds) instead of each variable
        self.trace = bool(trace)
        self.sigma_max = np.array(sigma_max, dtype=float).reshape(POSE_DIM)
        self.var_max = self.sigma_max * self.sigma_max
        self._var0 = self.var_max.copy()
        self.max_interval_us = int(max_interval_us)
        self.reason = 0   # 0 none, 1 uncertainty, 2 interval

    def set_scale(self, pos: float, ori: float) -> None:
        """Multiply the position and orientation bounds by ``pos`` and
        ``ori`` (e.g. ``(r / r_ref)^k``: an accuracy specified relative to
        the range, as tracker accuracies usually are; a pulse carries
        ``r^-8`` less position information per joule at range ``r``)."""
        for k in range(3):
            self.var_max[k] = self._var0[k] * pos * pos
            self.var_max[3 + k] = self._var0[3 + k] * ori * ori

    def set_bounds(self, sigma_max6) -> None:
        """Set the bounds (6,) directly (m, rad)."""
        for k in range(POSE_DIM):
            v = float(sigma_max6[k])
            self.var_max[k] = v * v if v > 0.0 else 1e-24

    def worst(self, P6) -> float:
        """``max_k sqrt(P_kk) / sigma_max_k`` (1 = at the bound)."""
        u = 0.0
        vm = self.var_max
        if self.trace:
            for g in (0, 3):
                x = (P6[g, g] + P6[g + 1, g + 1] + P6[g + 2, g + 2]) / (vm[g] + vm[g + 1] + vm[g + 2])
                if x > u:
                    u = x
            return math.sqrt(u)
        for k in range(POSE_DIM):
            x = P6[k, k] / vm[k]
            if x > u:
                u = x
        return math.sqrt(u)

    def due(self, P6_pred, now_us: int, last_update_us: int) -> bool:
        vm = self.var_max
        if self.trace:
            for g in (0, 3):
                if not (P6_pred[g, g] + P6_pred[g + 1, g + 1] + P6_pred[g + 2, g + 2]
                        < vm[g] + vm[g + 1] + vm[g + 2]):
                    self.reason = 1
                    return True
        else:
            for k in range(POSE_DIM):
                if not P6_pred[k, k] < vm[k]:     # also catches NaN
                    self.reason = 1
                    return True
        if now_us - last_update_us >= self.max_interval_us:
            self.reason = 2
            return True
        self.reason = 0
        return False


class NisMonitor:
    """Normalised innovation squared: per-update gate and windowed test.

    ``add(nis)`` records the NIS of one update computed with the nominal
    measurement covariance (``dof`` degrees of freedom each). The update is
    *gated* (rejected) when its NIS with the currently used covariance
    exceeds ``gate`` (chi-square quantile, default 3 dof at 99.9 %: 16.27).
    The filter is *inconsistent* when the mean of the last ``window`` NIS
    values exceeds the upper ``z`` quantile of ``chi2(dof n) / n`` (at least
    ``min_count`` values) and is at least ``min_excess`` times its
    expectation ``dof`` (a disturbance worth flagging, not a cluster of
    chi-square tails from a brief model mismatch); it stays so until the
    mean is back within the chi-square bound (hysteresis: with the
    covariance inflated the filter follows the biased pulses, the NIS
    drops, and leaving at the entry level would switch the inflation off
    while the disturbance is still there). While inconsistent, ``r_scale``
    (>= 1) is the factor the measurement covariance is multiplied by: the
    observed excess ``mean / dof`` (covariance matching), capped at
    ``max_scale``. ``excess`` (:meth:`add_used`) is the long-run mean of
    ``NIS / dof`` with the covariance actually used: above 1 the filter's
    covariance understates its errors, and the policy holds a smaller one
    (``accuracy.nis_bound_factor``).
    """

    def __init__(self, window: int = 8, dof: int = 3, gate: float = 16.27, z: float = 2.326,
                 min_count: int = 4, max_scale: float = 1e4, min_excess: float = 1.0,
                 feedback_updates: int = 30):
        if window < 1 or min_count < 1 or min_count > window:
            raise ValueError("need 1 <= min_count <= window")
        self.window = int(window)
        self.dof = int(dof)
        self.gate = float(gate)
        self.z = float(z)
        self.min_count = int(min_count)
        self.max_scale = float(max_scale)
        self.min_mean = float(min_excess) * self.dof
        self._buf = np.zeros(self.window)
        self._bound = np.array([chi2_upper(self.dof * n, self.z) / n if n else math.inf
                                for n in range(self.window + 1)])
        self.count = 0
        self._head = 0
        self.mean = float(self.dof)
        self.inconsistent = False
        self.r_scale = 1.0
        self.total = 0
        self.gated = 0
        self.flagged = 0      # updates made while inconsistent
        #: exponential mean of ``NIS / dof`` over about ``feedback_updates`` updates, with the
        #: measurement covariance actually used (:meth:`add_used`): 1 for a consistent filter
        self.excess = 1.0
        self._alpha = 1.0 / max(1, int(feedback_updates))
        self.excess_gate = float(gate)

    def reset(self) -> None:
        self.count = 0
        self._head = 0
        self.mean = float(self.dof)
        self.inconsistent = False
        self.r_scale = 1.0
        self.excess = 1.0

    def add_used(self, nis_used: float) -> None:
        """Record the NIS of one update with the covariance the filter used (the
        inflated one while disturbed), capped at the gate (a rejected pulse
        counts as the largest accepted one), into :attr:`excess`."""
        x = nis_used if nis_used < self.excess_gate else self.excess_gate
        if not x >= 0.0:                      # NaN
            x = self.excess_gate
        if x == math.inf:
            x = 10.0 * self.dof * self.max_scale
        self.excess += self._alpha * (x / self.dof - self.excess)

    def note_gated(self) -> None:
        """One update was rejected by the gate (counted in :attr:`gated`)."""
        self.gated += 1

    def bound(self) -> float:
        n = self.count
        return float(self._bound[n]) if n else math.inf

    def add(self, nis_nominal: float) -> None:
        if not math.isfinite(nis_nominal):
            nis_nominal = 1e9
        self._buf[self._head] = nis_nominal
        self._head = (self._head + 1) % self.window
        if self.count < self.window:
            self.count += 1
        s = 0.0
        for k in range(self.count):
            s += float(self._buf[k])
        self.mean = s / self.count
        self.total += 1
        beyond = self.count >= self.min_count and self.mean > float(self._bound[self.count])
        self.inconsistent = bool(beyond and (self.inconsistent or self.mean > self.min_mean))
        if self.inconsistent:
            self.flagged += 1
            self.r_scale = min(max(self.mean / self.dof, 1.0), self.max_scale)
        else:
            self.r_scale = 1.0
