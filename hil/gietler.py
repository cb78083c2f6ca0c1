"""Gietler et al. 2019 as a measurement-level experiment: moving emitters, a fixed receiver.

``seeds/003_93f59c2e1c5b6c59.txt``, sec III-C and IV-C: three emitter dipoles
of 1 A m^2 on a moving platform (emitter 1 at the platform origin ``z``,
emitter 2 at ``z + R p12``, emitter 3 at ``z + R p13``, ``p12 = (0.05, 0.05,
0.05)`` m, ``p13 = (-0.02, 0.03, 0.02)`` m, moments along z, y, x as in
sec IV-A), time-multiplexed, and a receiver at the origin measuring the 3-D
field strength ``H`` (A/m) of each emitter every ``dt`` with white noise of
variance ``sigma^2`` per component. At AC the receiver is synchronous with
the emitters and measures the field phasor (real and imaginary parts, each
with the same noise), so an object's phase is seen.

The platform may carry an object (a cube fixed to the emitter frame). Its
response is computed here, independently of the firmware's compensation
model, by :class:`CubeResponse`: the discrete-dipole (coupled-dipole) solution of
the magnetostatic volume integral equation on a fine lattice (default
10 x 10 x 10 cells) in the emitters' non-uniform fields, with an equivalent
complex permeability ``mu_eff`` that carries the eddy currents:
``mu_eff = (1 - W) / (1 + W / 2)`` with ``W`` the exact response of the
conducting, permeable sphere of the same volume (:func:`hil.conductors.sphere_response`,
Wait 1951), so a sphere of ``mu_eff`` in a uniform field has exactly Wait's
moment (DC: ``mu_eff = mu_r``; perfect conductor: ``mu_eff = 0``, the
field excluded). This equivalent medium is the emulator's own approximation
for a cube (it is exact for the sphere, which the tests check through the
same lattice solver). The object's field is the sum of the fine cells'
dipoles, each rotating with the platform.
"""
from __future__ import annotations

import functools
import math

import numpy as np

from coiltrack.hil.conductors import sphere_response
from coiltrack.hil.motion import BrownianMotion, Helix, euler_zyx_to_matrix

P12 = np.array([0.05, 0.05, 0.05])
P13 = np.array([-0.02, 0.03, 0.02])
#: emitter positions in the platform frame (emitter 1 is the origin), m
EMITTER_OFFSETS = np.array([np.zeros(3), P12, P13])
#: emitter moments in the platform frame, A m^2 (sec IV-A: m0 = z, m1 = y, m2 = x)
EMITTER_MOMENTS = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
FREQ_HZ = 450e3
MU0 = 4e-7 * math.pi


def dipole_h(points, position, moment):
    """``H = (1 / 4 pi) (3 r (m . r) / r^5 - m / r^3)`` (eq 1), A/m; ``points`` (n, 3),
    ``position`` (n, 3) or (3,), complex or real ``moment`` (n, 3) or (3,)."""
    r = np.asarray(points, dtype=float) - np.asarray(position, dtype=float)
    r2 = np.sum(r * r, axis=-1, keepdims=True)
    mr = np.sum(r * moment, axis=-1, keepdims=True)
    return (3.0 * r * mr / r2 - moment) / (4.0 * math.pi * r2 * np.sqrt(r2))


# ---------------------------------------------------------------- the object

def mu_effective(freq_hz: float, sigma: float, mu_r: float, radius: float) -> complex:
    """Equivalent complex relative permeability of a body of the sphere's response (see module)."""
    if freq_hz == 0.0 or sigma == 0.0:
        return complex(mu_r)
    W = sphere_response(2.0 * math.pi * freq_hz, radius, sigma, mu_r)
    return complex((1.0 - W) / (1.0 + W / 2.0))


def lattice_solve(cells: np.ndarray, cell_volume: float, mu: complex, applied: np.ndarray) -> np.ndarray:
    """Coupled-dipole solution: moments ``p`` (k, n, 3), A m^2, of ``n`` cubic cells at
    ``cells`` (n, 3) for ``k`` applied fields ``applied`` (k, n, 3) A/m.

    Each cell is a small sphere of the Clausius-Mossotti polarisability
    ``alpha = 3 v (mu - 1) / (mu + 2)`` in its local field, the applied field plus
    every other cell's dipole field: ``p_j / alpha - sum_{k != j} G_jk p_k = H0_j``,
    ``G_jk = (3 r r^T / r^2 - I) / (4 pi r^3)``."""
    n = len(cells)
    alpha = 3.0 * cell_volume * (mu - 1.0) / (mu + 2.0)
    d = cells[:, None, :] - cells[None, :, :]
    r2 = np.einsum("ijk,ijk->ij", d, d)
    np.fill_diagonal(r2, 1.0)
    inv3 = 1.0 / (4.0 * math.pi * r2 * np.sqrt(r2))
    G = (3.0 * d[:, :, :, None] * d[:, :, None, :] / r2[:, :, None, None] - np.eye(3)) * inv3[:, :, None, None]
    idx = np.arange(n)
    G[idx, idx] = 0.0
    A = -G.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n).astype(complex)
    A[np.arange(3 * n), np.arange(3 * n)] += 1.0 / alpha
    rhs = np.asarray(applied, dtype=complex).reshape(len(applied), 3 * n).T
    p = np.linalg.solve(A, rhs)
    return p.T.reshape(len(applied), n, 3)


def cube_cells(center, edge: float, n: int) -> tuple[np.ndarray, float]:
    """Centres (n^3, 3) and volume of the ``n x n x n`` cells of a cube."""
    h = edge / n
    g = (np.arange(n) + 0.5) * h - edge / 2.0
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    return np.asarray(center, float) + np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1), h ** 3


def sphere_cells(radius: float, n_across: int) -> tuple[np.ndarray, float]:
    """Centres and volume of the cubic cells whose centres lie in a sphere at the origin, with
    the cell edge chosen so that their total volume is the sphere's."""
    h = 2.0 * radius / n_across
    g = (np.arange(n_across) + 0.5) * h - radius
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    pts = pts[np.einsum("ij,ij->i", pts, pts) <= radius * radius]
    v = 4.0 / 3.0 * math.pi * radius ** 3 / len(pts)
    return pts * (v ** (1 / 3) / h), v


class CubeResponse:
    """A conductive and/or permeable cube fixed to the platform: its induced dipoles per emitter.

    ``center`` (m, platform frame), ``edge`` (m), ``sigma`` (S/m), ``mu_r``, ``freq_hz``
    (0 for DC), ``n`` cells per edge. ``cells`` (N, 3) and ``moments`` (3 emitters, N, 3)
    complex, A m^2, both in the platform frame."""

    def __init__(self, center, edge: float, sigma: float, mu_r: float, freq_hz: float, n: int = 10):
        self.center = np.asarray(center, dtype=float)
        self.edge, self.sigma, self.mu_r, self.freq_hz, self.n = edge, sigma, mu_r, freq_hz, n
        radius = edge * (3.0 / (4.0 * math.pi)) ** (1.0 / 3.0)
        self.mu_eff = mu_effective(freq_hz, sigma, mu_r, radius)
        self.cells, self.cell_volume = cube_cells(self.center, edge, n)
        applied = np.stack([dipole_h(self.cells, EMITTER_OFFSETS[k], EMITTER_MOMENTS[k]) for k in range(3)])
        self.moments = lattice_solve(self.cells, self.cell_volume, self.mu_eff, applied)

    def field(self, points, z, R) -> np.ndarray:
        """Object field phasor (n, 3 emitters, 3), A/m, at ``points`` (n, 3) for platform poses
        ``z`` (n, 3), ``R`` (n, 3, 3)."""
        out = np.zeros((len(points), 3, 3), dtype=complex)
        for i in range(len(points)):
            y = z[i] + self.cells @ R[i].T
            for k in range(3):
                m = self.moments[k] @ R[i].T
                out[i, k] = dipole_h(points[i][None, :], y, m).sum(axis=0)
        return out


@functools.lru_cache(maxsize=8)
def cube_response(center: tuple, edge: float, sigma: float, mu_r: float, freq_hz: float, n: int = 10) -> CubeResponse:
    """:class:`CubeResponse`, solved once per process and parameter set."""
    return CubeResponse(center, edge, sigma, mu_r, freq_hz, n)


# ---------------------------------------------------------------- runs

def brownian_truth(seed: int, duration_s: float, dt_s: float, sigma_v: float, sigma_w: float, z0, v0, theta0,
                   omega0=(0.0, 0.0, 0.0)) -> dict:
    """Eq 8 sampled every ``dt_s`` (``hil.motion.BrownianMotion``, no restoring terms):
    ``t`` (s), ``z``, ``v``, ``theta``, ``omega`` (n + 1, 3) from t = 0."""
    bm = BrownianMotion(seed, duration_s, dt_s, sigma_v, sigma_w, z0=z0, v0=v0, theta0=theta0, omega0=omega0,
                        stiffness=0.0, damping=0.0, angular_damping=0.0, wall_stiffness=0.0)
    nd = bm.nodes()
    return {"t": nd["t_us"] * 1e-6, "z": nd["z"], "v": nd["v"], "theta": nd["theta"], "omega": nd["omega"]}


def helix_truth(duration_s: float, dt_s: float) -> dict:
    """Eq 33 every ``dt_s`` from t = 0 (``hil.motion.Helix`` parameters)."""
    hx = Helix(duration_s=duration_s)
    n = int(round(duration_s / dt_s))
    t = np.arange(n + 1) * dt_s
    a, w = hx.radius, hx.omega
    z = np.stack([a * np.cos(w * t), a * np.sin(w * t), hx.climb * t], axis=1)
    v = np.stack([-a * w * np.sin(w * t), a * w * np.cos(w * t), np.full_like(t, hx.climb)], axis=1)
    th = np.stack([np.full_like(t, hx.roll), np.zeros_like(t), hx.yaw_rate * t], axis=1)
    om = np.zeros_like(th)
    om[:, 2] = hx.yaw_rate
    return {"t": t, "z": z, "v": v, "theta": th, "omega": om}


def true_fields(truth: dict, obj: CubeResponse | None = None, receiver=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Field phasor of each emitter at the receiver (n, 3 emitters, 3), A/m, complex: eq 1
    for the emitters plus, with ``obj``, the object's induced field."""
    z = truth["z"]
    R = np.stack([euler_zyx_to_matrix(th) for th in truth["theta"]])
    x = np.broadcast_to(np.asarray(receiver, float), z.shape)
    out = np.zeros((len(z), 3, 3), dtype=complex)
    for k in range(3):
        pos = z + np.einsum("nij,j->ni", R, EMITTER_OFFSETS[k])
        mom = np.einsum("nij,j->ni", R, EMITTER_MOMENTS[k])
        out[:, k] = dipole_h(x, pos, mom)
    if obj is not None:
        out += obj.field(np.ascontiguousarray(x), z, R)
    return out


def measurements(fields: np.ndarray, noise_var: float, ac: bool, rng: np.random.Generator) -> np.ndarray:
    """Noisy measurements (n, m): real parts of the 3 emitters' fields (m = 9), and at AC their
    imaginary parts after them (m = 18), each plus N(0, noise_var)."""
    n = len(fields)
    clean = fields.real.reshape(n, 9)
    if ac:
        clean = np.concatenate([clean, fields.imag.reshape(n, 9)], axis=1)
    return clean + math.sqrt(noise_var) * rng.standard_normal(clean.shape)
