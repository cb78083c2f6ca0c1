"""The static distortion of the room: a residual-field map added inside the one signal model.

Metal fixed in the room (a steel table, a frame) responds to every coil's field with a field of
its own, proportional to that coil's current and fixed in the source frame: the distortion of
coil ``j`` at the source-frame point ``p`` is ``I_j D_j(p)``. Raab et al. 1979
(``seeds/004_86267342cd7488ce.txt``, "Source and Sensor Imperfections" and the distortion
compensation it leaves to a look-up or polynomial correction) correct the measured couplings; here
the map is part of the measurement model instead, so the solver fits the pose to

    ``h_j = R^T (B_j(p) + I_j D_j(p))``,   ``J_j = dB_j/dp + I_j dD_j/dp``

(``model.signal``: the Jacobian of Schepers & Veltink ``seeds/000_e46ec0e8bf7ea271.txt`` eqs 9-11
with the map's gradient added to ``J_j``, so ``H_j = [R^T J_j, [h_j]x]`` stays consistent).

Model: per coil, ``K_j`` equivalent dipoles at fixed source-frame positions ``q_jk`` (m) with
moments ``mu_jk`` per ampere of the coil (A m^2 / A), ``D_j(p) = sum_k B_dip(p - q_jk; mu_jk)``
(Schepers eq 8, ``field.dipole_point``: a magnetisable body's response seen from outside it, the
image-source picture of a coil above a permeable sheet). ``coiltrack calibrate --method survey``
(``coiltrack.tools.calibration.survey``) fits the positions and moments to the residual field of a survey of
the working volume and writes them as the ``[distortion]`` table of the calibration file:

.. code-block:: toml

    [distortion]
    model = "dipoles"
    coils = 3
    coil0_position_m = [[x, y, z], ...]          # K_0 rows
    coil0_moment_am2_per_a = [[mx, my, mz], ...]
    coil0_position_m_sigma = [[...], ...]        # 1-sigma of each (optional)
    coil0_moment_am2_per_a_sigma = [[...], ...]
    residual_rms_t = 1.2e-9                      # the fit's residual per unit current (T/A)
    n_points = 294

Cost: one dipole kernel per equivalent dipole and point (~1/5 of an exact loop evaluation, no
elliptic integral); counted in :attr:`DistortionMap.evals`, beside the coil evaluations of
``SignalModel.evals`` that bound a tick's work. Everything preallocated; :meth:`add` allocates no
numpy array.
"""
from __future__ import annotations

import math

from coiltrack.firmware.model.field import dipole_point

__all__ = ["DistortionMap"]

#: the largest map accepted (equivalent dipoles per coil): bounds the kernel calls per evaluation
MAX_DIPOLES_PER_COIL = 16


def _rows(table: dict, key: str, required: bool = True):
    v = table.get(key)
    if v is None:
        if required:
            raise KeyError(f"distortion.{key}: missing")
        return None
    if not isinstance(v, list) or not all(isinstance(r, list) and len(r) == 3 for r in v):
        raise ValueError(f"distortion.{key}: must be an array of [x, y, z] rows")
    out = []
    for r in v:
        t = tuple(float(x) for x in r)
        if not all(math.isfinite(x) for x in t):
            raise ValueError(f"distortion.{key}: values must be finite")
        out.append(t)
    return out


class DistortionMap:
    """Equivalent dipoles of the room's static distortion, per coil (module docstring).

    Parameters
    ----------
    positions : list over coils of lists of (x, y, z), m, source frame
    moments : list over coils of lists of (mx, my, mz), A m^2 per A of the coil
    sigmas : optional dict of the 1-sigma arrays as read (kept for the report)
    meta : optional dict (``residual_rms_t``, ``n_points``)

    Attributes: ``n`` (coils), ``evals`` (dipole kernels evaluated so far).
    """

    def __init__(self, positions, moments, sigmas=None, meta=None):
        if len(positions) != len(moments) or not positions:
            raise ValueError("distortion: positions and moments need one entry per coil")
        self.n = len(positions)
        self._q = []
        self._m = []
        for j in range(self.n):
            q, m = list(positions[j]), list(moments[j])
            if len(q) != len(m):
                raise ValueError(f"distortion.coil{j}: as many positions as moments")
            if len(q) > MAX_DIPOLES_PER_COIL:
                raise ValueError(f"distortion.coil{j}: at most {MAX_DIPOLES_PER_COIL} dipoles per coil")
            self._q.append(tuple(tuple(float(v) for v in r) for r in q))
            self._m.append(tuple(tuple(float(v) for v in r) for r in m))
        self.sigmas = dict(sigmas or {})
        self.meta = dict(meta or {})
        self.evals = 0

    @property
    def dipoles(self) -> int:
        """Equivalent dipoles over all coils (kernels per evaluation point)."""
        return sum(len(q) for q in self._q)

    @classmethod
    def from_table(cls, table: dict, n_coils: int | None = None) -> "DistortionMap":
        """Parse the ``[distortion]`` table (module docstring); ``n_coils``, if given, must match."""
        if not isinstance(table, dict):
            raise ValueError("distortion: must be a table")
        model = table.get("model", "dipoles")
        if model != "dipoles":
            raise ValueError(f"distortion.model: only 'dipoles' is known, got {model!r}")
        n = table.get("coils")
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise ValueError(f"distortion.coils: must be a positive integer, got {n!r}")
        if n_coils is not None and n != n_coils:
            raise ValueError(f"distortion.coils: the map has {n} coils, the source {n_coils}")
        pos, mom, sig = [], [], {}
        for j in range(n):
            pos.append(_rows(table, f"coil{j}_position_m"))
            mom.append(_rows(table, f"coil{j}_moment_am2_per_a"))
            for key in (f"coil{j}_position_m_sigma", f"coil{j}_moment_am2_per_a_sigma"):
                s = _rows(table, key, required=False)
                if s is not None:
                    sig[key] = s
        meta = {k: table[k] for k in ("residual_rms_t", "n_points") if k in table}
        return cls(pos, mom, sig, meta)

    def to_table(self) -> dict:
        d = {"model": "dipoles", "coils": self.n}
        for j in range(self.n):
            d[f"coil{j}_position_m"] = [list(r) for r in self._q[j]]
            d[f"coil{j}_moment_am2_per_a"] = [list(r) for r in self._m[j]]
        for k, v in self.sigmas.items():
            d[k] = [list(r) for r in v]
        d.update(self.meta)
        return d

    # ------------------------------------------------------------ run time
    def add(self, px: float, py: float, pz: float, cur, jac: bool, Bv, Jv) -> None:
        """Add ``I_j D_j(p)`` to ``Bv[3 j + r]`` (T) and, if ``jac``, ``I_j dD_j/dp`` to
        ``Jv[9 j + 3 r + c]`` (T/m) for every coil ``j`` (the flat layouts of
        ``SignalModel.B`` / ``J``); ``cur`` n currents, A."""
        for j in range(self.n):
            i = cur[j]
            if i == 0.0:
                continue
            o = 3 * j
            g = 9 * j
            ms = self._m[j]
            for k, (qx, qy, qz) in enumerate(self._q[j]):
                mx, my, mz = ms[k]
                t = dipole_point(px - qx, py - qy, pz - qz, mx * i, my * i, mz * i, jac)
                self.evals += 1
                Bv[o] += t[0]
                Bv[o + 1] += t[1]
                Bv[o + 2] += t[2]
                if jac:
                    Jv[g] += t[3]
                    Jv[g + 4] += t[4]
                    Jv[g + 8] += t[5]
                    Jv[g + 1] += t[6]
                    Jv[g + 3] += t[6]
                    Jv[g + 2] += t[7]
                    Jv[g + 6] += t[7]
                    Jv[g + 5] += t[8]
                    Jv[g + 7] += t[8]

    def field(self, j: int, px: float, py: float, pz: float) -> tuple:
        """``D_j(p)`` per ampere (T/A), for tools and tests (a tuple)."""
        bx = by = bz = 0.0
        for k, (qx, qy, qz) in enumerate(self._q[j]):
            mx, my, mz = self._m[j][k]
            t = dipole_point(px - qx, py - qy, pz - qz, mx, my, mz, False)
            bx += t[0]
            by += t[1]
            bz += t[2]
        return bx, by, bz
