"""Fixed-interval Rauch-Tung-Striebel smoothing of the fusion filter (offline).

Roetenberg thesis (``002_cd7f1fdb7fc67471.txt``) sec 4.2.5: the forward
Kalman filter saves its a-priori and a-posteriori estimates and covariances
at every step; a backward sweep from the last step computes

    x_s(t) = x(t) + S_t (x_s(t+1) - x-(t+1))                  (eq 4.16)
    S_t    = P(t) A_t^T P-(t+1)^-1                              (eq 4.17)

and (the covariance of the smoothed estimate, same reference)
``P_s(t) = P(t) + S_t (P_s(t+1) - P-(t+1)) S_t^T``. Sec 6.2.3 proposes it for
the magnetic-inertial filter, to improve the inertial estimates between two
magnetic updates once the second one is known.

This runs on a host, after the run, so it may allocate freely; it is in
``firmware_py`` because it is the backward half of the firmware's filter.

Error-state form. The fusion filter feeds its error estimate back after
every update, so its a-posteriori error mean is zero at every step and the
a-priori one too. What the forward pass records per IMU step ``i``
(:class:`FusionRecorder`): the nominal state after the step (and its
correction), ``P-(i)``, ``P+(i)``, the transition ``A(i)`` from ``i-1`` and
the correction ``dx+(i)`` applied at ``i`` (zero without a measurement). The
smoothed error relative to the posterior nominal, ``e_s(i)``, then follows
from eq 4.16 with zero filter means::

    e_s(i) = S_i (e_s(i+1) + dx+(i+1))      e_s(N) = 0

(``e_s(i+1) + dx+(i+1)`` is the smoothed error relative to the a-priori
nominal of step ``i+1``; first order for the orientation, whose errors
compose as rotation vectors). The smoothed state is the posterior nominal
corrected by ``e_s(i)``. Only the inertial states (position, velocity,
orientation, sensor errors; ``layout.INS``) are smoothed: the magnetic error
states are white (``A`` rows zero), so they do not enter the gains of the
inertial states.

A filter restart (``FusionFilter._initialize``) starts a new segment; each
segment is smoothed on its own.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.estimate.layout import ACC, GYR, INS, ORI, POS, VEL

_NI = INS.stop - INS.start


class FusionRecorder:
    """Forward-pass recorder attached to ``FusionFilter.recorder`` (host only).

    Per step: ``t`` (us), nominal ``p``, ``v``, ``Th`` (3x3), ``ba``, ``bg``,
    ``phi`` (source orientation of the step), inertial blocks of ``P-``,
    ``P+`` and ``A``, and ``dx`` (inertial part of the correction).
    """

    def __init__(self):
        self.segments: list[dict] = []
        self._seg = None

    # ------------------------------------------------------------ hooks
    def on_init(self, fus, st) -> None:
        self._seg = {k: [] for k in ("t", "p", "v", "Th", "ba", "bg", "phi", "Pm", "Pp", "A", "dx")}
        self.segments.append(self._seg)
        self._append(fus, st, st.t_us, None)

    def _append(self, fus, st, t, k) -> None:
        s = self._seg
        s["t"].append(int(t))
        s["p"].append(st.p.copy())
        s["v"].append(st.v.copy())
        s["Th"].append(st.Th.copy())
        s["ba"].append(st.ba.copy())
        s["bg"].append(st.bg.copy())
        if k is None or fus.source_fixed:
            s["phi"].append(np.eye(3))
        else:
            s["phi"].append(fus.imu_d[k, fus.imu.PHI].reshape(3, 3).copy())
        P = st.P[INS, INS].copy()
        s["Pm"].append(P)
        s["Pp"].append(P.copy())
        s["A"].append(st.pred.A[INS, INS].copy())
        s["dx"].append(np.zeros(_NI))

    def on_step(self, fus, st, k, t1) -> None:
        """``st`` (the filter's live state or the shadow of a replay) stepped to ``t1``."""
        if self._seg is not None:
            self._append(fus, st, t1, k)

    def _at(self, t) -> int:
        """Index of the recorded step at time ``t`` (the newest such), or -1."""
        ts = self._seg["t"]
        for i in range(len(ts) - 1, -1, -1):
            if ts[i] == t:
                return i
        return -1

    def on_rewind(self, fus, t0) -> None:
        """The filter went back to ``t0``: forget the steps after it."""
        s = self._seg
        if s is None:
            return
        n = len(s["t"])
        while n and s["t"][n - 1] > t0:
            n -= 1
        for key in s:
            del s[key][n:]

    def on_prior(self, fus, st) -> None:
        """The prior of the update about to happen at ``st.t_us`` (a recorded step)."""
        i = self._at(st.t_us) if self._seg is not None else -1
        if i >= 0:
            self._seg["Pm"][i] = st.P[INS, INS].copy()

    def on_update(self, fus, st, dx) -> None:
        i = self._at(st.t_us) if self._seg is not None else -1
        if i < 0:
            return
        s = self._seg
        s["p"][i] = st.p.copy()
        s["v"][i] = st.v.copy()
        s["Th"][i] = st.Th.copy()
        s["ba"][i] = st.ba.copy()
        s["bg"][i] = st.bg.copy()
        s["Pp"][i] = st.P[INS, INS].copy()
        s["dx"][i] = np.array(dx[INS])


def rts(x_post, P_post, P_prior, A):
    """Textbook RTS smoother (eqs 4.16-4.17) for a linear filter: arrays of
    ``N`` posterior means (N, n), posterior and prior covariances (N, n, n)
    and transitions ``A[i]`` from step ``i-1`` to ``i`` (``A[0]`` unused), where
    the prior mean of step ``i`` is ``A[i] x_post[i-1]``. Returns smoothed
    means and covariances."""
    x_post = np.asarray(x_post, dtype=float)
    N = x_post.shape[0]
    xs = x_post.copy()
    Ps = np.array(P_post, dtype=float)
    for i in range(N - 2, -1, -1):
        G = np.linalg.solve(P_prior[i + 1].T, (P_post[i] @ A[i + 1].T).T).T
        x_prior_next = A[i + 1] @ x_post[i]
        xs[i] = x_post[i] + G @ (xs[i + 1] - x_prior_next)
        Ps[i] = P_post[i] + G @ (Ps[i + 1] - P_prior[i + 1]) @ G.T
    return xs, Ps


def _exp(w):
    t2 = float(w @ w)
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if t2 < 1e-12:
        return np.eye(3) + K + 0.5 * K @ K
    t = math.sqrt(t2)
    return np.eye(3) + math.sin(t) / t * K + (1.0 - math.cos(t)) / t2 * (K @ K)


def smooth_segment(seg: dict) -> dict:
    """Error-state RTS over one recorded segment (see module docstring).
    Returns smoothed ``t``, ``p``, ``v``, ``Th``, ``ba``, ``bg`` (global
    frame), ``phi``, and the smoothed inertial covariances ``P``."""
    t = np.asarray(seg["t"], dtype=np.int64)
    N = t.size
    Pp = np.asarray(seg["Pp"])
    Pm = np.asarray(seg["Pm"])
    A = np.asarray(seg["A"])
    dx = np.asarray(seg["dx"])
    e = np.zeros((N, _NI))
    Ps = Pp.copy()
    for i in range(N - 2, -1, -1):
        G = np.linalg.solve(Pm[i + 1].T, (Pp[i] @ A[i + 1].T).T).T
        e[i] = G @ (e[i + 1] + dx[i + 1])
        Ps[i] = Pp[i] + G @ (Ps[i + 1] - Pm[i + 1]) @ G.T
    p = np.asarray(seg["p"]) + e[:, POS]
    v = np.asarray(seg["v"]) + e[:, VEL]
    Th = np.array([_exp(e[i, ORI]) @ seg["Th"][i] for i in range(N)])
    ba = np.asarray(seg["ba"]) + e[:, ACC]
    bg = np.asarray(seg["bg"]) + e[:, GYR]
    return {"t": t, "p": p, "v": v, "Th": Th, "ba": ba, "bg": bg, "phi": np.asarray(seg["phi"]), "P": Ps,
            "p_forward": np.asarray(seg["p"]), "Th_forward": np.asarray(seg["Th"]),
            "P_forward": Pp}


def smooth(recorder: FusionRecorder) -> list[dict]:
    """Smooth every recorded segment (segments shorter than 2 steps are kept as they are)."""
    return [smooth_segment(s) for s in recorder.segments if len(s["t"]) >= 2]
