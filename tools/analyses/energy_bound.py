"""The least coil energy any pulse policy needs for the fixed cycle's accuracy.

``python -m coiltrack.tools.analyses.energy_bound --seeds 1-10 [--pulse-length fixed|chosen|all]
[--columns fixed,chosen,chosen-long] [--sample-phase mean|aligned] --json bound.json``

Schepers & Veltink 2010 (``../shared/seeds/001_*``, sec. 2.3-2.4) save energy
by deciding when, which coil and how strong; the seed paper also treats the
samples per pulse and the pulse width as design levers. How much can a policy
save at the accuracy of the fixed X, Y, Z cycle (60 ms pulses, 35 ms
baselines, 0.91 A, 600 ms) with the same filter? This command computes a bound
on the trajectories of ``schepers-adaptive`` from the physics alone, with the
bench's source (``hil.physics.thesis_source``), motion
(``hil.motion.HandMovedBench``) and earth field, and the scenario's
configuration (noise, model error, limits, extraction timing), never with the
firmware's policy:

* **Information of a pulse.** A pulse of coil ``k`` at current ``I`` at time
  ``t`` measures ``y = I u_k`` with ``u_k = R^T B_k(p)`` per ampere (sensor
  frame) and the 3 x 6 Jacobian ``I H_k``, ``H_k = [R^T dB_k/dp, [u_k]x]`` on
  (position, rotation) (the signal model of Schepers eqs 9-11). The filter's
  measurement variance is ``a + b I^2`` on every axis: the white noise of the
  extraction's ``n_u`` pulse and ``n_b`` baseline samples,
  ``sigma^2 (1/n_u + 1/n_b)``, the current's error ``tau^2 |u|^2`` and the
  field model's ``b I^2 = (rho I |u|)^2`` (``field_model_rel_sigma`` 3e-3 in
  this scenario: ``firmware_py/estimate/single_coil.py``,
  ``update_single_coil``). The information is ``s(I) J~_k`` with
  ``J~_k = H_k^T H_k`` and ``s = I^2 / (a + b I^2)``, which **saturates** at
  ``1 / (rho |u|)^2`` as the current grows: near the source a stronger pulse
  adds little (``pulse_cost`` derives it). So model error does not only raise
  the energy a policy needs: where the fixed cycle's 0.91 A pulses are
  saturated, weaker pulses bring nearly the same information for much less
  energy, and the bound is *lower* for it.
* **What a pulse costs.** ``I^2 T`` (coil resistance equal for all, it
  cancels), for a pulse of length ``T``, with ``n_u(T)`` counted as the
  extraction counts (``pulse_cost.pulse_samples``: a window with fewer than
  ``min_pulse_samples`` used samples is refused and counts none), baselines of ``B`` that
  cost no energy but time (``fall + B + guard`` after every pulse), one coil at
  a time, the window's time at most its duration, the current at most the
  driver's ``max_current_a`` and within the magnetometer's ``mag_range_t``
  together with the earth field (either sign), any number of pulses of any
  kind per window (relaxed to real numbers). ``pulse_cost.WindowCost`` gives
  the least energy ``E_w(x_w)`` of the information weights ``x_wk`` of a
  window, convex in ``x_w``.
* **Time.** The run is cut into windows of ``--window`` cycle periods; the
  information of window ``w`` is ``J_w = sum_k x_wk J~_k(t_w)`` (the pose
  changes little within a window: the trajectories' components are 0.02-0.08
  Hz). The fixed cycle brings ``x0_wk = window * s(0.91 A)`` with 60 ms pulses
  and 35 ms baselines.
* **From information to the filter's error.** Between pulses the IMU carries
  the state, so the filter's mean squared error is not ``J^-1`` but grows more
  slowly as the information shrinks: locally ``v = K [tr_B(J_w^-1)]^a`` for
  the position block ``B`` (and the rotation block), one exponent ``a`` per
  block, fitted per seed to the fixed cycle's own current sweep
  (``schepers-fixed-910`` against ``-450``, with those scenarios' model error):
  the ``a`` with which the model's mean ``v`` over the windows changes by the
  measured ratio of mean squares (without model error this is
  ``-log(rms_450^2 / rms_910^2) / log(E_450 / E_910)``). A steady Kalman
  filter with white acceleration noise has ``a = 3/4`` for position, with a
  gyroscope random walk ``1/2`` for orientation.
* **The accuracy asked.** The mean over the windows of each block's ``v`` at
  most ``ratio^2`` times the fixed cycle's (``ratio`` 1.1 is "within 10 %").

**Which floor a policy is held to.** ``pulse_length = "fixed"`` starts its pulses at any phase of
the magnetometer's samples: the ``fixed`` column at ``--sample-phase mean``. ``pulse_length =
"chosen"`` puts every start on the sample clock (``actuate.pulse_length.PulseLengths.align``), which a
pulse at an arbitrary phase cannot: its floor is the ``chosen`` column at ``--sample-phase aligned``
(``--columns chosen``), below the mean-phase one.

**Why it is a lower bound.** The least total energy under those constraints
is a convex programme: ``J -> 1 / tr_B(J^-1)`` is concave (the information on
a block, ``(E^T J^-1 E)^-1``, is matrix-concave and ``X -> 1/tr(X^-1)`` is
concave and increasing), so ``tr_B(J^-1)^a = (1 / tr_B(J^-1))^-a`` is convex
for every ``a > 0`` and each accuracy constraint is a convex set in ``x``;
``E_w`` is convex (a partial minimum of the jointly convex perspective cost,
``pulse_cost``), and the time limits are linear. SLSQP's optimum is therefore
the global one (within its tolerance, ``ftol`` 1e-10). Every simplification
gives a policy more than it has: real-valued pulse counts; pulse lengths
between grid points credited with the shorter length's time, the longer
one's samples and the least ``T / n_u`` of the two (``Kinds.chosen``;
``--grid-lengths`` gives the companion from above); the mean sample counts over the phase (the weight is concave in
them); the baseline's straight-line fit credited as a mean; the filter's
linearisation term, the NIS inflation and the magnetometer's saturation
margin left out; the duty limit (``coil_max_duty``) left out and reported
(``duty_max``: the largest on-time share over two consecutive windows; when
within the limit the bound is the same with it). The model error enters as the
filter weighs it, independent from pulse to pulse; a real gain error is common
to a coil's pulses, so several weak pulses tell a real policy less than the
filter credits, never more. What remains is the local model of the filter's
error.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from ..bench.sweep import parse_seeds as _seeds_arg
from ..inputs.sweepfile import read_json
from .pulse_cost import Kinds, Timing, WindowCost, pulse_samples, pulse_weight

#: cycle of ``schepers-adaptive``'s fixed baseline (three 60 ms pulses in 600 ms)
CYCLE_S = 0.6
POS, ROT = slice(0, 3), slice(3, 6)
#: the columns of the table: (name, pulse lengths, baselines)
MODES = ("fixed", "chosen", "chosen-long")


def unit_model(source, p: np.ndarray, R: np.ndarray, h: float = 1e-5):
    """Per-ampere model of each coil at each pose: ``(Jt (n, K, 6, 6), u (n, K, 3))`` with
    ``Jt = H^T H`` (noise 1) on (position m, rotation rad) and ``u`` the field per ampere in the
    sensor frame (T/A). source: ``hil.physics.Source``; p (n, 3) m; R (n, 3, 3) sensor -> source;
    ``dB/dp`` by central differences of step ``h`` m."""
    from coiltrack.hil.motion import skew

    n = len(p)
    B0 = source.unit_fields(p)                                             # (K, n, 3)
    G = np.empty((B0.shape[0], n, 3, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        G[..., i] = (source.unit_fields(p + d) - source.unit_fields(p - d)) / (2 * h)
    Rt = np.transpose(R, (0, 2, 1))
    u = np.einsum("nij,knj->kni", Rt, B0)                                  # sensor-frame field per A
    H = np.concatenate([np.einsum("nij,knjl->knil", Rt, G), skew(u)], axis=-1)   # (K, n, 3, 6)
    Jt = np.einsum("knji,knjl->knil", H, H)
    return np.transpose(Jt, (1, 0, 2, 3)), np.transpose(u, (1, 0, 2))


def pulse_information(source, currents: np.ndarray, p: np.ndarray, R: np.ndarray, h: float = 1e-5) -> np.ndarray:
    """Fisher information of one pulse of each coil at each pose, white noise 1, no model error:
    (n, K, 6, 6) = ``I_k^2 H_k^T H_k``."""
    Jt, _ = unit_model(source, p, R, h)
    return Jt * np.square(np.asarray(currents, dtype=float))[None, :, None, None]


def current_limit(u: np.ndarray, earth: np.ndarray, mag_range: float, max_current: float) -> np.ndarray:
    """Largest current (W, K) of a pulse of either sign that keeps every axis of ``earth + I u``
    within ``mag_range``, and at most ``max_current``. u (W, K, 3) T/A; earth (W, 3) T, sensor frame."""
    e = earth[:, None, :]
    au = np.abs(u)
    best = np.zeros(u.shape[:2])
    for sign in (1.0, -1.0):
        room = mag_range - sign * np.sign(u) * e                           # what is left on the pulse's side
        with np.errstate(divide="ignore"):
            lim = np.where(au > 0, np.maximum(room, 0.0) / au, np.inf)
        best = np.maximum(best, lim.min(axis=-1))
    return np.minimum(best, max_current)


def _block_traces(J: np.ndarray):
    """J (W, 6, 6) -> (Jinv, tr_pos, tr_rot)."""
    Ji = np.linalg.inv(J)
    return Ji, np.trace(Ji[:, POS, POS], axis1=1, axis2=2), np.trace(Ji[:, ROT, ROT], axis1=1, axis2=2)


def _accuracy(Jk, a_pos, a_rot, cap, vp0, vr0):
    """The two accuracy constraints (>= 0 when held) and their Jacobian in y, for J_w = sum_k y_wk Jk_wk."""
    W, K = Jk.shape[:2]

    def parts(y):
        return _block_traces(np.einsum("wk,wkij->wij", y.reshape(W, K), Jk))

    def con(y):
        _, tp, tr = parts(y)
        return np.array([1.0 - np.mean(tp ** a_pos) / (cap * vp0), 1.0 - np.mean(tr ** a_rot) / (cap * vr0)])

    def jac(y):
        Ji, tp, tr = parts(y)
        out = np.empty((2, W * K))
        for row, (blk, t, a, v0) in enumerate(((POS, tp, a_pos, vp0), (ROT, tr, a_rot, vr0))):
            M = Ji[:, :, blk] @ Ji[:, blk, :]                               # J^-1 P J^-1
            dtr = -np.einsum("wij,wkji->wk", M, Jk)                         # d tr / d y_wk
            out[row] = -(a * t[:, None] ** (a - 1.0) * dtr / W / (cap * v0)).ravel()
        return out
    return con, jac


def least_energy(Jt: np.ndarray, x0: np.ndarray, cost: WindowCost, ref_energy: float, a_pos: float,
                 a_rot: float, ratio: float = 1.1, floor: float = 1e-9) -> dict:
    """Least energy for the fixed cycle's accuracy times ``ratio``.

    Jt (W, K, 6, 6): per-ampere information ``H^T H`` of coil k in window w; x0 (W, K): the fixed
    cycle's information weights there; cost: the windows' :class:`WindowCost`; ref_energy: the fixed
    cycle's energy per coil and window (A^2 s). The variables are ``y = x / x0``. Returns the energy
    fraction of the fixed cycle, the information weights ``y`` (W, K), the achieved RMS ratios and
    the per-window details of the optimum (``WindowCost.energy``)."""
    from scipy.optimize import minimize

    W, K = Jt.shape[:2]
    Jk = Jt * x0[..., None, None]
    _, tp0, tr0 = _block_traces(Jk.sum(axis=1))
    cap = ratio ** 2
    con, con_jac = _accuracy(Jk, a_pos, a_rot, cap, np.mean(tp0 ** a_pos), np.mean(tr0 ** a_rot))
    scale = 1.0 / (W * K * ref_energy)
    memo = {}

    def evaluate(y):
        key = y.tobytes()
        if key not in memo:
            memo.clear()
            E, grad, _ = cost.energy(y.reshape(W, K) * x0)
            memo[key] = (float(E.sum() * scale), (grad * x0).ravel() * scale)
        return memo[key]

    # the windows' time: sum_k psi_wk x0_wk y_wk <= D (what the time can hold at the current limit)
    A = np.zeros((W, W * K))
    for w in range(W):
        A[w, w * K:(w + 1) * K] = cost.psi[w] * x0[w]
    time_con = {"type": "ineq", "fun": lambda y: cost.D - A @ y, "jac": lambda y: -A}
    y0 = np.ones(W * K)
    res = minimize(lambda y: evaluate(y)[0], y0, jac=lambda y: evaluate(y)[1], bounds=[(floor, None)] * (W * K),
                   method="SLSQP", constraints=[{"type": "ineq", "fun": con, "jac": con_jac}, time_con],
                   options={"maxiter": 1000, "ftol": 1e-10})
    y = np.maximum(res.x, floor)
    c = con(y)
    E, _, detail = cost.energy(y.reshape(W, K) * x0)
    return {"energy_fraction": float(E.sum() * scale), "y": y.reshape(W, K), "detail": detail,
            "position_rms_ratio": float(np.sqrt(max(1.0 - c[0], 0.0) * cap)),
            "orientation_rms_ratio": float(np.sqrt(max(1.0 - c[1], 0.0) * cap)),
            "time_violation_s": float(max(0.0, np.max(A @ y - cost.D))),
            "converged": bool(res.success), "message": str(res.message)}


def exponent(rms_hi, rms_lo, energy_hi: float, energy_lo: float) -> np.ndarray:
    """``a`` of ``mse ~ E^-a`` from two runs of the same windows at two energies."""
    return -np.log((np.asarray(rms_lo) / np.asarray(rms_hi)) ** 2) / np.log(energy_lo / energy_hi)


def fit_exponent(J_hi: np.ndarray, J_lo: np.ndarray, rms_hi: float, rms_lo: float, block: slice) -> float:
    """The ``a`` with which the model's mean ``tr_B(J_w^-1)^a`` over the windows grows from the
    windows' information ``J_hi`` (W, 6, 6) to ``J_lo`` by the measured ``(rms_lo / rms_hi)^2``.
    ``J_lo = J_hi / q`` gives the closed form ``log(rms_lo^2 / rms_hi^2) / log(q)``."""
    from scipy.optimize import brentq

    th = np.trace(np.linalg.inv(J_hi)[:, block, block], axis1=1, axis2=2)
    tl = np.trace(np.linalg.inv(J_lo)[:, block, block], axis1=1, axis2=2)
    target = 2.0 * np.log(rms_lo / rms_hi)
    f = lambda a: np.log(np.mean(tl ** a)) - np.log(np.mean(th ** a)) - target  # noqa: E731
    lo, hi = 1e-3, 5.0
    if f(lo) > 0 or f(hi) < 0:
        raise ValueError(f"no exponent in [{lo}, {hi}] fits the RMS ratio {rms_lo / rms_hi:.3f}")
    return float(brentq(f, lo, hi, xtol=1e-10))


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


def mode_kinds(mode: str, tm: Timing, fixed_pulse_s: float, baseline_s: float, long_baseline_s: float,
               max_pulse_s: float, step_s: float, phase: str, grid_lengths: bool = False) -> Kinds:
    """The pulse kinds of a column: ``fixed`` (the cycle's pulse and baseline), ``chosen`` (any pulse
    length up to ``max_pulse_s``, the cycle's baselines) or ``chosen-long`` (the same, baselines of
    ``baseline_s`` or ``long_baseline_s``)."""
    if mode == "fixed":
        return Kinds.fixed(fixed_pulse_s, baseline_s, tm, phase)
    # the grid's step up to 100 ms, ten times it to 200 ms, then one interval to the longest (long
    # pulses are never near the best; the optimistic kinds keep the bound valid on any grid)
    fine = np.arange(step_s, min(0.1, max_pulse_s) + 0.5 * step_s, step_s)
    grid = np.concatenate([fine, np.arange(fine[-1] + 10 * step_s, min(0.2, max_pulse_s) + 5 * step_s, 10 * step_s),
                           [max_pulse_s]])
    grid = np.unique(grid[grid <= max_pulse_s + 1e-12])
    bs = [baseline_s] if mode == "chosen" else sorted({baseline_s, long_baseline_s})
    return (Kinds.grid if grid_lengths else Kinds.chosen)(grid, bs, tm, phase)


def bench_world_seed(seed: int) -> int:
    """The world seed the bench draws from a run's seed (``tools.bench.runner.BenchSetup``: the first of
    five children of ``SeedSequence(seed)``), so the bound is taken on the trajectory the bench runs for
    that seed, not on the one ``build_world(seed)`` would give."""
    return int(np.random.SeedSequence(seed).spawn(5)[0].generate_state(1)[0])


class SeedModel:
    """The windows of one seed's ``schepers-adaptive`` trajectory: per-ampere information, fields,
    current limits and the fixed cycle's information weights, from the scenario's world and its
    fixed cycle's configuration (the same filter)."""

    def __init__(self, seed: int, window: int, duration_s: float, scenario: str = "schepers-adaptive",
                 phase: str = "mean"):
        from coiltrack.tools import scenarios

        sc = scenarios.get(scenario)
        world = sc.build_world(bench_world_seed(seed), duration_s)
        cfg = sc.fixed_config() if sc.fixed_config is not None else sc.firmware_config()
        self.cfg, self.window, self.phase = cfg, window, phase
        self.D = window * CYCLE_S
        t = (np.arange(int(duration_s / self.D)) + 0.5) * self.D
        p, R = world.trajectory.pose((t * 1e6).astype(np.int64))
        self.p = p
        self.Jt, self.u = unit_model(world.source, p, R)
        self.u2 = np.sum(self.u ** 2, axis=-1)
        earth = np.einsum("nji,j->ni", R, world.earth)                       # R^T earth, sensor frame
        self.imax = current_limit(self.u, earth, cfg.pulse.mag_range_t, cfg.limits.max_current_a)
        self.tm = Timing.from_config(cfg)
        self.I0 = np.array([c.current for c in cfg.source.coils])
        self.T0, self.B0 = cfg.timing.pulse_us * 1e-6, cfg.pulse.baseline_us * 1e-6
        self.x0 = window * self.weight(self.I0, cfg.adaptive.field_model_rel_sigma)
        self.ref_energy = window * float(np.mean(self.I0 ** 2)) * self.T0

    def weight(self, currents, rho: float) -> np.ndarray:
        """Information weights (W, K) of one pulse per coil at ``currents`` with the cycle's pulse and
        baseline and the model error ``rho`` (the cycle's pulses are not timed to the samples: the
        mean counts whatever ``phase``)."""
        nu, nb = pulse_samples(self.T0, self.B0, self.tm, "mean")
        a = self.cfg.pulse.mag_sigma_t ** 2 * (1 / nu + 1 / nb) + self.cfg.limits.current_tolerance_a ** 2 * self.u2
        return pulse_weight(np.asarray(currents, dtype=float)[None, :], a, rho * rho * self.u2)

    def saturated_share(self) -> float:
        """Share of the fixed cycle's coil-windows whose model error ``((rho I)^2 + tau^2) |u|^2``
        exceeds the white noise ``sigma^2 (1/n_u + 1/n_b)`` of the extraction."""
        nu, nb = pulse_samples(self.T0, self.B0, self.tm, "mean")
        c = self.cfg
        model = ((c.adaptive.field_model_rel_sigma * self.I0[None, :]) ** 2 + c.limits.current_tolerance_a ** 2) * self.u2
        return float(np.mean(model > c.pulse.mag_sigma_t ** 2 * (1 / nu + 1 / nb)))

    def cost(self, kinds: Kinds) -> WindowCost:
        c = self.cfg
        return WindowCost(kinds, c.pulse.mag_sigma_t ** 2, self.u2, c.adaptive.field_model_rel_sigma,
                          c.limits.current_tolerance_a, self.imax, self.D)

    def exponents(self, hi: tuple, lo: tuple, rho_sweep: float, currents=(0.91, 0.45)) -> tuple[float, float]:
        """(a_pos, a_rot) fitted to the fixed cycle's current sweep: figures ``hi``/``lo`` =
        (position RMS, orientation RMS, energy) at ``currents`` (those of ``schepers-fixed-910`` and
        ``-450``, ``tools/scenarios/adaptive.py``) with the sweep's model error."""
        J = [np.einsum("wk,wkij->wij", self.window * self.weight(np.full(len(self.I0), i), rho_sweep), self.Jt)
             for i in currents]
        return (fit_exponent(J[0], J[1], hi[0], lo[0], POS), fit_exponent(J[0], J[1], hi[1], lo[1], ROT))


def summarise(model: SeedModel, kinds: Kinds, out: dict, duration_s: float) -> dict:
    """Where and how the optimum spends: the energy-weighted pulse length, baseline and current, the
    pulses per second, the windows whose time binds, the duty over two windows, near against far."""
    d = out.pop("detail")
    e, time, kind = d["energy"], d["time"], d["kind"]
    slot = kinds.slot[kind]
    pulses = np.where(slot > 0, time / slot, 0.0)
    on = pulses * kinds.T[kind]                                               # on-time (W, K)
    pair = on[:-1] + on[1:] if len(on) > 1 else on
    ew = e / max(e.sum(), 1e-300)
    r = np.linalg.norm(model.p, axis=1)
    near = r < np.median(r)
    out.pop("y")
    out.update(pulse_ms=float(np.sum(ew * kinds.T[kind]) * 1e3), baseline_ms=float(np.sum(ew * kinds.baseline[kind]) * 1e3),
               current_a=float(np.sqrt(np.sum(ew * d["current"] ** 2))),
               pulses_per_s=float(pulses.sum() / duration_s), time_bound_share=float(np.mean(d["mu"] > 0)),
               duty_max=float(pair.max() / (2 * model.D)),
               energy_near_far=[float(e[near].sum() / e.sum()), float(e[~near].sum() / e.sum())])
    return out


def seed_bound(seed: int, a_pos: float | None, a_rot: float | None, ratio: float, window: int, duration_s: float,
               modes=MODES, sweeps: tuple | None = None, kinds_args: dict | None = None, phase: str = "mean") -> dict:
    """The bound on one seed's ``schepers-adaptive`` trajectory for each of ``modes``; the exponents
    not given are fitted to ``sweeps`` = (hi figures, lo figures, the sweeps' model error)."""
    model = SeedModel(seed, window, duration_s, phase=phase)
    if a_pos is None or a_rot is None:
        fp, fr = model.exponents(sweeps[0], sweeps[1], sweeps[2])
        a_pos = fp if a_pos is None else a_pos
        a_rot = fr if a_rot is None else a_rot
    r = np.linalg.norm(model.p, axis=1)
    row = {"seed": seed, "a_pos": a_pos, "a_rot": a_rot, "windows": len(r), "range_m": [float(r.min()), float(r.max())],
           "saturated_share": model.saturated_share(), "modes": {}}
    ka = dict(fixed_pulse_s=model.T0, baseline_s=model.B0, long_baseline_s=0.1, max_pulse_s=0.4, step_s=0.0005)
    ka.update(kinds_args or {})
    for mode in modes:
        kinds = mode_kinds(mode, model.tm, phase=phase, **ka)
        out = least_energy(model.Jt, model.x0, model.cost(kinds), model.ref_energy, a_pos, a_rot, ratio)
        row["modes"][mode] = summarise(model, kinds, out, duration_s)
    return row


def _sweep_model_error() -> float:
    """The model error of the ``schepers-fixed-910``/``-450`` sweeps the exponents are fitted to."""
    from coiltrack.tools import scenarios

    return float(scenarios.get("schepers-fixed-910").firmware_config().adaptive.field_model_rel_sigma)


def _arguments(argv):
    ap = argparse.ArgumentParser(prog="python -m coiltrack.tools.analyses.energy_bound", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=_seeds_arg, default=list(range(1, 11)), help="seeds, e.g. 1-10 (default 1-10)")
    ap.add_argument("--ratio", type=float, default=1.1, help="RMS allowed against the fixed cycle (default 1.1)")
    ap.add_argument("--window", type=int, default=1, help="cycle periods per window (default 1)")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds (default 60)")
    ap.add_argument("--pulse-length", choices=("fixed", "chosen", "all"), default="all",
                    help="fixed: the cycle's 60 ms pulses and 35 ms baselines; chosen: any pulse length with "
                         "those baselines, and with baselines of --long-baseline-ms as well; all: both (default)")
    ap.add_argument("--columns", help="a comma list of columns (fixed, chosen, chosen-long) instead of --pulse-length's")
    ap.add_argument("--long-baseline-ms", type=float, default=100.0, help="the longer baselines (default 100)")
    ap.add_argument("--max-pulse-ms", type=float, default=400.0, help="longest pulse considered (default 400)")
    ap.add_argument("--length-step-ms", type=float, default=0.5,
                    help="pulse-length grid step up to 100 ms, ten times it to 200 ms (default 0.5)")
    ap.add_argument("--grid-lengths", action="store_true",
                    help="only the grid's lengths, each a real pulse: the companion from above of the bound's "
                         "credit between grid points (the least energy over every length lies between the two)")
    ap.add_argument("--sample-phase", choices=("mean", "aligned"), default="mean",
                    help="mean: pulses not timed to the magnetometer's samples (default); aligned: each at its best phase")
    ap.add_argument("--sweeps", default="docs/adaptive-sweeps",
                    help="folder with fixed-910.json and fixed-450.json (exponents per seed)")
    ap.add_argument("--a-pos", type=float, help="position exponent for every seed instead of the sweeps'")
    ap.add_argument("--a-rot", type=float, help="orientation exponent for every seed instead of the sweeps'")
    ap.add_argument("--json", help="write the figures as JSON")
    return ap.parse_args(argv)


def _check(a) -> str | None:
    if not (a.ratio >= 1.0) or a.window < 1 or not (a.duration > 0):
        return "--ratio must be >= 1, --window >= 1, --duration > 0"
    if not (a.long_baseline_ms > 0 and a.length_step_ms > 0 and a.max_pulse_ms > a.length_step_ms):
        return "--long-baseline-ms and --length-step-ms must be > 0, --max-pulse-ms > --length-step-ms"
    bad = [m for m in (a.columns or "").split(",") if a.columns and m.strip() not in MODES]
    if bad:
        return f"--columns: unknown column(s) {bad}; choose from {', '.join(MODES)}"
    for name in ("a_pos", "a_rot"):
        v = getattr(a, name)
        if v is not None and not (v > 0):
            return f"--{name.replace('_', '-')} must be > 0, got {v}"
    return None


def main(argv=None) -> int:
    a = _arguments(argv)
    bad = _check(a)
    if bad:
        print(f"energy_bound: {bad}", file=sys.stderr)
        return 2
    modes = {"fixed": ("fixed",), "chosen": ("chosen", "chosen-long"), "all": MODES}[a.pulse_length]
    if a.columns:
        modes = tuple(m.strip() for m in a.columns.split(","))
    hi = lo = None
    if a.a_pos is None or a.a_rot is None:
        try:
            hi, lo = _sweep_figures(f"{a.sweeps}/fixed-910.json"), _sweep_figures(f"{a.sweeps}/fixed-450.json")
        except (OSError, ValueError) as e:
            print(f"energy_bound: --sweeps: {e}", file=sys.stderr)
            return 2
        missing = [s for s in a.seeds if s not in hi or s not in lo]
        if missing:
            print(f"energy_bound: --sweeps: no run of seed(s) {missing} in {a.sweeps}", file=sys.stderr)
            return 2
    ka = dict(long_baseline_s=a.long_baseline_ms * 1e-3, max_pulse_s=a.max_pulse_ms * 1e-3,
              step_s=a.length_step_ms * 1e-3, grid_lengths=a.grid_lengths)
    rho_s = _sweep_model_error() if hi is not None else 0.0
    rows = []
    print(f"least energy / fixed cycle at {a.ratio:g} x its RMS; columns: " + ", ".join(modes))
    for s in a.seeds:
        sw = (hi[s], lo[s], rho_s) if hi is not None else None
        row = seed_bound(s, a.a_pos, a.a_rot, a.ratio, a.window, a.duration, modes, sw, ka, a.sample_phase)
        rows.append(row)
        cells = "  ".join(f"{m} {r['energy_fraction']:.3f} ({r['pulse_ms']:.0f} ms, {r['baseline_ms']:.0f} ms, "
                          f"{'ok' if r['converged'] else r['message']})" for m, r in row["modes"].items())
        print(f"seed {s:2d}: a_pos {row['a_pos']:.2f} a_rot {row['a_rot']:.2f} saturated {row['saturated_share']:.2f}  {cells}")
    summary = {}
    for m in modes:
        f = np.array([r["modes"][m]["energy_fraction"] for r in rows])
        summary[m] = {"median": float(np.median(f)), "worst": float(f.max()), "best": float(f.min())}
        print(f"{m:12s} least energy fraction: median {np.median(f):.3f}, worst {f.max():.3f}, best {f.min():.3f}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"ratio": a.ratio, "window_cycles": a.window, "duration_s": a.duration,
                       "sample_phase": a.sample_phase, "long_baseline_ms": a.long_baseline_ms,
                       "max_pulse_ms": a.max_pulse_ms, "length_step_ms": a.length_step_ms,
                       "grid_lengths": a.grid_lengths,
                       "seeds": rows, "summary": summary}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
