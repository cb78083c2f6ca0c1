"""Gietler's measurement model: point sources on a moving platform, one fixed receiver.

A documented dipole form of the one signal model (``model/signal.py`` gives
``h = R^T B(p)`` for a moving sensor and fixed coils; here the sources move
and the receiver is fixed, which is the same relative geometry seen from the
other side: ``h(z, R) = sum_s f(x_r - z - R o_s, R mu_s)``). Gietler et al.
2019, ``seeds/003_93f59c2e1c5b6c59.txt``:

Sources (all rigidly attached to the platform, platform frame)
    ``o_s`` (m, (S, 3)) offset from the platform origin (emitter 1), ``mu_s``
    complex moment phasor, and a kind:

    * dipole (eq 1), ``mu_s`` in A m^2:
      ``f = (1 / 4 pi) (3 r (m . r) / |r|^5 - m / |r|^3)`` (A/m);
    * current element (eq 31, first term), ``mu_s = H~_Ci``, the integral of
      ``curl H~`` over a sub-volume (A m): ``f = grad_x G x C = C x r / (4 pi |r|^3)``
      with ``G = 1 / (4 pi |x - y|)`` (eq 28).

    The emitters are dipoles of 1 A m^2; the compensation of a conductive or
    ferromagnetic object fixed to the platform (eqs 27-32) adds, per emitter,
    the precomputed sub-volume terms: current elements ``H~_Ci`` and, for the
    second term of eq 31, ``(1 - mu*/mu0) (H_i . grad_y) grad_x G`` which is the
    dipole field of the moment ``(mu*/mu0 - 1) H_i`` (the integral of the
    magnetisation over ``B_i``), so it is a dipole source here.
    ``H = H0 + H~`` (eq 32).

Pose
    ``z`` (m) is the platform origin in the receiver frame, ``theta`` (rad) the
    Z-Y-X Euler angles, ``R = Rz(theta_3) Ry(theta_2) Rx(theta_1)`` (eqs 3-4).
    In the receiver frame a source sits at ``y_s = z + R o_s`` with moment
    ``R mu_s`` (eq 2, ``m = R m'``), ``r_s = x_r - y_s``. With the receiver
    moving and the emitters fixed the same model tracks the emitters' pose in
    the receiver's frame (the receiver's pose is its inverse).

Measurement
    Each channel (an emitter, time-multiplexed) gives the field phasor at the
    receiver, 3 components. DC (``ac=False``): ``h`` is the real field,
    ``3 n_ch`` rows; AC (a synchronous receiver, eddy-current phase, ``ac=True``):
    the real parts then the imaginary parts, ``6 n_ch`` rows (A/m).

Jacobian (``m x 6``, columns ``(dz, dtheta)``)
    ``dh/dz = -sum_s df/dr``,
    ``dh/dtheta_k = sum_s (-df/dr (dR/dtheta_k) o_s + A_s (dR/dtheta_k) mu_s)``
    with ``f = A_s(r) m`` linear in the moment (``A = (3 r r^T / |r|^2 - I) / (4 pi |r|^3)``
    for a dipole, ``-[r]x / (4 pi |r|^3)`` for a current element) and
    ``df/dr`` the closed forms of :meth:`PlatformModel._dipoles` and
    :meth:`PlatformModel._currents`.

Work: one *field evaluation* is one source's field and gradient at the
receiver (:attr:`PlatformModel.evals`). All arrays are sized at construction;
an evaluation allocates numpy temporaries (it is not part of the 1 kHz tick).
"""
from __future__ import annotations

import math

import numpy as np

DIPOLE = 0
CURRENT = 1
_INV4PI = 1.0 / (4.0 * math.pi)


def euler_zyx(theta, out=None, d_out=None):
    """``R = Rz(t3) Ry(t2) Rx(t1)`` (eqs 3-4), (3, 3), written into ``out``; with ``d_out``
    (3, 3, 3) also ``d_out[k] = dR / dtheta_k`` (the products of eq 4 multiplied out)."""
    a, b, c = float(theta[0]), float(theta[1]), float(theta[2])
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    R = np.empty((3, 3)) if out is None else out
    R.flat[:] = (cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa,
                 sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa,
                 -sb, cb * sa, cb * ca)
    if d_out is not None:
        d_out.flat[:] = (0.0, cc * sb * ca + sc * sa, -cc * sb * sa + sc * ca,
                         0.0, sc * sb * ca - cc * sa, -sc * sb * sa - cc * ca,
                         0.0, cb * ca, -cb * sa,
                         -cc * sb, cc * cb * sa, cc * cb * ca,
                         -sc * sb, sc * cb * sa, sc * cb * ca,
                         -cb, -sb * sa, -sb * ca,
                         -sc * cb, -sc * sb * sa - cc * ca, -sc * sb * ca + cc * sa,
                         cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa,
                         0.0, 0.0, 0.0)
    return R


class PlatformModel:
    """Sources on the platform, per channel; :meth:`measure` gives ``h`` and ``H``.

    ``offsets`` (S, 3) m, ``moments`` (S, 3) complex, ``kinds`` (S,) of
    :data:`DIPOLE` / :data:`CURRENT`, ``channels`` (S,) in ``0..n_channels-1``;
    ``receiver`` (3,) m, the receiver's position in its own frame (default origin).
    """

    def __init__(self, offsets, moments, kinds, channels, n_channels: int, ac: bool,
                 receiver=(0.0, 0.0, 0.0)):
        o = np.asarray(offsets, dtype=float).reshape(-1, 3)
        mu = np.asarray(moments, dtype=complex).reshape(-1, 3)
        k = np.asarray(kinds, dtype=int).reshape(-1)
        ch = np.asarray(channels, dtype=int).reshape(-1)
        if not (len(o) == len(mu) == len(k) == len(ch)) or len(o) == 0:
            raise ValueError("offsets, moments, kinds and channels need one row per source")
        if np.any((ch < 0) | (ch >= n_channels)) or np.any((k != DIPOLE) & (k != CURRENT)):
            raise ValueError("a channel or kind is out of range")
        self.n_channels = n_channels
        self.ac = bool(ac)
        self.m = (6 if ac else 3) * n_channels
        self.n_sources = len(o)
        self.receiver = np.asarray(receiver, dtype=float).reshape(3)
        # real moments (DC, or AC without an object's phase) are evaluated in real arithmetic
        dtype = complex if np.any(mu.imag != 0.0) else float
        mu = mu.astype(dtype) if dtype is complex else mu.real.copy()
        self._groups = []
        for kind in (DIPOLE, CURRENT):
            sel = k == kind
            if np.any(sel):
                onehot = np.zeros((n_channels, int(sel.sum())))
                onehot[ch[sel], np.arange(int(sel.sum()))] = 1.0
                self._groups.append((kind, o[sel].copy(), mu[sel].copy(), onehot))
        self._R = np.zeros((3, 3))
        self._dR = np.zeros((3, 3, 3))
        self._F = np.zeros((n_channels, 3), dtype=dtype)
        self._J = np.zeros((n_channels, 3, 6), dtype=dtype)
        self.evals = 0

    # -- the two kinds of source: field f (S, 3), df/dr (S, 3, 3) and A(r) (S, 3, 3)

    @staticmethod
    def _dipoles(r, m):
        r2 = np.einsum("si,si->s", r, r)
        inv3 = _INV4PI / (r2 * np.sqrt(r2))
        mr = np.einsum("si,si->s", r, m)
        f = (3.0 * r * (mr / r2)[:, None] - m) * inv3[:, None]
        eye = np.eye(3)
        rr = r[:, :, None] * r[:, None, :]
        jr = (3.0 * (eye[None] * mr[:, None, None] + r[:, :, None] * m[:, None, :] + m[:, :, None] * r[:, None, :])
              - 15.0 * rr * (mr / r2)[:, None, None]) * (inv3 / r2)[:, None, None]
        A = (3.0 * rr / r2[:, None, None] - eye[None]) * inv3[:, None, None]
        return f, jr, A

    @staticmethod
    def _currents(r, c):
        r2 = np.einsum("si,si->s", r, r)
        inv3 = _INV4PI / (r2 * np.sqrt(r2))
        f = np.cross(c, r) * inv3[:, None]
        jr = _skew(c) * inv3[:, None, None] - 3.0 * f[:, :, None] * (r / r2[:, None])[:, None, :]
        A = -_skew(r) * inv3[:, None, None]
        return f, jr, A

    def field_phasors(self, z, theta, jac: bool = True):
        """Per-channel field phasor at the receiver (n_channels, 3), complex, A/m; with
        ``jac`` also its derivatives (n_channels, 3, 6) over ``(dz, dtheta)``."""
        R = euler_zyx(theta, self._R, self._dR if jac else None)
        z = np.asarray(z, dtype=float)
        F, J = self._F, self._J
        F.fill(0.0)
        J.fill(0.0)
        for kind, o, mu, onehot in self._groups:
            ro = o @ R.T
            r = (self.receiver - z)[None, :] - ro
            m = mu @ R.T
            f, jr, A = (self._dipoles if kind == DIPOLE else self._currents)(r, m)
            F += onehot @ f
            if jac:
                S = len(o)
                J[:, :, 0:3] -= (onehot @ jr.reshape(S, 9)).reshape(-1, 3, 3)
                dRt = self._dR.transpose(0, 2, 1)
                do = np.matmul(o[None], dRt)                        # (3, S, 3): dR_k o_s
                dm = np.matmul(mu[None], dRt)                       # (3, S, 3): dR_k mu_s
                col = np.matmul(A[None], dm[..., None]) - np.matmul(jr[None], do[..., None])  # (3, S, 3, 1)
                J[:, :, 3:6] += (onehot @ col[..., 0].transpose(1, 0, 2).reshape(S, 9)).reshape(-1, 3, 3).transpose(0, 2, 1)
            self.evals += len(o)
        return F, (J if jac else None)

    def measure(self, z, theta, h, H=None) -> None:
        """``h`` (m,) and, when given, ``H`` (m, 6) over ``(dz, dtheta)``, written in place."""
        F, J = self.field_phasors(z, theta, H is not None)
        n3 = 3 * self.n_channels
        h[0:n3] = F.real.reshape(-1)
        if self.ac:
            h[n3:2 * n3] = F.imag.reshape(-1) if np.iscomplexobj(F) else 0.0
        if H is not None:
            H[0:n3] = J.real.reshape(n3, 6)
            if self.ac:
                H[n3:2 * n3] = J.imag.reshape(n3, 6) if np.iscomplexobj(J) else 0.0


def _skew(v):
    """``[v]x`` for each row of ``v`` (S, 3) -> (S, 3, 3)."""
    out = np.zeros(v.shape[:-1] + (3, 3), dtype=v.dtype)
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out
