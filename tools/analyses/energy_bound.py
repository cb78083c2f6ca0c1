"""The least coil energy any pulse policy needs for the fixed cycle's accuracy.

``python -m coiltrack.tools.analyses.energy_bound --seeds 1-10 --json bound.json``

Schepers & Veltink 2010 (``../shared/seeds/001_*``, sec. 2.3-2.4) save energy
by deciding when, which coil and how strong. How much can that save at the
accuracy of the fixed X, Y, Z cycle with the same pulses and filter? This
command computes a bound on the trajectories of ``schepers-adaptive`` from the
physics alone, with the bench's source (``hil.physics.thesis_source``) and
motion (``hil.motion.HandMovedBench``), never with the firmware:

* **Information of a pulse.** A pulse of coil ``k`` at the cycle's current at
  time ``t`` measures ``h = R^T B_k(p)`` (sensor frame), with the 3 x 6
  Jacobian ``H_k = [R^T dB_k/dp, [h]x]`` on (position, rotation) (the signal
  model of Schepers eqs 9-11). Its Fisher information is
  ``J_k = H_k^T H_k / sigma^2``. A pulse of ``e`` times the cycle's energy
  (same length, current ``sqrt(e)`` times) gives ``e J_k``: information and
  coil energy both grow as ``I^2``. The noise ``sigma`` cancels in every
  ratio below.
* **Time.** The run is cut into windows of ``--window`` cycle periods. In
  window ``w`` a policy spends energies ``e_wk >= 0``; the fixed cycle spends
  1 per coil per cycle. The information of a window is
  ``J_w = sum_k e_wk J_k(t_w)`` (the pose changes little within a window:
  the trajectories' components are 0.02-0.08 Hz).
* **From information to the filter's error.** Between pulses the IMU carries
  the state, so the filter's mean squared error is not ``J^-1`` but grows more
  slowly as the information shrinks: locally ``v = K [tr_B(J_w^-1)]^a`` for
  the position block ``B`` (and the rotation block), with one exponent ``a``
  per block. ``a`` is measured, per seed, on the fixed cycle's own current
  sweep (``schepers-fixed-910`` against ``-450``: the same windows with all
  information scaled by ``(0.45 / 0.91)^2``), which is exactly this
  scaling: ``a = -log(rms_450^2 / rms_910^2) / log(E_450 / E_910)``. A steady
  Kalman filter with white acceleration noise has ``a = 3/4`` for position,
  with a gyroscope random walk ``1/2`` for orientation; the sweeps give
  0.6-0.9 and 0.3-0.7.
* **The accuracy asked.** The mean over the windows of each block's ``v``
  at most ``ratio^2`` times the fixed cycle's (the RMS is the root of that
  mean; ``ratio`` 1.1 is the issue's "within 10 %").

The least total energy under those two constraints is a convex programme in
``e`` (``tr(J^-1)`` is convex in ``J``, ``x^a`` for ``a <= 1`` concave
increasing, so it is solved to a local optimum from the fixed cycle; SLSQP
with analytic gradients). It ignores the driver's limits, the
magnetometer's range, acquisition, the settle time and any model error: all
of those only raise the energy a real policy needs, so what it prints is a
lower bound for a policy held to the same filter, as far as the local model
holds.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from ..bench.sweep import parse_seeds as _seeds_arg
from ..inputs.sweepfile import read_json

#: cycle of ``schepers-adaptive``'s fixed baseline (three 60 ms pulses in 600 ms)
CYCLE_S = 0.6
POS, ROT = slice(0, 3), slice(3, 6)


def pulse_information(source, currents: np.ndarray, p: np.ndarray, R: np.ndarray, h: float = 1e-5) -> np.ndarray:
    """Fisher information of one pulse of each coil at each pose, noise 1.

    source: ``hil.physics.Source``; currents (K,) A; p (n, 3) m; R (n, 3, 3)
    sensor -> source. Returns (n, K, 6, 6) on (position m, rotation rad),
    with ``dB/dp`` by central differences of step ``h`` m.
    """
    from coiltrack.hil.motion import skew

    n = len(p)
    B0 = source.unit_fields(p) * currents[:, None, None]                  # (K, n, 3)
    G = np.empty((len(currents), n, 3, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        G[..., i] = (source.unit_fields(p + d) - source.unit_fields(p - d)) * currents[:, None, None] / (2 * h)
    Rt = np.transpose(R, (0, 2, 1))
    hs = np.einsum("nij,knj->kni", Rt, B0)                                 # sensor-frame field
    H = np.concatenate([np.einsum("nij,knjl->knil", Rt, G), skew(hs)], axis=-1)   # (K, n, 3, 6)
    return np.transpose(np.einsum("knji,knjl->knil", H, H), (1, 0, 2, 3))


def _block_traces(J: np.ndarray):
    """J (W, 6, 6) -> (Jinv, tr_pos, tr_rot)."""
    Ji = np.linalg.inv(J)
    return Ji, np.trace(Ji[:, POS, POS], axis1=1, axis2=2), np.trace(Ji[:, ROT, ROT], axis1=1, axis2=2)


def least_energy(Jk: np.ndarray, a_pos: float, a_rot: float, ratio: float = 1.1,
                 floor: float = 1e-6) -> dict:
    """Least energy for the fixed cycle's accuracy times ``ratio``.

    Jk (W, K, 6, 6): information of a full pulse of coil k in window w
    (already multiplied by the cycles per window). Returns the energy
    fraction of the fixed cycle (which spends 1 per coil per window), the
    optimal energies (W, K) and the achieved RMS ratios.
    """
    from scipy.optimize import minimize

    W, K = Jk.shape[:2]
    _, tp0, tr0 = _block_traces(Jk.sum(axis=1))
    vp0, vr0 = np.mean(tp0 ** a_pos), np.mean(tr0 ** a_rot)
    cap = ratio ** 2

    def parts(x):
        J = np.einsum("wk,wkij->wij", x.reshape(W, K), Jk)
        Ji, tp, tr = _block_traces(J)
        return Ji, tp, tr

    def con(x):
        _, tp, tr = parts(x)
        return np.array([1.0 - np.mean(tp ** a_pos) / (cap * vp0), 1.0 - np.mean(tr ** a_rot) / (cap * vr0)])

    def con_jac(x):
        Ji, tp, tr = parts(x)
        out = np.empty((2, W * K))
        for row, (blk, t, a, v0) in enumerate(((POS, tp, a_pos, vp0), (ROT, tr, a_rot, vr0))):
            M = Ji[:, :, blk] @ Ji[:, blk, :]                               # J^-1 P J^-1
            dtr = -np.einsum("wij,wkji->wk", M, Jk)                         # d tr / d e_wk
            out[row] = -(a * t[:, None] ** (a - 1.0) * dtr / W / (cap * v0)).ravel()
        return out

    x0 = np.ones(W * K)
    res = minimize(lambda x: x.sum() / (W * K), x0, jac=lambda x: np.full(W * K, 1.0 / (W * K)),
                   bounds=[(floor, None)] * (W * K), method="SLSQP",
                   constraints=[{"type": "ineq", "fun": con, "jac": con_jac}],
                   options={"maxiter": 500, "ftol": 1e-10})
    x = np.maximum(res.x, floor)
    c = con(x)
    return {"energy_fraction": float(x.sum() / (W * K)), "energies": x.reshape(W, K),
            "position_rms_ratio": float(np.sqrt((1.0 - c[0]) * cap)),
            "orientation_rms_ratio": float(np.sqrt((1.0 - c[1]) * cap)),
            "converged": bool(res.success), "message": str(res.message)}


def exponent(rms_hi, rms_lo, energy_hi: float, energy_lo: float) -> np.ndarray:
    """``a`` of ``mse ~ E^-a`` from two runs of the same windows at two energies."""
    return -np.log((np.asarray(rms_lo) / np.asarray(rms_hi)) ** 2) / np.log(energy_lo / energy_hi)


def _sweep_figures(path: str) -> dict:
    d = read_json(path)
    out = {}
    for r in d["runs"]:
        if r["params"] and r["params"].get("timing.cycle_us", 600000) != 600000:
            continue
        g = r["figures"]
        try:
            out[int(r["seed"])] = (g["position_rms_mm"], g["orientation_rms_deg"], g["coil_energy_j"])
        except KeyError as exc:
            from ..inputs.infile import InputFileError

            raise InputFileError(path, "missing", key=f"figures.{exc.args[0]}") from None
    return out


def seed_bound(seed: int, a_pos: float, a_rot: float, ratio: float, window: int, duration_s: float,
               current_a: float = 0.91) -> dict:
    """The bound on one seed's ``schepers-adaptive`` trajectory."""
    from coiltrack.hil import motion, physics

    source = physics.thesis_source()
    traj = motion.HandMovedBench(seed=seed, duration_s=duration_s, r_min=0.15, r_max=0.40, v_max=0.12,
                                 w_max_deg=30.0)
    per = window * CYCLE_S
    t = (np.arange(int(duration_s / per)) + 0.5) * per
    p, R = traj.pose((t * 1e6).astype(np.int64))
    Jk = pulse_information(source, np.full(len(source), current_a), p, R) * window
    out = least_energy(Jk, a_pos, a_rot, ratio)
    e = out.pop("energies")
    r = np.linalg.norm(p, axis=1)
    out.update(seed=seed, a_pos=a_pos, a_rot=a_rot, windows=len(t),
               range_m=[float(r.min()), float(r.max())],
               energy_near_far=[float(e[r < np.median(r)].sum() / e.sum()), float(e[r >= np.median(r)].sum() / e.sum())])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m coiltrack.tools.analyses.energy_bound", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=_seeds_arg, default=list(range(1, 11)), help="seeds, e.g. 1-10 (default 1-10)")
    ap.add_argument("--ratio", type=float, default=1.1, help="RMS allowed against the fixed cycle (default 1.1)")
    ap.add_argument("--window", type=int, default=1, help="cycle periods per window (default 1)")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds (default 60)")
    ap.add_argument("--sweeps", default="docs/adaptive-sweeps",
                    help="folder with fixed-910.json and fixed-450.json (exponents per seed)")
    ap.add_argument("--a-pos", type=float, help="position exponent for every seed instead of the sweeps'")
    ap.add_argument("--a-rot", type=float, help="orientation exponent for every seed instead of the sweeps'")
    ap.add_argument("--json", help="write the figures as JSON")
    a = ap.parse_args(argv)
    if a.ratio < 1.0 or a.window < 1 or a.duration <= 0:
        print("energy_bound: --ratio must be >= 1, --window >= 1, --duration > 0", file=sys.stderr)
        return 2
    hi = lo = None
    if a.a_pos is None or a.a_rot is None:
        try:
            hi, lo = _sweep_figures(f"{a.sweeps}/fixed-910.json"), _sweep_figures(f"{a.sweeps}/fixed-450.json")
        except (OSError, ValueError) as e:
            print(f"energy_bound: --sweeps: {e}", file=sys.stderr)
            return 2
    rows = []
    for s in a.seeds:
        ap_, ar_ = a.a_pos, a.a_rot
        if hi is not None:
            (p1, o1, e1), (p2, o2, e2) = hi[s], lo[s]
            ap_ = float(exponent(p1, p2, e1, e2)) if ap_ is None else ap_
            ar_ = float(exponent(o1, o2, e1, e2)) if ar_ is None else ar_
        row = seed_bound(s, ap_, ar_, a.ratio, a.window, a.duration)
        rows.append(row)
        print(f"seed {s:2d}: a_pos {ap_:.2f} a_rot {ar_:.2f}  least energy {row['energy_fraction']:.3f} of the "
              f"fixed cycle (position x{row['position_rms_ratio']:.3f}, orientation x{row['orientation_rms_ratio']:.3f}, "
              f"{'converged' if row['converged'] else row['message']})")
    f = np.array([r["energy_fraction"] for r in rows])
    print(f"least energy fraction: median {np.median(f):.3f}, worst {f.max():.3f}, best {f.min():.3f}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"ratio": a.ratio, "window_cycles": a.window, "seeds": rows,
                       "median": float(np.median(f)), "worst": float(f.max())}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
