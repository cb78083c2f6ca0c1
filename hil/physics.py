"""Physics of the emulated bench: coil fields, coil currents, eddy currents,
ferromagnetic and conducting objects, earth field.

SI units throughout (tesla, metre, ampere, second); times are integer
microseconds. Run-time dependencies are numpy and magpylib only. The field of
a winding is the sum of its turns, each a ``magpylib.current.Circle``
(exact circular filament, complete elliptic integrals, Ortner et al. 2023);
this module never uses the firmware's own field models.

Model summary (what the firmware does *not* know about):

* :class:`SourceCoil`: finite winding cross-section (inner/outer radius,
  length) discretised into a grid of circular filaments, axis misalignment,
  resistance and inductance. The field is linear in the current, so callers
  evaluate the per-ampere field once per point (:meth:`SourceCoil.unit_field`,
  :meth:`Source.unit_fields`) and scale by the instantaneous current.
* :class:`CoilCurrent`: regulated pulses with first-order L/R rise and fall
  (thesis ``002_cd7f1fdb7fc67471.txt`` sec 5.2: pulsed DC, 60 ms pulses;
  sec 7.2: edges, then steady state), a pulse's own L/R (a heated winding) and
  the driver's ripple on its flat top (``hil.nodes.DriverAccuracy``).
* :class:`EddyConductor`: lumped eddy-current dipole, a first-order high-pass
  of the coil moment (thesis sec 5.5 / 7.2, Schepers ``000_e46ec0e8bf7ea271.txt``
  sec 5: eddy currents appear at the edges and "decay at an exponential rate
  with a time constant defined by the ratio between inductance and resistance
  of the object"). It is the one-sub-volume, first-order-in-time reduction of
  Gietler ``003_93f59c2e1c5b6c59.txt`` eqs 27, 31 (first term).
* :class:`FerroSphere`: induced dipole of a linear magnetic sphere (the
  ferromagnetic term of Gietler eq 27 for a sphere, in closed form).
* :class:`ConductingSphere`: exact transient eddy response of a non-magnetic
  conducting sphere (mode series), an analytic reference case; with ``mu_r``
  the permeable sphere's modes (:func:`permeable_sphere_modes`, Wait 1951: the
  roots and residues of :func:`hil.conductors.sphere_response`), steel.
* :data:`EARTH_FIELD_T`, :class:`EarthField`, :func:`sensor_frame`.
* :class:`MagneticScene`: sums all of the above at sensor points and times.

Objects respond to the source and earth fields only (first-order scattering:
no object-object interaction, no back-action on the coil current).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Iterable, Sequence

import magpylib
import numpy as np

from coiltrack.hil.motion import matrix_to_rotvec, rotvec_to_matrix

__all__ = [
    "MU0",
    "EARTH_FIELD_T",
    "wheeler_inductance",
    "ring_inductance",
    "SourceCoil",
    "Source",
    "thesis_source",
    "dipole_field",
    "CoilCurrent",
    "EddyConductor",
    "FerroSphere",
    "ConductingSphere",
    "permeable_sphere_roots",
    "permeable_sphere_modes",
    "EarthField",
    "sensor_frame",
    "MagneticScene",
]

#: vacuum permeability (H/m), the value magpylib uses
MU0: float = float(magpylib.mu_0)

#: earth field in the world/source frame (T): ~20 uT horizontal along +x, ~45 uT down
#: (z up), roughly the Netherlands where the thesis measurements were made
EARTH_FIELD_T = np.array([20e-6, 0.0, -45e-6])


# ---------------------------------------------------------------------------
# Inductance formulas
# ---------------------------------------------------------------------------


def wheeler_inductance(turns: int, mean_radius: float, length: float, depth: float) -> float:
    """Wheeler's multilayer air-core formula (H).

    ``L = 31.6e-6 N^2 r^2 / (6 r + 9 l + 10 d)`` with mean radius ``r``, winding
    length ``l`` and depth ``d`` in metres (the metric form of
    ``0.8 a^2 N^2 / (6a + 9b + 10c)`` uH in inches). About 1 % when the three
    denominator terms are comparable; for thin rings it ignores the
    logarithmic dependence on the cross-section (see :func:`ring_inductance`).
    """
    r = mean_radius
    return 31.6e-6 * turns**2 * r * r / (6.0 * r + 9.0 * length + 10.0 * depth)


def ring_inductance(turns: int, mean_radius: float, length: float, depth: float) -> float:
    """Inductance of a ring coil with a small rectangular cross-section (H).

    Maxwell's formula ``L = mu0 N^2 a (ln(8 a / g) - 2)`` with the geometric
    mean distance of the rectangular section ``g = 0.2235 (l + d)``; valid for
    ``l, d << a`` (error of order ``((l + d)/a)^2``).
    """
    g = 0.2235 * (length + depth)
    if g <= 0.0:
        raise ValueError("ring_inductance needs a finite cross-section")
    return MU0 * turns**2 * mean_radius * (math.log(8.0 * mean_radius / g) - 2.0)


# ---------------------------------------------------------------------------
# Small geometry helpers
# ---------------------------------------------------------------------------


def _frame_with_z(axis: np.ndarray) -> np.ndarray:
    """Rotation matrix whose third column is ``axis`` (unit)."""
    z = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = helper - z * (helper @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def _default_grid(turns: int, depth: float, length: float) -> tuple[int, int]:
    """(layers, turns per layer) with ``layers * per_layer == turns`` and near-square cells."""
    if depth <= 0.0 and length <= 0.0:
        return 1, 1
    if depth <= 0.0:
        return 1, turns
    if length <= 0.0:
        return turns, 1
    best, best_cost = (1, turns), float("inf")
    for nr in range(1, turns + 1):
        if turns % nr:
            continue
        na = turns // nr
        cost = abs(math.log((depth / nr) / (length / na)))
        if cost < best_cost - 1e-12:
            best, best_cost = (nr, na), cost
    return best


def dipole_field(points: np.ndarray, position: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """Point-dipole field ``B = mu0/(4 pi) (3 r_hat (r_hat . m) - m) / r^3`` (T).

    Thesis eq 5.2 / Schepers eq 8 in vector form. ``points`` (n, 3); ``moment``
    (3,) or (n, 3) A m^2.
    """
    d = np.asarray(points, dtype=float) - np.asarray(position, dtype=float)
    r2 = np.sum(d * d, axis=-1, keepdims=True)
    r = np.sqrt(r2)
    m = np.asarray(moment, dtype=float)
    mr = np.sum(d * m, axis=-1, keepdims=True)
    return MU0 / (4.0 * np.pi) * (3.0 * d * mr / r2 - m) / (r2 * r)


# ---------------------------------------------------------------------------
# Source coils
# ---------------------------------------------------------------------------


@dataclass
class SourceCoil:
    """One source coil.

    Geometry: ``center`` (3,) m and nominal ``axis`` (3,) in the source/world
    frame; winding of ``turns`` turns with mean ``radius``, radial extent
    ``inner_radius..outer_radius`` and axial ``length`` (defaults: thin coil,
    all turns on one filament). ``misalignment`` is a small rotation vector
    (rad, world frame) applied to the nominal axis: the true axis is
    ``rotvec_to_matrix(misalignment) @ axis`` (Raab ``004`` source
    imperfections; the firmware assumes the nominal axis).

    Discretisation: ``grid = (layers, turns_per_layer)`` circular filaments at
    the centres of a regular grid over the cross-section, each carrying
    ``turns / (layers * turns_per_layer)`` times the coil current (a uniform
    current density, midpoint rule). Default: one filament per physical turn
    (``layers * per_layer == turns``, near-square cells), or one filament for a
    thin coil. A finer grid converges to the continuous winding (error
    O(cell size^2)). ``quadrature="gauss"`` instead puts the filaments at
    Gauss-Legendre nodes of the cross-section (default 2 x 2), which
    integrates the uniform current density to O(cell size^4) away from the
    winding: 12x fewer filaments than turn by turn for the thesis coil, at a
    relative difference below 1e-5 beyond 10 cm (see the tests).

    Electrical: ``resistance`` (ohm, default 2.0) and ``inductance`` (H,
    default :func:`ring_inductance` when the cross-section is finite and
    smaller than ``radius/5``, else :func:`wheeler_inductance`).

    The geometry is fixed at construction (filament arrays, the magpylib
    Collection and the fast-path arrays are built once); make a new coil to
    change it.
    """

    center: np.ndarray
    axis: np.ndarray
    radius: float
    turns: int
    inner_radius: float | None = None
    outer_radius: float | None = None
    length: float = 0.0
    misalignment: np.ndarray = dc_field(default_factory=lambda: np.zeros(3))
    resistance: float = 2.0
    inductance: float | None = None
    grid: tuple[int, int] | None = None
    quadrature: str = "turns"
    name: str = ""
    #: effective turns x area relative to the nominal winding (a gain error, Raab ``004``
    #: source imperfections): scales every filament's current; the inductance is kept
    gain: float = 1.0

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, dtype=float).reshape(3)
        self.axis = np.asarray(self.axis, dtype=float).reshape(3)
        self.axis = self.axis / np.linalg.norm(self.axis)
        self.misalignment = np.asarray(self.misalignment, dtype=float).reshape(3)
        if self.inner_radius is None:
            self.inner_radius = self.radius
        if self.outer_radius is None:
            self.outer_radius = self.radius
        if not (0.0 < self.inner_radius <= self.radius <= self.outer_radius):
            raise ValueError("need 0 < inner_radius <= radius <= outer_radius")
        if self.length < 0.0 or self.turns < 1:
            raise ValueError("need length >= 0 and turns >= 1")
        depth = self.outer_radius - self.inner_radius
        if self.grid is None:
            if self.quadrature == "gauss":
                self.grid = (1 if depth == 0.0 else 2, 1 if self.length == 0.0 else 2)
            else:
                self.grid = _default_grid(int(self.turns), depth, self.length)
        if self.inductance is None:
            if 0.0 < depth + self.length and max(depth, self.length) < self.radius / 5.0:
                self.inductance = ring_inductance(self.turns, self.radius, self.length, depth)
            else:
                self.inductance = wheeler_inductance(self.turns, self.radius, self.length, depth)
        nr, na = self.grid
        if self.quadrature == "turns":
            r_edges = np.linspace(self.inner_radius, self.outer_radius, nr + 1)
            z_edges = np.linspace(-0.5 * self.length, 0.5 * self.length, na + 1)
            r_nodes = 0.5 * (r_edges[1:] + r_edges[:-1])
            z_nodes = 0.5 * (z_edges[1:] + z_edges[:-1])
            r_w = np.full(nr, 1.0 / nr)
            z_w = np.full(na, 1.0 / na)
        elif self.quadrature == "gauss":
            xr, wr = np.polynomial.legendre.leggauss(nr)
            xz, wz = np.polynomial.legendre.leggauss(na)
            r_nodes = 0.5 * (self.inner_radius + self.outer_radius) + 0.5 * depth * xr
            z_nodes = 0.5 * self.length * xz
            r_w, z_w = 0.5 * wr, 0.5 * wz
        else:
            raise ValueError("quadrature must be 'turns' or 'gauss'")
        rr, zz = np.meshgrid(r_nodes, z_nodes, indexing="ij")
        self._fil_r = rr.ravel()
        self._fil_z = zz.ravel()
        self._fil_w = self.turns * np.outer(r_w, z_w).ravel()
        if self.gain != 1.0:
            self._fil_w = self._fil_w * float(self.gain)
        self._collection = None
        self._source = None

    # -- geometry -------------------------------------------------------------

    @property
    def true_axis(self) -> np.ndarray:
        """Unit axis after misalignment (world frame)."""
        return rotvec_to_matrix(self.misalignment) @ self.axis

    @property
    def rotation(self) -> np.ndarray:
        """Rotation from the coil frame (winding in the xy-plane, axis +z) to the world frame."""
        return _frame_with_z(self.true_axis)

    @property
    def filaments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(radius, axial offset, turns carried)`` of each filament, coil frame."""
        return self._fil_r.copy(), self._fil_z.copy(), self._fil_w.copy()

    @property
    def moment_per_amp(self) -> np.ndarray:
        """Dipole moment per ampere (A m^2 / A): ``sum_i w_i pi r_i^2`` along the true axis (thesis eq 5.3)."""
        return float(np.sum(self._fil_w * np.pi * self._fil_r**2)) * self.true_axis

    @property
    def tau_s(self) -> float:
        """Electrical time constant L/R (s)."""
        return float(self.inductance) / float(self.resistance)

    # -- fields ---------------------------------------------------------------

    def unit_field(self, points: np.ndarray) -> np.ndarray:
        """Field per ampere of coil current at ``points`` (n, 3) -> (n, 3) T/A, world frame."""
        if self._source is None:
            self._source = Source([self])
        return self._source.unit_fields(points)[0]

    def field(self, points: np.ndarray, current: float) -> np.ndarray:
        """Field (T) at ``points`` (n, 3) for a coil current (A)."""
        return current * self.unit_field(points)

    def collection(self) -> magpylib.Collection:
        """The winding as a magpylib Collection of ``Circle`` filaments at 1 A coil current (built once)."""
        if self._collection is None:
            children = [
                magpylib.current.Circle(current=float(w), diameter=2.0 * float(r), position=(0.0, 0.0, float(z)))
                for r, z, w in zip(self._fil_r, self._fil_z, self._fil_w)
            ]
            col = magpylib.Collection(*children)
            rv = matrix_to_rotvec(self.rotation)
            angle = float(np.linalg.norm(rv))
            if angle > 0.0:
                col.rotate_from_angax(angle, rv / angle, anchor=(0.0, 0.0, 0.0), degrees=False)
            col.move(self.center)
            self._collection = col
        return self._collection

    def unit_field_magpylib(self, points: np.ndarray) -> np.ndarray:
        """Reference path: ``Collection.getB`` (slower, same result as :meth:`unit_field`)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        return np.asarray(self.collection().getB(pts)).reshape(pts.shape)


class Source:
    """Several coils evaluated together (one vectorised filament-field call).

    Behaves as a sequence of :class:`SourceCoil` (``len``, indexing, iteration).
    :meth:`unit_fields` returns the per-ampere field of every coil at a batch
    of points, shape ``(n_coils, n_points, 3)``; the total field for currents
    ``I`` (A, shape (n_coils,)) is ``einsum("k,kni->ni", I, unit_fields)``.

    The fast path transforms the points once per coil into cylindrical
    coordinates and evaluates all filaments of all coils in one call of
    ``magpylib.core.current_circle_Hfield`` (the same kernel that
    ``magpylib.current.Circle.getB`` uses), so no per-call object handling.
    """

    def __init__(self, coils: Iterable[SourceCoil]):
        self.coils: list[SourceCoil] = list(coils)
        if not self.coils:
            raise ValueError("a Source needs at least one coil")
        self.refresh()

    def refresh(self) -> None:
        """Build the precomputed filament arrays of all coils."""
        self._centers = np.stack([c.center for c in self.coils])
        self._axes = np.stack([c.true_axis for c in self.coils])
        r, z, w, k = [], [], [], []
        for i, c in enumerate(self.coils):
            r.append(c._fil_r)
            z.append(c._fil_z)
            w.append(c._fil_w)
            k.append(np.full(c._fil_r.size, i))
        self._fil_r = np.concatenate(r)
        self._fil_z = np.concatenate(z)
        self._fil_w = np.concatenate(w)
        self._fil_k = np.concatenate(k)
        self._starts = np.concatenate([[0], np.cumsum([c._fil_r.size for c in self.coils])[:-1]])

    def __len__(self) -> int:
        return len(self.coils)

    def __getitem__(self, i):
        return self.coils[i]

    def __iter__(self):
        return iter(self.coils)

    @property
    def moments_per_amp(self) -> np.ndarray:
        return np.stack([c.moment_per_amp for c in self.coils])

    def unit_fields(self, points: np.ndarray) -> np.ndarray:
        """Per-ampere field of each coil: (n, 3) points -> (n_coils, n, 3) T/A."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        n = pts.shape[0]
        d = pts[None, :, :] - self._centers[:, None, :]  # (K, n, 3)
        zc = np.einsum("kni,ki->kn", d, self._axes)  # axial coordinate
        radial = d - zc[..., None] * self._axes[:, None, :]
        rho = np.sqrt(np.sum(radial * radial, axis=-1))  # (K, n)
        F = self._fil_r.size
        r_obs = rho[self._fil_k].ravel()  # (F*n,)
        z_obs = (zc[self._fil_k] - self._fil_z[:, None]).ravel()
        r0 = np.repeat(self._fil_r, n)
        i0 = np.repeat(self._fil_w, n)
        H = magpylib.core.current_circle_Hfield(r0=r0, r=r_obs, z=z_obs, i0=i0)
        Hr = np.add.reduceat(H[0].reshape(F, n), self._starts, axis=0)  # (K, n)
        Hz = np.add.reduceat(H[2].reshape(F, n), self._starts, axis=0)
        safe = np.where(rho > 0.0, rho, 1.0)
        e_r = radial / safe[..., None]
        return MU0 * (Hr[..., None] * e_r + Hz[..., None] * self._axes[:, None, :])

    def field(self, points: np.ndarray, currents: Sequence[float]) -> np.ndarray:
        """Total field (T) at ``points`` (n, 3) for coil currents (A), (n_coils,)."""
        return np.einsum("k,kni->ni", np.asarray(currents, dtype=float), self.unit_fields(points))


def thesis_source(
    misalignment: Sequence[Sequence[float]] | None = None,
    section: float = 0.003,
    resistance: float = 2.0,
    center=(0.0, 0.0, 0.0),
    quadrature: str = "turns",
) -> Source:
    """The thesis source (``002_cd7f1fdb7fc67471.txt`` sec 5.2.1 / 6.3): three orthogonal coils.

    X, Y, Z coils sharing the origin, each 50 turns, mean radius 0.055 m
    (Fig. 5.4 / eq 5.5 design), wound on a ``section`` x ``section`` square
    cross-section (default 3 mm x 3 mm: 5 layers x 10 turns), R = 2 ohm,
    L from :func:`ring_inductance` (about 0.66 mH, tau = L/R about 0.33 ms).
    The thesis drives them with 1.5 A, 60 ms pulses, 600 ms cycle.
    ``misalignment``: optional (3, 3) rotation vectors (rad), one per coil.
    ``quadrature="gauss"`` gives the fast 2 x 2 Gauss filament model
    (see :class:`SourceCoil`).
    """
    mis = np.zeros((3, 3)) if misalignment is None else np.asarray(misalignment, dtype=float).reshape(3, 3)
    coils = []
    for i, name in enumerate("XYZ"):
        axis = np.zeros(3)
        axis[i] = 1.0
        coils.append(
            SourceCoil(
                center=np.asarray(center, dtype=float),
                axis=axis,
                radius=0.055,
                turns=50,
                inner_radius=0.055 - section / 2,
                outer_radius=0.055 + section / 2,
                length=section,
                misalignment=mis[i],
                resistance=resistance,
                quadrature=quadrature,
                name=name,
            )
        )
    return Source(coils)


# ---------------------------------------------------------------------------
# Coil current: regulated pulses with L/R edges
# ---------------------------------------------------------------------------


def _decay_diff(s: np.ndarray, tau_a: np.ndarray, tau_b: float) -> np.ndarray:
    """``(exp(-s/tau_a) - exp(-s/tau_b)) / (tau_a - tau_b)`` for ``s >= 0``, without overflow or cancellation.

    Equals ``-exp(-s/max(tau)) expm1(-s |d| / (tau_a tau_b)) / |d|`` with ``d = tau_a - tau_b``,
    and ``exp(-s/tau) s / tau^2`` in the limit ``d -> 0``.
    """
    tau_a = np.asarray(tau_a, dtype=float)
    tau_b = np.asarray(tau_b, dtype=float)
    d = np.abs(tau_a - tau_b)
    tmax = np.maximum(tau_a, tau_b)
    near = d < 1e-12 * tau_b
    safe = np.where(near, 1.0, d)
    val = -np.exp(-s / tmax) * np.expm1(-s * safe / (tau_a * tau_b)) / safe
    lim = np.exp(-s / tau_b) * s / (tau_b * tau_b)
    return np.where(near, lim, val)


class CoilCurrent:
    """Current of one coil driven by regulated pulses through R and L.

    Each pulse ``(start_us, duration_us, target_a)``: from ``start`` the
    driver regulates towards ``target`` and the current follows a first-order
    response with ``tau_rise`` (L/R),

        I(t) = I_T + (I(t0) - I_T) exp(-(t - t0)/tau_rise)   (= I_T (1 - exp(..)) from rest),

    and after ``start + duration`` it decays freely towards zero with
    ``tau_fall`` (default = ``tau_rise``). ``tau_rise`` is given directly or
    as ``inductance / resistance``. A pulse starting before the previous one
    ends cuts it short (see :meth:`add_pulse`). Times are
    integer microseconds; :meth:`current_at`, :meth:`didt_at` and
    :meth:`highpass_at` accept a scalar or an array of times.
    ``max_current_a`` (e.g. supply voltage / R, see :meth:`from_coil`) is the
    driver's compliance: a larger target is clipped to it (same sign).

    Internally the waveform is a list of segments ``(t0, I0, I_inf, tau)``;
    evaluation is a binary search plus one exponential, so arbitrary long
    pulse trains stay cheap. Pulses can be appended while the simulation runs
    (:meth:`add_pulse`), as a coil driver executing commands does.
    """

    def __init__(self, tau_rise_s: float | None = None, tau_fall_s: float | None = None,
                 pulses: Iterable[tuple[int, int, float]] = (), max_current_a: float | None = None,
                 *, resistance: float | None = None, inductance: float | None = None):
        if tau_rise_s is None:
            if resistance is None or inductance is None:
                raise ValueError("give tau_rise_s, or resistance and inductance")
            tau_rise_s = float(inductance) / float(resistance)
        if tau_rise_s < 0.0:
            raise ValueError("tau must be >= 0")
        self.max_current = None if max_current_a is None else abs(float(max_current_a))
        self.tau_rise = max(float(tau_rise_s), 1e-12)
        self.tau_fall = self.tau_rise if tau_fall_s is None else max(float(tau_fall_s), 1e-12)
        self._pulses: list[tuple[int, int, float]] = []
        self._seg_t: list[int] = []
        self._seg_i0: list[float] = []
        self._seg_inf: list[float] = []
        self._seg_tau: list[float] = []
        self._arrays = None
        self._hp_cache: dict[float, tuple[int, np.ndarray]] = {}
        self._pulse_taus: list[float | None] = []      # per pulse: its own L/R (None: tau_rise/tau_fall)
        self._ripple: tuple[list[int], list[tuple]] = ([], [])   # ripple spans: starts, (end, amp, omega, phase)
        self._edits: list[int] = []     # per edit (a pulse, a ripple span): the first time it changes
        for p in pulses:
            self.add_pulse(*p)

    @classmethod
    def from_coil(cls, coil: SourceCoil, tau_fall_s: float | None = None, pulses=(),
                  v_supply: float | None = None) -> "CoilCurrent":
        """Rise time constant ``L/R`` of ``coil``; with ``v_supply`` (V) the current cannot exceed ``V/R``."""
        limit = None if v_supply is None else v_supply / coil.resistance
        return cls(coil.tau_s, tau_fall_s, pulses, max_current_a=limit)

    @property
    def pulses(self) -> list[tuple[int, int, float]]:
        return list(self._pulses)

    def add_pulse(self, start_us: int, duration_us: int, target_a: float, tau_s: float | None = None) -> None:
        """Add a pulse (integer microseconds, amperes).

        The driver follows the latest command: a pulse that starts before the
        previous one has ended cuts it short at its own start. Pulses may be
        added in any order; appending in time order is O(1), anything else
        rebuilds the waveform. ``tau_s``: this pulse's L/R time constant for its
        rise and its fall (s; a winding whose resistance changed with its
        temperature), default ``tau_rise`` / ``tau_fall``.
        """
        start_us, duration_us = int(start_us), int(duration_us)
        if duration_us <= 0:
            raise ValueError("duration must be positive")
        if tau_s is not None and tau_s <= 0.0:
            raise ValueError("tau must be positive")
        target_a = float(target_a)
        if self.max_current is not None:
            target_a = math.copysign(min(abs(target_a), self.max_current), target_a)
        # before its start nothing changes: a pulse cuts an earlier one short at its own start
        self._edits.append(start_us)
        taus = self._pulse_taus
        if not self._pulses or start_us >= self._pulses[-1][0] + self._pulses[-1][1]:
            self._append(start_us, duration_us, target_a, tau_s)
            return
        pulses = sorted(zip(self._pulses + [(start_us, duration_us, target_a)], taus + [tau_s]),
                        key=lambda p: p[0][0])
        self._pulses, self._seg_t, self._seg_i0, self._seg_inf, self._seg_tau = [], [], [], [], []
        self._pulse_taus = []
        self._hp_cache.clear()
        self._arrays = None
        for i, ((s, d, a), tp) in enumerate(pulses):
            if i + 1 < len(pulses):
                d = min(d, pulses[i + 1][0][0] - s)
            if d > 0:
                self._append(s, d, a, tp)

    def add_ripple(self, start_us: int, end_us: int, amplitude_a: float, freq_hz: float, phase_rad: float) -> None:
        """A ripple ``amplitude sin(2 pi f (t - start) + phase)`` (A) on ``[start_us, end_us)``: the
        regulator's residual switching ripple on a pulse's flat top (:meth:`ripple_at`). It is
        kept apart from the regulated waveform of :meth:`current_at`: the pulse edges, the eddy
        high-pass (:meth:`highpass_at`; a conductor's response to a small kHz ripple is left out)
        and the flat-part ground truth see the smooth current, the field sees both
        (:meth:`hil.world.World.coil_currents`). Appended in time order."""
        rip = self._ripple
        self._edits.append(int(start_us))
        rip[0].append(int(start_us))
        rip[1].append((int(end_us), float(amplitude_a), 2.0 * math.pi * float(freq_hz), float(phase_rad)))

    def ripple_at(self, t_us) -> float:
        """The ripple (A) at integer microsecond time ``t_us`` (scalar); 0 outside every ripple span."""
        rip = self._ripple
        if not rip[0]:
            return 0.0
        t = int(t_us)
        k = bisect.bisect_right(rip[0], t) - 1
        if k < 0:
            return 0.0
        end, amp, om, ph = rip[1][k]
        if t >= end:
            return 0.0
        return amp * math.sin(om * (t - rip[0][k]) * 1e-6 + ph)

    #: alias used by the coil-driver node
    schedule = add_pulse

    @property
    def edits(self) -> int:
        """How many edits (pulses, ripple spans) the waveform has had: a mark for :meth:`edited_since`."""
        return len(self._edits)

    def edited_since(self, mark: int, t_us: int) -> bool:
        """True when an edit made after the mark ``mark`` (:attr:`edits` then) changed the current
        (or its ripple) at some time at or before ``t_us``: a value computed at the mark for a time up
        to ``t_us`` may no longer hold. An edit changes nothing before its pulse's (span's) start."""
        e = self._edits
        for i in range(mark, len(e)):
            if e[i] <= t_us:
                return True
        return False

    @property
    def tau_us(self) -> float:
        """Rise time constant in microseconds."""
        return self.tau_rise * 1e6

    def _append(self, start_us: int, duration_us: int, target_a: float, tau_s: float | None = None) -> None:
        i_start = self._value_at_end(start_us)
        rise = self.tau_rise if tau_s is None else float(tau_s)
        fall = self.tau_fall if tau_s is None else float(tau_s)
        self._seg_t.append(start_us)
        self._seg_i0.append(i_start)
        self._seg_inf.append(target_a)
        self._seg_tau.append(rise)
        s_on = duration_us * 1e-6
        i_end = target_a + (i_start - target_a) * math.exp(-s_on / rise)
        self._seg_t.append(start_us + duration_us)
        self._seg_i0.append(i_end)
        self._seg_inf.append(0.0)
        self._seg_tau.append(fall)
        self._pulses.append((start_us, duration_us, target_a))
        self._pulse_taus.append(tau_s)
        self._arrays = None

    def _value_at_end(self, t_us: int) -> float:
        if not self._seg_t:
            return 0.0
        t0, i0, inf, tau = self._seg_t[-1], self._seg_i0[-1], self._seg_inf[-1], self._seg_tau[-1]
        return inf + (i0 - inf) * math.exp(-(t_us - t0) * 1e-6 / tau)

    def _arr(self):
        if self._arrays is None:
            self._arrays = (
                np.asarray(self._seg_t, dtype=np.int64),
                np.asarray(self._seg_i0, dtype=float),
                np.asarray(self._seg_inf, dtype=float),
                np.asarray(self._seg_tau, dtype=float),
            )
        return self._arrays

    def _locate(self, t_us):
        t = np.asarray(t_us, dtype=np.int64)
        st, i0, inf, tau = self._arr()
        k = np.searchsorted(st, t, side="right") - 1
        active = k >= 0
        kk = np.where(active, k, 0)
        if st.size == 0:
            return t, active & False, kk, np.zeros(t.shape), None
        s = np.where(active, (t - st[kk]) * 1e-6, 0.0)
        return t, active, kk, s, (i0[kk], inf[kk], tau[kk])

    def _seg_scalar(self, t_us: int) -> int:
        """Index of the segment holding scalar time ``t_us`` (-1 before the first)."""
        return bisect.bisect_right(self._seg_t, t_us) - 1

    def current_at(self, t_us):
        """Coil current (A) at integer microsecond time(s)."""
        if isinstance(t_us, (int, np.integer)):          # scalar fast path (plain floats)
            k = self._seg_scalar(int(t_us))
            if k < 0:
                return 0.0
            inf, i0 = self._seg_inf[k], self._seg_i0[k]
            return inf + (i0 - inf) * math.exp(-(int(t_us) - self._seg_t[k]) * 1e-6 / self._seg_tau[k])
        t, active, kk, s, seg = self._locate(t_us)
        if seg is None:
            return np.zeros(t.shape) if t.ndim else 0.0
        i0, inf, tau = seg
        val = np.where(active, inf + (i0 - inf) * np.exp(-s / tau), 0.0)
        return val if t.ndim else float(val)

    def didt_at(self, t_us):
        """Time derivative of the current (A/s) (right derivative at edges)."""
        t, active, kk, s, seg = self._locate(t_us)
        if seg is None:
            return np.zeros(t.shape) if t.ndim else 0.0
        i0, inf, tau = seg
        val = np.where(active, -(i0 - inf) / tau * np.exp(-s / tau), 0.0)
        return val if t.ndim else float(val)

    def highpass_at(self, t_us, tau_s):
        """First-order high-pass of the current, ``y`` with ``tau y' + y = tau I'`` and ``y = 0`` at rest (A).

        Exact for the exponential segments: on a segment with ``I = I_inf +
        (I_0 - I_inf) exp(-s/tau_c)``,
        ``y(s) = y_0 exp(-s/tau) + tau (I_inf - I_0) (exp(-s/tau_c) - exp(-s/tau)) / (tau_c - tau)``.
        A step of the current makes ``y`` jump by the step and decay with ``tau``.
        ``tau_s`` scalar, or a 1-D array of time constants giving a leading axis
        (``(n_tau,) + shape(t_us)``).
        """
        if isinstance(t_us, (int, np.integer)) and isinstance(tau_s, (float, int)):
            return self._highpass_scalar(int(t_us), float(tau_s))
        taus = np.asarray(tau_s, dtype=float)
        if np.any(taus <= 0.0):
            raise ValueError("tau must be positive")
        t, active, kk, s, seg = self._locate(t_us)
        shape = taus.shape + t.shape
        if seg is None:
            return np.zeros(shape) if shape else 0.0
        i0, inf, tau_c = seg
        tt = taus.reshape(taus.shape + (1,) * t.ndim)
        if taus.ndim == 0:
            y0 = self._hp_starts(float(taus))[kk]
        else:
            y0 = np.stack([self._hp_starts(float(x))[kk] for x in taus])
        val = y0 * np.exp(-s / tt) + tt * (inf - i0) * _decay_diff(np.broadcast_to(s, shape), np.broadcast_to(tau_c, shape), tt)
        val = np.where(active, val, 0.0)
        return val if shape else float(val)

    def _highpass_scalar(self, t_us: int, tau: float) -> float:
        """:meth:`highpass_at` for one time and one time constant, in plain floats."""
        if tau <= 0.0:
            raise ValueError("tau must be positive")
        k = self._seg_scalar(t_us)
        if k < 0:
            return 0.0
        y0 = float(self._hp_starts(tau)[k])
        s = (t_us - self._seg_t[k]) * 1e-6
        i0, inf, tc = self._seg_i0[k], self._seg_inf[k], self._seg_tau[k]
        d = abs(tc - tau)
        if d < 1e-12 * tau:
            dd = math.exp(-s / tau) * s / (tau * tau)
        else:
            dd = -math.exp(-s / max(tc, tau)) * math.expm1(-s * d / (tc * tau)) / d
        return y0 * math.exp(-s / tau) + tau * (inf - i0) * dd

    def _hp_starts(self, tau: float) -> np.ndarray:
        """High-pass state at every segment start, extended incrementally as pulses are appended."""
        st, i0, inf, tc = self._arr()
        cached = self._hp_cache.get(tau)
        if cached is not None and cached[0] == st.size:
            return cached[1]
        done = 0 if cached is None else cached[0]
        y = np.zeros(st.size)
        if done:
            y[:done] = cached[1]
        for k in range(max(done, 1), st.size):
            s = (st[k] - st[k - 1]) * 1e-6
            y[k] = y[k - 1] * math.exp(-s / tau) + tau * (inf[k - 1] - i0[k - 1]) * float(
                _decay_diff(np.asarray(s), tc[k - 1], tau)
            )
        self._hp_cache[tau] = (st.size, y)
        return y


# ---------------------------------------------------------------------------
# Eddy currents, ferromagnetic and conducting objects
# ---------------------------------------------------------------------------


@dataclass
class EddyConductor:
    """Lumped eddy-current conductor: a secondary dipole at ``position``.

    Model: the conductor is a shorted secondary circuit
    with self-inductance ``L_e``, resistance ``R_e`` and mutual inductance ``M``
    to the coil, ``L_e I_e' + R_e I_e = -M I_c'``, so its current is a
    first-order high-pass of the coil current with ``tau_e = L_e / R_e``:
    ``I_e = -(M/L_e) HP_tau_e[I_c]``. Its moment is taken along the coil
    moment, scaled by the dimensionless ``coupling`` ``kappa`` (scalar, or a
    3x3 matrix for an anisotropic conductor):

        m_e(t) = -kappa @ m_c_per_amp * HP_tau_e[I_c](t)

    A current step makes ``m_e`` jump to ``-kappa m_c`` and decay as
    ``exp(-t/tau_e)``; in steady state it vanishes (thesis sec 7.2, Schepers
    sec 5). The field at the sensor is the point-dipole field of ``m_e``.
    For the thesis coil (``|m_c|`` = 0.48 A m^2/A) a coupling of 1e-3 gives
    0.07-0.14 uT at 10 cm from the conductor right after a 1.5 A step
    (a few times the thesis magnetometer noise of 0.05 uT, sec 5.2.1).
    This is Gietler eq 31 (first term) collapsed onto one sub-volume with a
    single relaxation time.
    """

    position: np.ndarray
    coupling: float | np.ndarray = 1e-3
    tau_s: float = 1e-3

    def __post_init__(self) -> None:
        self.position = np.asarray(self.position, dtype=float).reshape(3)
        if self.tau_s <= 0.0:
            raise ValueError("tau_s must be positive")

    def moment_per_amp(self, coil: SourceCoil) -> np.ndarray:
        """Eddy moment per ampere of high-passed coil current (A m^2 / A)."""
        k = np.asarray(self.coupling, dtype=float)
        m = coil.moment_per_amp
        return -(k @ m if k.ndim == 2 else k * m)

    def unit_field(self, points: np.ndarray, coil: SourceCoil) -> np.ndarray:
        """Field at ``points`` per ampere of ``HP[I_c]`` (T/A)."""
        return dipole_field(np.atleast_2d(points), self.position, self.moment_per_amp(coil))

    def field(self, points: np.ndarray, coil: SourceCoil, current: CoilCurrent, t_us) -> np.ndarray:
        """Eddy field (T) at ``points`` (n, 3) at time ``t_us`` (scalar or (n,))."""
        y = np.asarray(current.highpass_at(t_us, self.tau_s))
        u = self.unit_field(points, coil)
        return (y[..., None] if y.ndim else y) * u


@dataclass
class FerroSphere:
    """Small linear magnetic sphere (centre ``position``, radius, relative permeability).

    In a uniform applied field ``B0`` the sphere magnetises uniformly,
    ``M = 3 (mu_r - 1)/(mu_r + 2) B0/mu0``, and outside it is exactly a dipole

        m = 4 pi a^3 / mu0 * (mu_r - 1)/(mu_r + 2) * B0

    (closed-form special case of the ferromagnetic term of Gietler eq 27).
    The applied field is taken at the centre (sphere small compared with the
    distance to the coil). Inside, the field is ``3 mu_r/(mu_r + 2) B0``.
    """

    position: np.ndarray
    radius: float
    mu_r: float

    def __post_init__(self) -> None:
        self.position = np.asarray(self.position, dtype=float).reshape(3)

    @property
    def polarizability(self) -> float:
        """``m / B0`` (A m^2 / T)."""
        return 4.0 * np.pi * self.radius**3 / MU0 * (self.mu_r - 1.0) / (self.mu_r + 2.0)

    def moment(self, B0: np.ndarray) -> np.ndarray:
        return self.polarizability * np.asarray(B0, dtype=float)

    def field(self, points: np.ndarray, B0: np.ndarray) -> np.ndarray:
        """Induced field (T) at ``points`` outside the sphere for applied field ``B0`` ((3,) or (n, 3))."""
        return dipole_field(np.atleast_2d(points), self.position, self.moment(B0))


def _permeable_sphere_g(x: np.ndarray, mu_r: float) -> np.ndarray:
    """``G(x) = x^2 sin x + (mu_r - 1)(sin x - x cos x)``: its positive roots are the sphere's modes."""
    return x * x * np.sin(x) + (mu_r - 1.0) * (np.sin(x) - x * np.cos(x))


def permeable_sphere_roots(mu_r: float, n_modes: int) -> np.ndarray:
    """The first ``n_modes`` positive roots ``x_n`` of ``tan x = (mu_r - 1) x / (x^2 + mu_r - 1)`` (n,).

    The transcendental equation of a conducting, permeable sphere's free decay (Wait 1951,
    Geophysics 16, 666; Kaufman & Keller, *Frequency and Transient Soundings*, the sphere): the
    poles ``s_n = -x_n^2 / (mu_r mu0 sigma a^2)`` of the frequency response of
    :func:`hil.conductors.sphere_response` (``x^2 = -s mu_r mu0 sigma a^2``). Written as
    ``G(x) = 0`` (:func:`_permeable_sphere_g`): ``G((n +- 1/2) pi)`` have opposite signs for any
    ``mu_r > 0`` and exactly one root lies between them, found by bisection to machine precision
    (numpy only). ``mu_r = 1``: ``x_n = n pi``.
    """
    if mu_r <= 0.0 or n_modes < 1:
        raise ValueError("need mu_r > 0 and n_modes >= 1")
    n = np.arange(1, n_modes + 1, dtype=float)
    lo, hi = (n - 0.5) * np.pi, (n + 0.5) * np.pi
    g_lo = _permeable_sphere_g(lo, mu_r)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        g_mid = _permeable_sphere_g(mid, mu_r)
        same = np.sign(g_mid) == np.sign(g_lo)
        lo, g_lo, hi = np.where(same, mid, lo), np.where(same, g_mid, g_lo), np.where(same, hi, mid)
    return 0.5 * (lo + hi)


def permeable_sphere_modes(radius: float, sigma: float, mu_r: float, n_modes: int,
                           lump_tail: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Step response of a conducting permeable sphere as a sum of exponentials: ``(weights, taus)``.

    For a uniform applied-field step ``B0`` at ``t = 0`` (from zero) the moment is

        m(t) = -(2 pi a^3 / mu0) B0 [R_0 + sum_n r_n exp(-t / tau_n)],   R_0 = -2 (mu_r - 1)/(mu_r + 2),
        tau_n = mu_r mu0 sigma a^2 / x_n^2,
        r_n = -6 mu_r (sin x_n - x_n cos x_n) / (x_n^2 ((mu_r + 1) sin x_n + x_n cos x_n)),

    the residues of ``R(s)/s`` at the poles of Wait's response (:func:`hil.conductors.sphere_response`,
    ``R = -P/G`` with ``P = (1 + 2 mu_r)(sin x - x cos x) - x^2 sin x``; the inverse Laplace
    transform, ``x_n`` from :func:`permeable_sphere_roots`). Limits: ``t -> inf`` gives
    ``R_0``, the static magnetic sphere of :class:`FerroSphere`; ``t = 0+`` gives
    ``R_0 + sum r_n = 1`` (the field excluded: ``sum r_n = 3 mu_r/(mu_r + 2)``); ``mu_r = 1``
    gives ``x_n = n pi``, ``r_n = 6/(n^2 pi^2)``, :class:`ConductingSphere`'s series. For the
    default steel (a = 2 cm, mu_r 200, 6 MS/m) ``x_1 = 4.471``, ``tau_1 = 30.2 ms`` (against
    0.31 ms for a non-magnetic sphere of the same size and conductivity) and every mode up to
    ``x_n ~ sqrt(mu_r)`` weighs about ``6/mu_r``: the moment approaches its static value as
    4.6 % short at 3 ms, 1.9 % at 10 ms, 0.23 % at 58 ms.

    The weights fall off only as ``1/n^2`` beyond ``x_n ~ sqrt(mu_r)``, so ``lump_tail``
    replaces the modes beyond ``n_modes`` by one exponential with their exact total weight
    ``3 mu_r/(mu_r + 2) - sum_{n <= N} r_n`` and their exact first moment
    ``sum r_n tau_n = 3 mu_r tau_0 / (5 (mu_r + 2)^2)`` (``tau_0 = mu_r mu0 sigma a^2``; the
    slope of ``R`` at ``s = 0``) minus the kept modes': the step response stays exact at
    ``t = 0+`` and ``t -> inf`` and in its area, and is within 1e-3 of ``|R_0|`` from a few
    ``tau_N`` on (``tests/hil/test_permeable_sphere.py``). Returns ``n_modes`` (+1 with the
    tail) weights (dimensionless) and time constants (s).
    """
    if radius <= 0.0 or sigma <= 0.0:
        raise ValueError("need radius > 0 and sigma > 0")
    x = permeable_sphere_roots(mu_r, n_modes)
    tau0 = mu_r * MU0 * sigma * radius**2
    taus = tau0 / (x * x)
    w = -6.0 * mu_r * (np.sin(x) - x * np.cos(x)) / (x * x * ((mu_r + 1.0) * np.sin(x) + x * np.cos(x)))
    if lump_tail:
        w_tail = 3.0 * mu_r / (mu_r + 2.0) - float(w.sum())
        m_tail = 3.0 * mu_r * tau0 / (5.0 * (mu_r + 2.0) ** 2) - float(np.dot(w, taus))
        if w_tail > 0.0 and m_tail > 0.0:
            w = np.append(w, w_tail)
            taus = np.append(taus, m_tail / w_tail)
    return w, taus


@dataclass
class ConductingSphere:
    """Non-magnetic conducting sphere (radius ``a``, conductivity ``sigma``): transient eddy response.

    For a step ``dB0`` of a uniform applied field at ``t = 0`` the induced
    moment is the classical mode series (Wait; Kaufman & Keller)

        m(t) = -(2 pi a^3 / mu0) dB0 sum_n (6 / (n^2 pi^2)) exp(-t / tau_n),
        tau_n = mu0 sigma a^2 / (n^2 pi^2),

    whose frequency-domain form is ``m = -(2 pi a^3/mu0) B0 [1 - 3/x^2 + 3 cot(x)/x]``
    with ``x^2 = -i omega mu0 sigma a^2``. At ``t = 0+`` the weights sum to one
    (perfect diamagnet, the ``mu_r -> 0`` limit of :class:`FerroSphere`); the
    first mode (weight 6/pi^2 = 0.61, ``tau_1 = mu0 sigma a^2/pi^2``) dominates:
    from ``t = tau_1`` on it is within 1.5 % of the full series (0.1 % from
    ``2 tau_1``). ``n_modes = 1`` gives the first-mode model.
    For an arbitrary applied-field history the response is linear:
    ``m(t) = -(2 pi a^3/mu0) sum_n c_n HP_tau_n[B0](t)`` (a constant field,
    e.g. the earth field, induces nothing).

    ``mu_r != 1`` (a permeable conductor, steel): the modes are those of
    :func:`permeable_sphere_modes` (the exact roots and weights, the tail beyond
    ``n_modes`` lumped into one exponential), and the transient is the part of the
    step response above its static value: the static moment itself is
    :class:`FerroSphere`'s, which the caller adds (:class:`hil.world.MetalObject`).
    """

    position: np.ndarray
    radius: float
    sigma: float
    n_modes: int = 40
    mu_r: float = 1.0

    def __post_init__(self) -> None:
        self.position = np.asarray(self.position, dtype=float).reshape(3)
        self._modes = None

    @property
    def tau1(self) -> float:
        if self.mu_r == 1.0:
            return MU0 * self.sigma * self.radius**2 / np.pi**2
        x1 = float(permeable_sphere_roots(self.mu_r, 1)[0])
        return self.mu_r * MU0 * self.sigma * self.radius**2 / (x1 * x1)

    def modes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(weights c_n, time constants tau_n)`` of the first ``n_modes`` modes."""
        if self.mu_r == 1.0:
            n = np.arange(1, self.n_modes + 1)
            return 6.0 / (n * n * np.pi**2), self.tau1 / (n * n)
        if self._modes is None:
            self._modes = permeable_sphere_modes(self.radius, self.sigma, self.mu_r, self.n_modes)
        return self._modes

    def step_moment(self, t_s, dB0: np.ndarray) -> np.ndarray:
        """Moment (A m^2) at ``t_s`` (s, scalar or (n,)) after a uniform field step ``dB0`` (T) at 0."""
        c, tau = self.modes()
        t = np.asarray(t_s, dtype=float)
        g = np.sum(c * np.exp(-np.maximum(t[..., None], 0.0) / tau), axis=-1)
        g = np.where(t >= 0.0, g, 0.0)
        return -(2.0 * np.pi * self.radius**3 / MU0) * g[..., None] * np.asarray(dB0, dtype=float)

    def response(self, omega: float) -> complex:
        """Complex ``m / (-(2 pi a^3/mu0) B0)`` at angular frequency ``omega`` (closed form)."""
        if omega == 0.0:
            return 0.0 + 0.0j
        x = np.sqrt(-1j * omega * MU0 * self.sigma * self.radius**2)
        return complex(1.0 - 3.0 / x**2 + 3.0 / (x * np.tan(x)))

    def moment_from_coils(self, source: Source, currents: Sequence[CoilCurrent], t_us) -> np.ndarray:
        """Moment (A m^2) driven by the coil currents' history: ((3,) or (n, 3))."""
        u = source.unit_fields(self.position[None, :])[:, 0, :]  # (K, 3) T/A
        c, tau = self.modes()
        t = np.asarray(t_us)
        acc = np.zeros(t.shape + (3,))
        for k, cur in enumerate(currents):
            h = np.tensordot(c, np.asarray(cur.highpass_at(t_us, tau)), axes=1)
            acc = acc + np.asarray(h)[..., None] * u[k]
        return -(2.0 * np.pi * self.radius**3 / MU0) * acc

    def field(self, points: np.ndarray, moment: np.ndarray) -> np.ndarray:
        return dipole_field(np.atleast_2d(points), self.position, moment)


# ---------------------------------------------------------------------------
# Earth field and frames
# ---------------------------------------------------------------------------


@dataclass
class EarthField:
    """Constant field in the world frame (T)."""

    B: np.ndarray = dc_field(default_factory=lambda: EARTH_FIELD_T.copy())

    def field(self, points: np.ndarray) -> np.ndarray:
        pts = np.atleast_2d(points)
        return np.broadcast_to(np.asarray(self.B, dtype=float), pts.shape).copy()


def sensor_frame(B_world: np.ndarray, R_world_from_sensor: np.ndarray) -> np.ndarray:
    """Express world-frame vectors in the sensor frame: ``B_sensor = R^T B_world``.

    ``B_world`` (3,) or (n, 3); ``R`` (3, 3) or (n, 3, 3).
    """
    B = np.asarray(B_world, dtype=float)
    R = np.asarray(R_world_from_sensor, dtype=float)
    return np.einsum("...ji,...j->...i", R, B)


# ---------------------------------------------------------------------------
# Scene: everything at once
# ---------------------------------------------------------------------------


class MagneticScene:
    """Total field at sensor points: source coils + eddy + ferro + conducting spheres + earth.

    ``currents[k]`` drives ``source[k]``. :meth:`field` takes points (n, 3) and
    a time (scalar) or one time per point ((n,) integer microseconds) and
    returns the world-frame field (n, 3) T. Static object couplings (unit
    fields of every coil at every object centre) are computed once here.
    """

    def __init__(self, source: Source, currents: Sequence[CoilCurrent], earth: EarthField | None = None,
                 eddies: Sequence[EddyConductor] = (), ferros: Sequence[FerroSphere] = (),
                 spheres: Sequence[ConductingSphere] = ()):
        if len(currents) != len(source):
            raise ValueError("one CoilCurrent per coil")
        self.source, self.currents = source, list(currents)
        self.earth = earth
        self.eddies, self.ferros, self.spheres = list(eddies), list(ferros), list(spheres)
        self._ferro_u = [source.unit_fields(f.position[None, :])[:, 0, :] for f in self.ferros]

    def coil_currents(self, t_us) -> np.ndarray:
        """Currents of all coils, (n_coils,) or (n_coils, n)."""
        return np.stack([np.asarray(c.current_at(t_us)) for c in self.currents])

    def field(self, points: np.ndarray, t_us) -> np.ndarray:
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        n = pts.shape[0]
        t = np.asarray(t_us)
        I = self.coil_currents(t_us)  # (K,) or (K, n)
        U = self.source.unit_fields(pts)  # (K, n, 3)
        Ib = I[:, None] if I.ndim == 1 else I
        B = np.einsum("kn,kni->ni", np.broadcast_to(Ib, (len(self.source), n)), U)
        earth = np.zeros(3) if self.earth is None else np.asarray(self.earth.B, dtype=float)
        B = B + earth
        for e in self.eddies:
            for coil, cur in zip(self.source, self.currents):
                B = B + e.field(pts, coil, cur, t_us)
        for f, u in zip(self.ferros, self._ferro_u):
            B0 = (Ib.T if I.ndim == 2 else I[None, :]) @ u + earth  # (n or 1, 3)
            B = B + f.field(pts, B0)
        for s in self.spheres:
            m = s.moment_from_coils(self.source, self.currents, t)
            B = B + s.field(pts, m)
        return B
