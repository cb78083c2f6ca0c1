"""Static metal in the room: a steel table under the working volume.

The table top is a mild-steel sheet, a linear, isotropic, magnetisable body
of relative permeability ``mu_r`` (no hysteresis, no saturation: the coil
fields at the table are tens of uT, far below the knee of mild steel,
whose initial permeability is 100-300; 200 by default). The sheet is cut
into ``nx x ny`` cuboid cells of uniform polarisation ``J_i`` (T), and the
polarisations are solved self-consistently (the volume-integral / method of
moments formulation of magnetostatics, as in Radia or magpylib's material
response):

    ``J_i = mu0 chi H_i``,  ``H_i = B0(x_i) / mu0 + sum_j G_ij J_j``

with ``chi = mu_r - 1``, ``B0`` the applied field (one coil at 1 A, or the
earth field) at the cell centre ``x_i`` and ``G_ij`` the H field at
``x_i`` of cell ``j`` at unit polarisation, *including* the cell's own
demagnetising field (``j = i``), from magpylib's exact cuboid field
(``magpylib.func.cuboid_field``, Yang et al. 1990 / Engel-Herbert 2005
closed forms). That is the linear system ``(I - chi mu0 G) J = chi B0``,
solved once per coil and once for the earth field (``3 n_cells`` unknowns).
The field of the table at any point is then the sum of the cells' exact
cuboid fields (magpylib again), linear in the coil currents:

    ``B_table(p) = sum_k I_k F_k(p) + F_earth(p)``.

The solver is checked against the closed form of a permeable sphere in a
uniform field (a voxelised sphere: uniform magnetisation
``M = 3 (mu_r - 1) / (mu_r + 2) H0``, ``tests/hil/test_room.py``).

Objects respond to the source and earth fields only (the coils are not
loaded by the table). The sheet's eddy currents are left out: the
diffusion time through a 5 mm sheet of 6 MS/m, ``mu0 mu_r sigma t^2 / pi^2``,
is 3.8 ms, and the pulse amplitudes, the survey's and the tracker's alike,
see the settled, static response (the ``metal`` fault models transients).

Placement is seeded (:class:`SteelTable` ``seed``): the table's centre is
moved by up to 3 cm in x and y and lowered by up to 2 cm.
"""
from __future__ import annotations

import numpy as np

from . import physics

__all__ = ["SteelTable", "solve_polarisation", "cuboid_cells_field"]

MU0 = physics.MU0


def cuboid_cells_field(points, centres, dims, J) -> np.ndarray:
    """B (T) at ``points`` (m, (m, 3)) of cuboid cells (centres (n, 3) m, edge lengths ``dims``
    (n, 3) m, axis-aligned) of polarisation ``J`` (n, 3) T: the sum over the cells (m, 3)."""
    import magpylib as magpy

    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    n = centres.shape[0]
    m = pts.shape[0]
    obs = np.repeat(pts, n, axis=0)
    B = magpy.func.cuboid_field("B", obs, np.tile(dims, (m, 1)), np.tile(J, (m, 1)), np.tile(centres, (m, 1)))
    return B.reshape(m, n, 3).sum(axis=1)


def _interaction(centres, dims) -> np.ndarray:
    """``G`` (3n, 3n): H (A/m) at centre i of cell j at unit polarisation (1 T) along each axis."""
    import magpylib as magpy

    n = centres.shape[0]
    obs = np.repeat(centres, n, axis=0)            # row i*n + j: observer i, source j
    src = np.tile(centres, (n, 1))
    dim = np.tile(dims, (n, 1))
    G = np.zeros((n, 3, n, 3))
    for a in range(3):
        J = np.zeros((n * n, 3))
        J[:, a] = 1.0
        H = magpy.func.cuboid_field("H", obs, dim, J, src).reshape(n, n, 3)     # [i, j, component]
        G[:, :, :, a] = H.transpose(0, 2, 1)
    return G.reshape(3 * n, 3 * n)


def solve_polarisation(centres, dims, mu_r: float, B0) -> np.ndarray:
    """Self-consistent cell polarisations ``J`` (n, 3) T of linear cells of relative permeability
    ``mu_r`` in the applied fields ``B0`` ((n, 3) T at the cell centres, or (k, n, 3) for k fields
    at once): ``(I - chi mu0 G) J = chi B0`` (module docstring)."""
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    dims = np.broadcast_to(np.asarray(dims, dtype=float), centres.shape).copy()
    n = centres.shape[0]
    chi = float(mu_r) - 1.0
    A = np.eye(3 * n) - chi * MU0 * _interaction(centres, dims)
    B0 = np.asarray(B0, dtype=float)
    rhs = chi * B0.reshape(-1, 3 * n).T
    J = np.linalg.solve(A, rhs).T
    return J.reshape(B0.shape)


class SteelTable:
    """A flat steel sheet (the table top) in the source frame, its thin dimension along the source
    axis ``up_axis`` (0: x, 1: y, 2: z): the top face at ``top_m`` on that axis, the sheet
    centred at ``centre_m`` on the other two (in axis order), ``size_m`` along them,
    ``thickness_m`` thick, relative permeability ``mu_r``, cut into ``cells`` cuboids.

    Defaults: the source stands on the table with its +x axis up (the firmware's hemisphere, the
    side the roetenberg-bench sensor stays on: ``x >= 0.061 m``, ``hil.motion.HandMovedBench``),
    its centre 25 cm above a 1.6 m (y) x 1.2 m (z) x 5 mm sheet, 40 x 30 cells of 4 cm.

    A :mod:`hil.world` object: ``field_at`` (coils and earth), ``coil_unit_field`` (steady
    response per ampere of coil k: what a pulse amplitude sees); always active unless
    ``t_on_us`` / ``t_off_us`` are given.
    """

    def __init__(self, top_m: float = -0.25, centre_m=(0.0, 0.0), size_m=(1.6, 1.2), up_axis: int = 0,
                 thickness_m: float = 0.005, mu_r: float = 200.0, cells=(40, 30), seed: int | None = None,
                 t_on_us=None, t_off_us=None):
        if up_axis not in (0, 1, 2):
            raise ValueError("up_axis must be 0, 1 or 2")
        a, b = (int(i) for i in (0, 1, 2) if i != up_axis)
        ca, cb = float(centre_m[0]), float(centre_m[1])
        top = float(top_m)
        if seed is not None:
            rng = np.random.default_rng([int(seed), 0x7AB1E])
            ca += rng.uniform(-0.03, 0.03)
            cb += rng.uniform(-0.03, 0.03)
            top -= rng.uniform(0.0, 0.02)
        self.up_axis = up_axis
        self.top_m = top
        self.size_m = (float(size_m[0]), float(size_m[1]))
        self.thickness_m = float(thickness_m)
        self.mu_r = float(mu_r)
        self.centre = np.zeros(3)
        self.centre[up_axis], self.centre[a], self.centre[b] = top - 0.5 * thickness_m, ca, cb
        na, nb = int(cells[0]), int(cells[1])
        da, db = self.size_m[0] / na, self.size_m[1] / nb
        ua = ca - 0.5 * self.size_m[0] + da * (np.arange(na) + 0.5)
        ub = cb - 0.5 * self.size_m[1] + db * (np.arange(nb) + 0.5)
        A, B = np.meshgrid(ua, ub, indexing="ij")
        C = np.zeros((A.size, 3))
        C[:, a], C[:, b], C[:, up_axis] = A.ravel(), B.ravel(), self.centre[up_axis]
        self.cell_centres = C
        dims = np.zeros(3)
        dims[a], dims[b], dims[up_axis] = da, db, self.thickness_m
        self.cell_dims = np.tile(dims, (A.size, 1))
        self.t_on_us, self.t_off_us = t_on_us, t_off_us
        self._J = None          # (ncoils + 1, ncells, 3): per ampere of each coil, then the earth field

    def active(self, t_us: int) -> bool:
        return ((self.t_on_us is None or t_us >= self.t_on_us)
                and (self.t_off_us is None or t_us < self.t_off_us))

    def describe(self) -> dict:
        return {"kind": "steel_table", "up_axis": "xyz"[self.up_axis], "top_m": round(self.top_m, 4),
                "centre_m": [round(float(v), 4) for v in self.centre], "size_m": list(self.size_m),
                "thickness_m": self.thickness_m, "mu_r": self.mu_r, "cells": int(self.cell_centres.shape[0])}

    def solve(self, world) -> np.ndarray:
        """The cells' polarisations per ampere of each coil and for the earth field (once)."""
        if self._J is None:
            U = world.source.unit_fields(self.cell_centres)          # (ncoils, ncells, 3) T/A
            B0 = np.concatenate([U, np.broadcast_to(world.earth, self.cell_centres.shape)[None]], axis=0)
            self._J = solve_polarisation(self.cell_centres, self.cell_dims, self.mu_r, B0)
        return self._J

    def response(self, world, points, weights) -> np.ndarray:
        """B (T, (m, 3)) of the table at ``points`` for the applied-field weights
        ``(I_1, .., I_n, earth)`` (n + 1 floats: coil currents in A, 1 or 0 for the earth)."""
        J = np.tensordot(np.asarray(weights, dtype=float), self.solve(world), axes=1)
        return cuboid_cells_field(points, self.cell_centres, self.cell_dims, J)

    def field_at(self, world, t_us: int, p, R) -> np.ndarray:
        w = np.append(world.coil_currents(t_us), 1.0)
        return self.response(world, p, w)[0]

    def coil_unit_field(self, world, k: int, p, R) -> np.ndarray:
        w = np.zeros(len(world.coils) + 1)
        w[k] = 1.0
        return self.response(world, p, w)[0]
