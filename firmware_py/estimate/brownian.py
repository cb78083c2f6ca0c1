"""Gietler's Brownian-motion tracker: the 12-state model and its (iterated) EKF.

Gietler et al. 2019, ``seeds/003_93f59c2e1c5b6c59.txt``:

Model (eqs 6-12)
    State ``X = [v, z, omega, theta]`` (eq 11, :data:`~coiltrack.firmware.estimate.layout.BROWNIAN_LAYOUT`),
    velocity and Euler-angle rate Wiener processes of intensities ``sigma_v``
    (m s^-3/2) and ``sigma_w`` (rad s^-3/2) (eqs 6-7), sampled every ``dt``:
    ``X_t = F X_{t-1} + U_t`` (eqs 12-13) with ``F = [[I, 0, 0, 0], [dt I, I, 0, 0],
    [0, 0, I, 0], [0, 0, dt I, I]]`` and ``U_t ~ N(0, Sigma)``, eq 10:
    per axis ``sigma^2 [[dt, dt^2/2], [dt^2/2, dt^3/3]]`` for ``(v, z)`` and
    ``(omega, theta)``.

Measurement (eq 14)
    ``V_t = h(z_t, theta_t) + W_t``, ``W_t ~ N(0, noise_var I)`` ((A/m)^2), with
    ``h`` the base model ``H0`` (eq 1) or the extended model ``H0 + H~`` (eq 32)
    of :class:`coiltrack.firmware.model.emitters.PlatformModel`.

Filter (eqs 17-24)
    Prediction ``x = F x``, ``P = F P F^T + Sigma`` (eqs 18, 20, through the one
    :class:`~coiltrack.firmware.estimate.ekf.CovariancePredict`); update through the
    one :class:`~coiltrack.firmware.estimate.ekf.KalmanUpdate` (eqs 21-23, the
    covariance in Joseph form instead of eq 24, no gate: the paper has none).

    ``iterations = 1`` is the EKF of the paper. ``iterations > 1`` is the
    iterated EKF (Gauss-Newton on the posterior): at iterate ``x_i`` the
    measurement is relinearised, ``y = V - h(x_i) - H_i (x^- - x_i)`` and
    ``x_{i+1} = x^- + K_i y`` with ``K_i`` and the Joseph update from the
    predicted ``P^-``; it stops when no state moves by more than ``tol``
    (the last iterate's ``P`` is kept). Each iterate costs one evaluation of
    every source of the model.

    The noise is white and uncorrelated between components (``R = noise_var I``),
    so at a given linearisation point the ``m`` rows are applied as ``m / 3``
    sequential 3-row updates (one per emitter and, at AC, per real or imaginary
    part): the same posterior as one ``m``-row update, through the closed-form
    3 x 3 inverse of the update instead of an ``m x m`` Cholesky factorisation.
    Block ``b`` sees the innovation ``V_b - h_b(x_i) - H_b (x^- + dx - x_i)``
    with ``dx`` the correction of the blocks before it.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.estimate.ekf import EKF_OK, CovariancePredict, KalmanUpdate
from coiltrack.firmware.estimate.layout import BROWNIAN_LAYOUT as L


def transition(dt: float) -> np.ndarray:
    """``F`` of eq 12 (12, 12)."""
    F = np.eye(L.n)
    F[L.POS, L.VEL] = dt * np.eye(3)
    F[L.THETA, L.RATE] = dt * np.eye(3)
    return F


def process_covariance(dt: float, sigma_v: float, sigma_w: float) -> np.ndarray:
    """``Sigma`` of eq 10 (12, 12), in the state order of eq 11."""
    Q = np.zeros((L.n, L.n))
    I3 = np.eye(3)
    for vel, pos, s in ((L.VEL, L.POS, sigma_v), (L.RATE, L.THETA, sigma_w)):
        s2 = s * s
        Q[vel, vel] = s2 * dt * I3
        Q[vel, pos] = Q[pos, vel] = s2 * dt * dt / 2.0 * I3
        Q[pos, pos] = s2 * dt ** 3 / 3.0 * I3
    return Q


class BrownianEKF:
    """EKF (``iterations = 1``) or iterated EKF on the Brownian-motion model.

    ``model``: a :class:`~coiltrack.firmware.model.emitters.PlatformModel`;
    ``dt`` (s), ``sigma_v``, ``sigma_w``, ``noise_var`` ((A/m)^2 per measured
    component). :meth:`reset` sets ``x`` (12,) and ``P`` (12, 12);
    :meth:`step` predicts one ``dt`` and applies a measurement (m,).
    """

    def __init__(self, model, dt: float, sigma_v: float, sigma_w: float, noise_var: float,
                 iterations: int = 1, tol: float = 1e-6):
        if iterations < 1:
            raise ValueError("iterations must be >= 1")
        self.model = model
        self.iterations = int(iterations)
        self.tol = float(tol)
        m = model.m
        self.x = np.zeros(L.n)
        self.P = np.eye(L.n)
        self.pred = CovariancePredict(L.n)
        self.pred.A[:] = transition(dt)
        self.pred.Q[:] = process_covariance(dt, sigma_v, sigma_w)
        if m % 3:
            raise ValueError("the measurement has 3 rows per block")
        self.ku = KalmanUpdate(L.n, 3, gate_probability=1.0)
        self.ku.R[:] = noise_var * np.eye(3)
        self._H = np.zeros((m, L.n))
        self._r = np.zeros(m)
        self._dx = np.zeros(L.n)
        self._h = np.zeros(m)
        self._Hm = np.zeros((m, 6))
        self._xp = np.zeros(L.n)
        self._xi = np.zeros(L.n)
        self._xn = np.zeros(L.n)
        self._Pp = np.zeros((L.n, L.n))
        self._d = np.zeros(L.n)
        self.iterations_last = 0
        self.iterations_total = 0
        self.flags = EKF_OK

    def reset(self, x0, P0) -> None:
        self.x[:] = x0
        self.P[:] = P0

    def predict(self) -> None:
        """Eqs 18 and 20."""
        np.matmul(self.pred.A, self.x, out=self._xn)
        self.x[:] = self._xn
        self.pred.predict(self.P)

    def update(self, V) -> int:
        """Eqs 19, 21-23 (iterated when ``iterations > 1``); the health flags of the last update
        (non-zero when a block was refused, whose rows are then left out)."""
        ku = self.ku
        H, r, dx = self._H, self._r, self._dx
        xp, xi, xn, d = self._xp, self._xi, self._xn, self._d
        xp[:] = self.x
        xi[:] = xp
        self._Pp[:] = self.P
        flags = EKF_OK
        for it in range(self.iterations):
            self.model.measure(xi[L.POS], xi[L.THETA], self._h, self._Hm)
            H[:, L.POS] = self._Hm[:, 0:3]
            H[:, L.THETA] = self._Hm[:, 3:6]
            # r = V - h(x_i) - H (x^- - x_i): the residual of the linearised model at x^-
            np.subtract(xp, xi, out=d)
            np.matmul(H, d, out=r)
            np.subtract(V, r, out=r)
            np.subtract(r, self._h, out=r)
            self.P[:] = self._Pp
            dx.fill(0.0)
            flags = EKF_OK
            for b in range(0, self.model.m, 3):
                ku.H[:] = H[b:b + 3]
                np.matmul(ku.H, dx, out=ku.y)
                np.subtract(r[b:b + 3], ku.y, out=ku.y)
                f = ku.update(self.P)
                flags |= f
                if f == EKF_OK:
                    np.add(dx, ku.dx, out=dx)
            np.add(xp, dx, out=xn)
            np.subtract(xn, xi, out=d)
            xi[:] = xn
            if float(np.max(np.abs(d))) <= self.tol:
                break
        self.flags = flags
        self.iterations_last = it + 1
        self.iterations_total += it + 1
        self.x[:] = xi
        return flags

    def step(self, V) -> int:
        self.predict()
        return self.update(V)
