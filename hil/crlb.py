"""Cramer-Rao bound of a pose from one magnetic cycle, computed from the
emulator's own physics (magpylib fields, finite differences), so it is
independent of the firmware's field models and Jacobians.

Measurement: the 3 x ncoils amplitudes ``y_j = R^T I_j b_j(p)`` (field of
coil ``j`` per ampere at ``p``, seen in the sensor frame) with independent
Gaussian noise of standard deviation ``sigma[:, j]``. Parameters: position
(3, m) and a rotation-vector perturbation (3, rad) of ``R``. The bound is
``F^-1`` with ``F = J^T W J`` (Schepers & Veltink 2010, sec. 2, the
covariance of eq 4 with no prior).
"""
from __future__ import annotations

import numpy as np

from .motion import rotvec_to_matrix


def amplitudes(world, p, R, currents) -> np.ndarray:
    """(3, ncoils) noise-free amplitudes in the sensor frame."""
    U = world.unit_fields(p)                     # (ncoils, 3) source frame, per ampere
    return R.T @ (U * np.asarray(currents)[:, None]).T


def fisher(world, p, R, currents, sigma, h_pos: float = 1e-5, h_rot: float = 1e-6) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    ncoil = len(world.coils)
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (3, ncoil)).ravel()
    J = np.empty((3 * ncoil, 6))
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = h_pos
        J[:, k] = ((amplitudes(world, p + dp, R, currents) - amplitudes(world, p - dp, R, currents))
                   / (2 * h_pos)).ravel()
    for k in range(3):
        w = np.zeros(3)
        w[k] = h_rot
        Rp, Rm = R @ rotvec_to_matrix(w), R @ rotvec_to_matrix(-w)
        J[:, 3 + k] = ((amplitudes(world, p, Rp, currents) - amplitudes(world, p, Rm, currents))
                       / (2 * h_rot)).ravel()
    Jw = J / sig[:, None]
    return Jw.T @ Jw


def crlb(world, p, R, currents, sigma) -> np.ndarray:
    """6x6 bound: position (m) then rotation vector (rad)."""
    F = fisher(world, p, R, currents, sigma)
    try:
        return np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf)


def crlb_position_rms(world, p, R, currents, sigma) -> float:
    C = crlb(world, p, R, currents, sigma)
    return float(np.sqrt(max(np.trace(C[:3, :3]), 0.0)))


# ---------------------------------------------------------------------------
# The bound's inputs from the bench's ground truth
# ---------------------------------------------------------------------------


def amplitude_variance_factor(t_pulse, t_base) -> float:
    """``var(A) / sigma^2`` of a pulse amplitude ``A`` estimated from white samples, model
    ``y_i = b0 + b1 (t_i - t_c) + A [i in pulse]`` (a baseline linear in time, the quiet samples on
    both sides, plus the step; least squares = the bound for Gaussian noise): the (A, A) element of
    ``(X^T X)^-1``. The baseline's own variance is in it (for a constant baseline, known slope,
    ``1/n_pulse + 1/n_base``). Falls back to a constant baseline when the slope cannot be fitted;
    inf without a pulse or a baseline sample. ``t_pulse``, ``t_base``: sample times (us)."""
    tp = np.asarray(t_pulse, dtype=float)
    tb = np.asarray(t_base, dtype=float)
    if tp.size == 0 or tb.size == 0:
        return float("inf")
    t = np.concatenate([tp, tb])
    tc = float(t.mean())
    ind = np.concatenate([np.ones(tp.size), np.zeros(tb.size)])
    for X in (np.column_stack([np.ones(t.size), (t - tc) * 1e-6, ind]), np.column_stack([np.ones(t.size), ind])):
        G = X.T @ X
        if np.linalg.cond(G) < 1e12:
            return float(np.linalg.inv(G)[-1, -1])
    return float("inf")


class TruthAmplitudes:
    """Per magnetic pose, the achieved coil currents and the amplitude noise of the bound, from
    what the bench knows, never from the firmware's window reports.

    For each window a pose was made of, the pulse that really ran (``driver.executed``: its true
    edges and its true current, regulation error and voltage limit included), the sensor's true
    sample times (``SensorNode.true_times``), and:

    * in-pulse samples: those in the pulse's settled interval, from ``World.flat_start_us``
      (current and every eddy field within ``tol`` of the pulse's steady field) to the true end edge;
    * baseline samples: quiet ones (no coil on and none still decaying, each pulse's decay
      followed to ``tol`` of its field, eddy fields included) within ``baseline_us`` before the
      start edge and within ``baseline_us`` after the pulse's own decay;
    * the amplitude variance ``sigma^2 amplitude_variance_factor(...)``, the baseline's
      variance included.

    ``sigma_t``: the sensor's per-sample noise (T, the bench's own figure).
    """

    def __init__(self, bench, sigma_t: float, baseline_us: int, tol: float = 1e-3, step_us: int = 20):
        from .bench import _executed_index

        self.bench, self.sigma_t, self.baseline_us = bench, float(sigma_t), int(baseline_us)
        self.tol, self.step_us = tol, step_us
        self.idx = _executed_index(bench.driver)
        self.sensors = {s.node_id: s for s in bench.sensors}
        self._times: dict[int, np.ndarray] = {}
        self._flat: dict[int, int] = {}
        ex = sorted((e for e in bench.driver.executed if abs(e.get("current_a", 0.0)) > 0.0),
                    key=lambda e: e["start_us"])
        nxt = [ex[i + 1]["start_us"] if i + 1 < len(ex) else None for i in range(len(ex))]
        self._busy = np.array([[e["start_us"], self._quiet_from(e, n)] for e, n in zip(ex, nxt)],
                              dtype=np.int64).reshape(-1, 2)
        self._quiet_end = {id(e): int(q) for e, q in zip(ex, self._busy[:, 1])}

    def _quiet_from(self, e, next_start_us) -> int:
        """First true time after ``e``'s end edge from which its coil's current and the eddy fields
        it drives stay below ``tol`` of its steady field (searched up to the next pulse's start, at
        most 200 ms: a baseline sample after that start is not quiet anyway)."""
        world = self.bench.world
        k, t1 = e["coil"], int(e["end_us"])
        cur = world.currents[k]
        until = t1 + 200_000 if next_start_us is None else min(t1 + 200_000, max(int(next_start_us), t1 + self.step_us))
        grid = np.arange(t1, until, self.step_us, dtype=np.int64)
        i_ss = abs(float(e["current_a"]))
        err = np.abs(np.asarray(cur.current_at(grid))) / i_ss
        p, R = world.pose(t1)
        p = np.asarray(p, dtype=float)
        coil_ss = i_ss * float(np.linalg.norm(world.unit_fields(p)[k]))
        for obj in world.objects:
            if hasattr(obj, "eddy_error") and (obj.active(int(e["start_us"])) or obj.active(t1)):
                err = np.maximum(err, obj.eddy_error(world, k, grid, p, R) / max(coil_ss, 1e-30))
        bad = np.nonzero(err >= self.tol)[0]
        return t1 if bad.size == 0 else int(grid[min(bad[-1] + 1, grid.size - 1)])

    def _sensor_times(self, node: int) -> np.ndarray:
        if node not in self._times:
            self._times[node] = np.asarray(self.sensors[node].true_times, dtype=np.int64)
        return self._times[node]

    def _quiet(self, t: np.ndarray) -> np.ndarray:
        if self._busy.size == 0:
            return np.ones(t.shape, dtype=bool)
        i = np.searchsorted(self._busy[:, 0], t, side="right") - 1
        ok = i < 0
        j = np.maximum(i, 0)
        # the latest pulse started before t, and any earlier one still decaying (the running maximum)
        qmax = np.maximum.accumulate(self._busy[:, 1])
        return ok | (t >= qmax[j])

    def window(self, w, rx_us: int):
        """``(achieved current (A), variance factor)`` of one PULSE_WINDOW, or None (no pulse ran)."""
        from .bench import _match

        e = _match(self.idx, w.coil, w.pulse_id, rx_us)
        s = self.sensors.get(w.node)
        if e is None or s is None or abs(e.get("current_a", 0.0)) == 0.0:
            return None
        key = id(e)
        if key not in self._flat:
            self._flat[key] = self.bench.world.flat_start_us(e["coil"], e["start_us"], e["end_us"], self.tol)
        T = self._sensor_times(w.node)
        t0, t1, B = int(e["start_us"]), int(e["end_us"]), self.baseline_us
        q1 = self._quiet_end.get(key, t1)
        tp = T[(T >= self._flat[key]) & (T < t1)]
        cand = T[((T >= t0 - B) & (T < t0)) | ((T >= q1) & (T < q1 + B))]
        tb = cand[self._quiet(cand)]
        return float(e["current_a"]), amplitude_variance_factor(tp, tb)

    def for_pose(self, rp, ncoil: int):
        """``(currents (ncoil,) A, sigma (3, ncoil) T)`` of one magnetic pose; a coil without a window
        gets no current (it adds nothing to the bound). None when no window of the pose ran."""
        currents = np.zeros(ncoil)
        sigma = np.full((3, ncoil), np.inf)
        any_ok = False
        for w in rp["windows"]:
            r = self.window(w, rp["rx_us"])
            if r is None or not 0 <= w.coil < ncoil or not np.isfinite(r[1]):
                continue
            currents[w.coil] = r[0]
            sigma[:, w.coil] = self.sigma_t * np.sqrt(r[1])
            any_ok = True
        return (currents, sigma) if any_ok else None
