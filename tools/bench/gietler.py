"""Gietler et al. 2019 run path: emulated measurements (``hil.gietler``) into the firmware's
Brownian-motion filters (``firmware.estimate.brownian``), without the protocol bench.

The experiment of ``seeds/003_93f59c2e1c5b6c59.txt`` sec III-C and IV-C is a
measurement-level one (emitter fields at a fixed receiver plus white noise), so
a run here is: the true trajectory (eq 8 or the helix eq 33), the field of each
emitter at the receiver (with the object's, computed by the bench's lattice
solver), noise of variance ``sigma^2``; then the plain EKF and the iterated EKF,
each with the base model ``H0`` (eq 1) and, when the scenario has an object,
the extended model ``H0 + H~`` (eq 32) whose sub-volume integrals (eqs 29-31)
are precomputed from the bench's solution on the firmware's coarser
79-sub-volume partition. The figures of a run: per filter and model the
time-averaged squared position error (m^2) over the run and whether it
diverged (the estimate left the 2 m sphere; the run of that filter stops). A
run ends early, for every filter and without a divergence, when the true
platform itself leaves the 2 m sphere (the unbounded eq-8 motion does so in
2 of the first 100 seeds of Table I), or comes closer than ``min_range_m``
(0.1 m) to the receiver with emitter 1 or the object's centre (the unbounded
motion can carry the cube through the receiver): ``steps`` is the number of
updates scored.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

#: filter variants: (figure suffix, model, iterated)
VARIANTS = (("", "extended", True), ("_ekf", "extended", False), ("_base", "base", True),
            ("_ekf_base", "base", False))


@dataclass(frozen=True)
class GietlerFilterConfig:
    """The Brownian-motion filters' settings (``003_93f59c2e1c5b6c59.txt`` eqs 6-24;
    ``coiltrack.firmware.estimate.brownian``): a research experiment's, not the firmware's
    configuration. A sweep sets them as ``--set gietler.KEY=V`` (:func:`filter_config_from_dict`)."""
    gietler_dt_s: float = 0.1               # s, filter step (sec III-C: delta tau = 0.1 s)
    gietler_sigma_v: float = 0.01           # m s^-3/2, velocity Wiener intensity of the model (eq 6)
    gietler_sigma_w: float = 0.1            # rad s^-3/2, Euler-rate Wiener intensity (eq 7)
    gietler_noise_var: float = 1e-4         # (A/m)^2, measurement noise variance per component (eq 14)
    gietler_p0: float = 0.1                 # initial covariance P0 = p0 I (eq 17; 0.1 in sec III-C)
    gietler_iterations: int = 3             # iterated EKF: at most this many linearisations per step (1: EKF)
    gietler_iter_tol: float = 1e-4          # m or rad: the iteration stops when no state moves more
    gietler_diverge_m: float = 2.0          # m: an estimate farther from the receiver has diverged

    def validate(self) -> "GietlerFilterConfig":
        """Return self, or raise ConfigError naming ``gietler.KEY``."""
        from coiltrack.firmware.config import ConfigError

        for name in ("gietler_dt_s", "gietler_sigma_v", "gietler_sigma_w", "gietler_noise_var", "gietler_p0",
                     "gietler_iter_tol", "gietler_diverge_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise ConfigError(f"gietler.{name}", f"must be a positive number, got {v!r}")
        v = self.gietler_iterations
        if not (isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 100):
            raise ConfigError("gietler.gietler_iterations", f"must be an integer in 1..100 (1: the plain EKF), got {v!r}")
        return self


def filter_config_from_dict(d: dict, base: GietlerFilterConfig | None = None) -> GietlerFilterConfig:
    """``{"gietler": {key: value}}`` over ``base``, validated; anything else refused by name."""
    from coiltrack.firmware.config import ConfigError

    base = base or GietlerFilterConfig()
    kw = {}
    names = {f.name: f.default for f in fields(GietlerFilterConfig)}
    for sec, table in d.items():
        if sec != "gietler" or not isinstance(table, dict):
            raise ConfigError(sec if not isinstance(table, dict) else f"{sec}.{next(iter(table), '')}",
                              "not a setting of the Gietler experiment (its sections: gietler, noise)")
        for key, value in table.items():
            if key not in names:
                raise ConfigError(f"gietler.{key}", f"unknown key (the gietler section has: {', '.join(names)})")
            if isinstance(names[key], int):
                if not isinstance(value, int) or isinstance(value, bool):
                    raise ConfigError(f"gietler.{key}", f"must be an integer, got {value!r}")
            elif not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ConfigError(f"gietler.{key}", f"must be a number, got {value!r}")
            else:
                value = float(value)
            kw[key] = value
    return replace(base, **kw).validate()


@dataclass(frozen=True)
class GietlerSpec:
    """One of the paper's experiments (all SI units)."""
    trajectory: str = "brownian"           # "brownian" (eq 8) | "helix" (eq 33)
    duration_s: float = 20.0
    dt_s: float = 0.1
    sigma_v: float = 0.01
    sigma_w: float = 0.1
    v0: tuple = (0.01, 0.0, -0.005)
    z0: tuple = (0.2, -0.2, 0.3)
    omega0: tuple = (0.0, 0.0, 0.0)
    theta0: tuple = (0.02, -0.05, math.pi / 4)
    x0_filter: dict = field(default_factory=lambda: {"v": (0, 0, 0), "z": (0.05, -0.1, 0.4), "omega": (0, 0, 0),
                                                     "theta": (0.0, 0.0, 1.0)})
    noise_var: float = 1e-4               # (A/m)^2, the emulated noise
    # the object fixed to the emitters (None: air)
    cube_center: tuple | None = None       # platform frame, m
    cube_edge: float = 0.05
    sigma: float = 0.0
    mu_r: float = 1.0
    freq_hz: float = 0.0                   # 0: DC
    lattice_n: int = 10
    # S/m: the conductivity the bench's eddy currents see, when it differs from the material's
    # ``sigma`` (None: ``sigma``). ``gietler-ferro`` follows the paper's FEM response (Table III),
    # which is that of the mu_r 100 material with a 1 mm skin (5 kS/m), not the 0.24 mm skin
    # of 0.1 MS/m: see ``scenarios_gietler.PAPER_FEM_FERRO_SIGMA``
    eddy_sigma: float | None = None
    # the experiment ends when the receiver comes closer than this to emitter 1 or the cube's
    # centre (point sources, and a receiver outside the object, no longer hold)
    min_range_m: float = 0.1


def coarse_partition(center, edge: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The firmware's 79 sub-volumes (Gietler Fig. 4: finer toward the emitters): five layers
    of ``edge / 5`` along z, of 2x2, 3x3, 4x4, 5x5 and 5x5 cells from the far (-z) to the near
    (+z) face. Returns the lower corners, upper corners and centres (79, 3)."""
    c = np.asarray(center, dtype=float)
    lo, hi = [], []
    for layer, k in enumerate((2, 3, 4, 5, 5)):
        z0, z1 = -edge / 2 + layer * edge / 5, -edge / 2 + (layer + 1) * edge / 5
        g = np.linspace(-edge / 2, edge / 2, k + 1)
        for i in range(k):
            for j in range(k):
                lo.append((g[i], g[j], z0))
                hi.append((g[i + 1], g[j + 1], z1))
    lo, hi = c + np.array(lo), c + np.array(hi)
    return lo, hi, (lo + hi) / 2.0


def compensation_table(obj, center, edge: float):
    """Sub-volume integrals for the firmware (eq 31): the bench's fine-cell moments summed over
    each coarse sub-volume ``B_i`` (the integral of the magnetisation, ``(mu*/mu0 - 1) H_i``),
    at the sub-volume centre; per emitter (3, 79, 3) complex, with the centres (79, 3)."""
    lo, hi, centres = coarse_partition(center, edge)
    inside = np.all((obj.cells[None, :, :] >= lo[:, None, :] - 1e-12) & (obj.cells[None, :, :] < hi[:, None, :] - 1e-12),
                    axis=2)
    # a fine cell on the upper face of the cube belongs to the last sub-volume
    owner = np.argmax(inside, axis=0)
    assert np.all(inside.any(axis=0)), "a fine cell outside the partition"
    moments = np.zeros((3, len(centres), 3), dtype=complex)
    for k in range(3):
        np.add.at(moments[k], owner, obj.moments[k])
    return centres, moments


def platform_model(spec: GietlerSpec, extended: bool, obj=None):
    """The firmware's measurement model for the spec (base: the three emitters; extended: plus
    the 3 x 79 compensation dipoles)."""
    from coiltrack.firmware.model.emitters import DIPOLE, PlatformModel
    from coiltrack.hil.gietler import EMITTER_MOMENTS, EMITTER_OFFSETS

    offsets, moments, channels = list(EMITTER_OFFSETS), list(EMITTER_MOMENTS.astype(complex)), [0, 1, 2]
    if extended and obj is not None:
        centres, table = compensation_table(obj, spec.cube_center, spec.cube_edge)
        for k in range(3):
            offsets.extend(centres)
            moments.extend(table[k])
            channels.extend([k] * len(centres))
    return PlatformModel(offsets, moments, [DIPOLE] * len(offsets), channels, 3, ac=spec.freq_hz > 0.0)


def bench_object(spec: GietlerSpec):
    if spec.cube_center is None:
        return None
    from coiltrack.hil.gietler import cube_response

    sigma = spec.sigma if spec.eddy_sigma is None else spec.eddy_sigma
    return cube_response(tuple(spec.cube_center), spec.cube_edge, sigma, spec.mu_r, spec.freq_hz, spec.lattice_n)


def truth_and_measurements(spec: GietlerSpec, seed: int, obj=None):
    from coiltrack.hil import gietler as hg

    if spec.trajectory == "helix":
        truth = hg.helix_truth(spec.duration_s, spec.dt_s)
    else:
        truth = hg.brownian_truth(seed, spec.duration_s, spec.dt_s, spec.sigma_v, spec.sigma_w, spec.z0, spec.v0,
                                  spec.theta0, spec.omega0)
    fields = hg.true_fields(truth, obj)
    # the noise stream is the seed's own, independent of the trajectory's
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x6E01]))
    V = hg.measurements(fields, spec.noise_var, spec.freq_hz > 0.0, rng)
    return truth, V


def run_filter(spec: GietlerSpec, cfg, model, truth: dict, V: np.ndarray, iterated: bool) -> dict:
    """One filter (configured by the :class:`GietlerFilterConfig` ``cfg``) over the run:
    ``mse_m2`` (time average of |z - z^|^2 over the updates; None when diverged),
    ``diverged`` (0/1), ``iterations`` (iterates over the run, one model evaluation each),
    ``evals`` (field evaluations), ``z_hat`` (n, 3)."""
    from coiltrack.firmware.estimate.brownian import BrownianEKF
    from coiltrack.firmware.estimate.layout import BROWNIAN_LAYOUT as L

    diverge_m = cfg.gietler_diverge_m
    f = BrownianEKF(model, cfg.gietler_dt_s, cfg.gietler_sigma_v, cfg.gietler_sigma_w, cfg.gietler_noise_var,
                    iterations=cfg.gietler_iterations if iterated else 1, tol=cfg.gietler_iter_tol)
    x0 = np.zeros(L.n)
    x0[L.VEL], x0[L.POS] = spec.x0_filter["v"], spec.x0_filter["z"]
    x0[L.RATE], x0[L.THETA] = spec.x0_filter["omega"], spec.x0_filter["theta"]
    f.reset(x0, cfg.gietler_p0 * np.eye(L.n))
    n = len(V) - 1
    # the experiment ends when the true platform leaves the range (the paper's 2 m sphere): a filter
    # that follows it out is not diverged
    near = np.linalg.norm(truth["z"][1:], axis=1) < spec.min_range_m
    if spec.cube_center is not None:
        from coiltrack.hil.motion import euler_zyx_to_matrix

        c = truth["z"][1:] + np.einsum("nij,j->ni", euler_zyx_to_matrix(truth["theta"][1:]), np.asarray(spec.cube_center))
        near |= np.linalg.norm(c, axis=1) < spec.min_range_m
    out = np.flatnonzero((np.linalg.norm(truth["z"][1:], axis=1) > diverge_m) | near)
    n_end = int(out[0]) if out.size else n
    err2 = np.zeros(max(n_end, 1))
    zh = np.full((n, 3), np.nan)
    diverged = False
    edge_sigma = None
    for t in range(1, n_end + 1):
        f.step(V[t])
        zh[t - 1] = f.x[L.POS]
        if not np.all(np.isfinite(f.x)) or float(np.linalg.norm(f.x[L.POS])) > diverge_m:
            diverged = True
            edge_sigma = _edge_sigma(f.x[L.POS], f.P[L.POS, L.POS], truth["z"][t], diverge_m)
            break
        d = f.x[L.POS] - truth["z"][t]
        err2[t - 1] = float(d @ d)
    return {"mse_m2": None if diverged else float(err2.mean()), "diverged": int(diverged),
            "iterations": f.iterations_total, "evals": model.evals, "z_hat": zh, "steps": n_end,
            "edge_sigma": edge_sigma}


def _edge_sigma(z_hat, P_pos, z_true, diverge_m: float):
    """At a divergence: how far the true platform was inside the boundary, in the filter's own
    radial standard deviations, ``(diverge_m - |z|) / sqrt(u^T P u)`` with ``u = z^ / |z^|``
    (None for a non-finite estimate). Small values (<= 3) mark a consistent estimate that crossed
    a boundary the platform itself had nearly reached; large ones an estimate that ran off."""
    if not (np.all(np.isfinite(z_hat)) and np.all(np.isfinite(P_pos))):
        return None
    u = z_hat / float(np.linalg.norm(z_hat))
    s2 = float(u @ P_pos @ u)
    if not s2 > 0.0:
        return None
    return (diverge_m - float(np.linalg.norm(z_true))) / math.sqrt(s2)


def run(spec: GietlerSpec, cfg, seed: int, variants=VARIANTS) -> dict:
    """Every filter variant on one seed's measurements: the figures of the run (``mse_m2``,
    ``diverged``, ``iterations``, ``evals``, each with the variant's suffix of :data:`VARIANTS`;
    in air there is one model, reported without ``_base``)."""
    obj = bench_object(spec)
    truth, V = truth_and_measurements(spec, seed, obj)
    out = {}
    models = {}
    for suffix, model_name, iterated in variants:
        if obj is None and model_name == "base":
            continue
        if model_name not in models:
            models[model_name] = platform_model(spec, model_name == "extended", obj)
        model = models[model_name]
        model.evals = 0
        r = run_filter(spec, cfg, model, truth, V, iterated)
        for k in ("mse_m2", "diverged", "iterations", "evals", "edge_sigma"):
            out[k + suffix] = r[k]
        out["steps"] = r["steps"]
    return out
