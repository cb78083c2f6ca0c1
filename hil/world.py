"""The emulated world: source coils and their currents, the earth field,
conductors and ferromagnetic objects, and the sensor's motion. Fields come
from magpylib through ``hil.physics``; nothing here borrows the firmware's
field code.

Frames: the source frame is the world frame when the source is fixed (the
default); a source that moves (``source_trajectory``, a body model, ``hil.body``)
has its own world pose, and the earth field (world frame) reaches the source
frame as ``R_s^T B_earth``. The coil fields are computed in the source frame
from the sensor's relative pose, which is the world-frame field of the moved
source turned into the source frame (checked against magpylib with the source
moved and rotated in ``tests/hil/test_body.py``); objects live in the source
frame. A trajectory gives the sensor pose ``(p, R)`` with ``R`` mapping sensor-frame
vectors to the source frame. Times are integer microseconds of *true* time
(the bench's time base; node clocks drift against it, see ``hil.clock``).

Objects (each may be switched on and off at true times, so a scenario or a
fault can bring metal near mid-run):

* :class:`EddyObject`: a lumped eddy-current conductor
  (:class:`hil.physics.EddyConductor`): a dipole that jumps at every current
  edge and decays with its own time constant;
* :class:`FerroObject`: a linear magnetic sphere (:class:`hil.physics.FerroSphere`)
  magnetised by the coils' and the earth's field;
* :class:`ConductingSphereObject`: the analytic transient response of a
  conducting sphere (:class:`hil.physics.ConductingSphere`);
* :class:`MetalObject`: a steel part: ferro sphere and eddy conductor at the
  same place, either fixed in the world or carried with the sensor;
* :class:`HardIron`: a constant field in the sensor frame (a magnet fixed
  to the sensor board), e.g. to drive the magnetometer into saturation.

Objects respond to the source and earth fields only (first-order
scattering); a carried object's eddy model ignores motional EMF (the
object moves little during an eddy time constant).
"""
from __future__ import annotations

import copy
import math

import numpy as np

from . import physics

EARTH_FIELD_T = physics.EARTH_FIELD_T


class _Timed:
    """Active on ``[t_on_us, t_off_us)`` (None: unbounded)."""

    t_on_us: int | None = None
    t_off_us: int | None = None

    def active(self, t_us: int) -> bool:
        return ((self.t_on_us is None or t_us >= self.t_on_us)
                and (self.t_off_us is None or t_us < self.t_off_us))


class EddyObject(_Timed):
    def __init__(self, conductor: physics.EddyConductor, t_on_us=None, t_off_us=None):
        self.conductor = conductor
        self.t_on_us, self.t_off_us = t_on_us, t_off_us

    def _moments(self, world) -> np.ndarray:
        if getattr(self, "_m", None) is None:
            self._m = np.stack([self.conductor.moment_per_amp(coil) for coil in world.source])
        return self._m

    def field_at(self, world: "World", t_us: int, p, R) -> np.ndarray:
        c = self.conductor
        y = np.array([cur.highpass_at(t_us, c.tau_s) for cur in world.currents])
        if not np.any(np.abs(y) > 1e-15):
            return np.zeros(3)
        return physics.dipole_field(p[None, :], c.position, y @ self._moments(world))[0]

    def eddy_error(self, world: "World", k: int, grid, p, R) -> np.ndarray:
        """|eddy field of coil k's current history| at ``p`` over ``grid`` (T per A of coil field scale)."""
        coil = world.source[k]
        e = physics.dipole_field(p[None, :], self.conductor.position, self.conductor.moment_per_amp(coil))[0]
        y = np.asarray(world.currents[k].highpass_at(grid, self.conductor.tau_s))
        return np.abs(y) * float(np.linalg.norm(e))


def _sphere_moment(world: "World", centre, radius: float, sphere: physics.ConductingSphere, t_us, u=None):
    """Eddy moment (A m^2) of a conducting sphere at ``centre`` driven by all coils (mode series)."""
    if u is None:
        u = world.source.unit_fields(np.asarray(centre, dtype=float)[None, :])[:, 0, :]
    cw, tau = sphere.modes()
    acc = np.zeros(3)
    for k, cur in enumerate(world.currents):
        h = float(np.dot(cw, np.asarray(cur.highpass_at(t_us, tau))))
        if h != 0.0:
            acc += h * u[k]
    return -(2.0 * np.pi * radius**3 / physics.MU0) * acc


def _sphere_error(world: "World", k: int, grid, centre, radius: float, sphere: physics.ConductingSphere,
                  p, u_k) -> np.ndarray:
    cw, tau = sphere.modes()
    h = np.tensordot(cw, np.asarray(world.currents[k].highpass_at(grid, tau)), axes=1)
    m_per = -(2.0 * np.pi * radius**3 / physics.MU0) * u_k
    e = physics.dipole_field(p[None, :], centre, m_per)[0]
    return np.abs(h) * float(np.linalg.norm(e))


class _SphereObject(_Timed):
    """A sphere fixed in the source frame, switched on between ``t_on_us`` and
    ``t_off_us``; the coils' field at its centre per ampere is computed once."""

    def __init__(self, sphere, t_on_us=None, t_off_us=None):
        self.sphere = sphere
        self.t_on_us, self.t_off_us = t_on_us, t_off_us
        self._u = None

    def _unit(self, world):
        if self._u is None:
            self._u = world.source.unit_fields(self.sphere.position[None, :])[:, 0, :]
        return self._u


class FerroObject(_SphereObject):
    def field_at(self, world: "World", t_us: int, p, R) -> np.ndarray:
        B0 = world.coil_currents(t_us) @ self._unit(world) + world.earth
        return self.sphere.field(p[None, :], B0)[0]

    def coil_unit_field(self, world: "World", k: int, p, R) -> np.ndarray:
        """Induced field at ``p`` per ampere of coil ``k`` (steady state, T/A)."""
        return self.sphere.field(p[None, :], self._unit(world)[k])[0]


class ConductingSphereObject(_SphereObject):
    def field_at(self, world: "World", t_us: int, p, R) -> np.ndarray:
        m = _sphere_moment(world, self.sphere.position, self.sphere.radius, self.sphere, t_us, self._unit(world))
        return self.sphere.field(p[None, :], m)[0]

    def eddy_error(self, world: "World", k: int, grid, p, R) -> np.ndarray:
        return _sphere_error(world, k, grid, self.sphere.position, self.sphere.radius, self.sphere, p,
                             self._unit(world)[k])


class MetalObject(_Timed):
    """A metal part: a conducting, permeable sphere. Its moment is the static magnetic sphere's
    (induced dipole, :class:`hil.physics.FerroSphere`) plus the eddy transient of a permeable
    conductor at the same centre (:class:`hil.physics.ConductingSphere` with ``mu_r``, the
    exact modes of :func:`hil.physics.permeable_sphere_modes`): a step of the applied field
    first meets a diamagnetic moment (the field excluded) that relaxes to the static one through
    modes of ``tau_n = mu_r mu0 sigma a^2 / x_n^2`` (Wait 1951). Its response at one frequency
    is :func:`hil.conductors.sphere_response` with the same ``mu_r`` (the AC bench).
    ``mu_r = 1`` gives a non-magnetic conductor (copper, aluminium; ``tau_1 = mu0 sigma a^2/pi^2``),
    ``sigma = 0`` a non-conducting ferrite.

    ``position`` (world frame, fixed) or ``carried_offset`` (sensor frame: the
    part moves with the sensor, e.g. a tool or a watch held next to it).
    Defaults: a 2 cm radius steel part (mu_r 200, 6e6 S/m, tau_1 = 30.2 ms; 4.6 % short of its
    static moment 3 ms after a step, 1.9 % at 10 ms, 0.23 % at 58 ms). ``n_modes`` exact modes,
    the rest lumped into one (within 1e-3 of the static moment from 0.15 ms after a step on
    for 40 modes).
    """

    def __init__(self, radius: float = 0.02, mu_r: float = 200.0, sigma: float = 6e6, n_modes: int = 40,
                 position=None, carried_offset=None, t_on_us=None, t_off_us=None):
        if (position is None) == (carried_offset is None):
            raise ValueError("give position or carried_offset")
        self.radius, self.mu_r, self.sigma = float(radius), float(mu_r), float(sigma)
        self.position = None if position is None else np.asarray(position, dtype=float).reshape(3)
        self.carried_offset = None if carried_offset is None else np.asarray(carried_offset, dtype=float).reshape(3)
        self.t_on_us, self.t_off_us = t_on_us, t_off_us
        self._cs = physics.ConductingSphere(np.zeros(3), self.radius, max(self.sigma, 1e-30), n_modes=n_modes,
                                            mu_r=self.mu_r)
        self._fixed_u = None

    @property
    def tau1_s(self) -> float:
        return self._cs.tau1

    def center(self, p, R) -> np.ndarray:
        return self.position if self.position is not None else p + R @ self.carried_offset

    def _unit(self, world, c):
        if self.position is not None:
            if self._fixed_u is None:
                self._fixed_u = world.source.unit_fields(c[None, :])[:, 0, :]
            return self._fixed_u
        return world.source.unit_fields(c[None, :])[:, 0, :]

    def field_at(self, world: "World", t_us: int, p, R) -> np.ndarray:
        c = self.center(p, R)
        u = self._unit(world, c)
        B0 = world.coil_currents(t_us) @ u + world.earth
        m = physics.FerroSphere(c, self.radius, self.mu_r).moment(B0)
        if self.sigma > 0.0:
            m = m + _sphere_moment(world, c, self.radius, self._cs, t_us, u)
        return physics.dipole_field(p[None, :], c, m)[0]

    def coil_unit_field(self, world: "World", k: int, p, R) -> np.ndarray:
        c = self.center(p, R)
        u = self._unit(world, c)
        return physics.FerroSphere(c, self.radius, self.mu_r).field(p[None, :], u[k])[0]

    def eddy_error(self, world: "World", k: int, grid, p, R) -> np.ndarray:
        if self.sigma <= 0.0:
            return np.zeros(np.shape(grid))
        c = self.center(p, R)
        return _sphere_error(world, k, grid, c, self.radius, self._cs, p, self._unit(world, c)[k])


class HardIron(_Timed):
    """Constant field ``b_sensor`` (T, sensor frame): a magnet on the sensor board."""

    def __init__(self, b_sensor, t_on_us=None, t_off_us=None):
        self.b_sensor = np.asarray(b_sensor, dtype=float).reshape(3)
        self.t_on_us, self.t_off_us = t_on_us, t_off_us

    def field_at(self, world: "World", t_us: int, p, R) -> np.ndarray:
        return R @ self.b_sensor


class World:
    """Source, coil currents, earth field, objects and sensor motion.

    ``coils``: an iterable of :class:`hil.physics.SourceCoil` (or a
    :class:`hil.physics.Source`). ``objects``: any of the classes above
    (``disturbers`` is an alias). ``supply_v``: the coil driver's supply
    voltage (the current cannot exceed ``V/R``; the driver applies sag).
    """

    def __init__(self, coils, trajectory, earth_field_t=EARTH_FIELD_T, disturbers=(), supply_v: float = 6.0,
                 objects=(), source_trajectory=None, sensor_world_trajectory=None):
        #: the source's pose in the world over time (None: fixed at the origin, level; see
        #: :meth:`source_kinematics`), and the sensor's world trajectory when it is known
        #: directly (a body model); else it is composed from the source's and ``trajectory``
        self.source_trajectory = source_trajectory
        self.sensor_world_trajectory = sensor_world_trajectory
        self._src_R: dict[int, np.ndarray] = {}
        self.coils = list(coils)
        self.source = physics.Source(self.coils)
        self.trajectory = trajectory
        self.earth = np.asarray(earth_field_t, dtype=float).reshape(3)
        self.objects = list(objects) + list(disturbers)
        self.currents = [physics.CoilCurrent(resistance=c.resistance, inductance=c.inductance)
                         for c in self.coils]
        self.supply_v = supply_v
        # per-time cache of (p, R, unit fields), filled in vectorised chunks by the sensor nodes
        self._cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def view(self, trajectory) -> "World":
        """The same world seen by another sensor moving on ``trajectory``: source, coil currents,
        earth field and objects are shared (the driver's pulses, metal brought in, appear in every
        view); only the sensor's motion and the per-time cache are its own."""
        v = copy.copy(self)
        v.trajectory = trajectory
        v._cache = {}
        return v

    # kept for callers of the first version
    @property
    def disturbers(self):
        return self.objects

    def add(self, obj) -> None:
        """Add an object (e.g. metal brought near by a fault at its ``t_on_us``)."""
        self.objects.append(obj)

    def edit_mark(self) -> tuple:
        """A mark of what the field depends on besides time and geometry: the objects and every
        coil's current waveform (the driver edits them as it commits commanded pulses); see
        :meth:`edited_since`."""
        return (len(self.objects), *(c.edits for c in self.currents))

    def edited_since(self, mark: tuple, t_us: int) -> bool:
        """True when the field at some time at or before ``t_us`` may have changed since ``mark``
        (:meth:`edit_mark`): an object added, or a coil current edited from a time ``<= t_us``
        (``hil.physics.CoilCurrent.edited_since``). A field computed ahead at the mark still holds
        otherwise: the trajectory, the earth field and the objects' own schedules are fixed."""
        if mark[0] != len(self.objects):
            return True
        for c, m in zip(self.currents, mark[1:]):
            if c.edited_since(m, t_us):
                return True
        return False

    def precompute(self, times) -> None:
        """Evaluate the pose and every coil's unit field at ``times`` (true us) in one vectorised
        call and keep them for :meth:`pose` and :meth:`field_source_frame` (a sensor node knows
        its future sample instants; geometry does not depend on what the firmware commands)."""
        t = np.asarray(times, dtype=np.int64).reshape(-1)
        if t.size == 0:
            return
        if len(self._cache) > 8192:
            lo = int(t.min()) - 2_000_000
            for key in [k for k in self._cache if k < lo]:
                del self._cache[key]
        p, R = self.trajectory.pose(t)
        U = self.source.unit_fields(p)
        for i, ti in enumerate(t.tolist()):
            self._cache[ti] = (p[i], R[i], U[:, i, :])
        if self.source_trajectory is not None:
            if len(self._src_R) > 8192:
                lo = int(t.min()) - 2_000_000
                for key in [k for k in self._src_R if k < lo]:
                    del self._src_R[key]
            _, Rs = self.source_trajectory.pose(t)
            for i, ti in enumerate(t.tolist()):
                self._src_R[ti] = Rs[i]

    def pose(self, t_us):
        if np.ndim(t_us) == 0:
            c = self._cache.get(int(t_us))
            if c is not None:
                return c[0], c[1]
        return self.trajectory.pose(t_us)

    def coil_currents(self, t_us: int) -> np.ndarray:
        """The coils' currents (A) at ``t_us``: the regulated waveform plus the driver's ripple."""
        return np.array([c.current_at(t_us) + c.ripple_at(t_us) for c in self.currents])

    def unit_fields(self, p) -> np.ndarray:
        """(ncoils, 3) field per ampere of each coil at source-frame point p."""
        p = np.asarray(p, dtype=float).reshape(1, 3)
        return self.source.unit_fields(p)[:, 0, :]

    def field_source_frame(self, t_us: int, p=None, R=None) -> np.ndarray:
        """Total field (coils + earth + active objects) at the sensor, source frame (T)."""
        t_us = int(t_us)
        U = None
        if p is None or R is None:
            c = self._cache.get(t_us)
            if c is not None:
                p, R, U = c
            else:
                p, R = self.trajectory.pose(t_us)
        p = np.asarray(p, dtype=float)
        I = self.coil_currents(t_us)
        B = self.earth_source_frame(t_us)
        if np.any(I != 0.0):
            B += I @ (self.unit_fields(p) if U is None else U)
        for obj in self.objects:
            if obj.active(t_us):
                B += obj.field_at(self, t_us, p, R)
        return B

    def field_sensor_frame(self, t_us: int) -> np.ndarray:
        t_us = int(t_us)
        c = self._cache.get(t_us)
        if c is not None:
            return c[1].T @ self.field_source_frame(t_us)
        p, R = self.trajectory.pose(t_us)
        return R.T @ self.field_source_frame(t_us, p, R)

    # ------------------------------------------------------------ ground truth
    def steady_amplitude(self, k: int, t_us: int, current_a: float) -> np.ndarray:
        """Steady-state field change (sensor frame, T) that coil ``k`` at ``current_a`` makes at the
        sensor pose of ``t_us``: the coil field plus the ferromagnetic objects' response to it
        (eddy currents have died out). This is what a pulse amplitude should measure."""
        p, R = self.pose(int(t_us))
        p = np.asarray(p, dtype=float)
        u = self.unit_fields(p)[k].copy()
        for obj in self.objects:
            if obj.active(int(t_us)) and hasattr(obj, "coil_unit_field"):
                u += obj.coil_unit_field(self, k, p, R)
        return current_a * (R.T @ u)

    def flat_start_us(self, k: int, true_start_us: int, true_end_us: int, tol: float = 1e-3,
                      step_us: int = 20) -> int:
        """First true time after a pulse's start edge from which, until the end edge, the coil
        current is within ``tol`` of its final value AND the eddy field of every active conductor
        is below ``tol`` of the coil's steady field at the sensor (relative). Computed from the
        actual current waveform and the eddy high-pass states on a ``step_us`` grid, at the
        sensor pose of the start edge."""
        cur = self.currents[k]
        t0, t1 = int(true_start_us), int(true_end_us)
        if t1 <= t0:
            return t1
        grid = np.arange(t0, t1, step_us, dtype=np.int64)
        i_ss = float(cur.current_at(t1 - 1))
        if abs(i_ss) < 1e-12:
            return t0
        err = np.abs(np.asarray(cur.current_at(grid)) - i_ss) / abs(i_ss)
        p, R = self.pose(t0)
        p = np.asarray(p, dtype=float)
        coil_ss = abs(i_ss) * float(np.linalg.norm(self.unit_fields(p)[k]))
        for obj in self.objects:
            if hasattr(obj, "eddy_error") and (obj.active(t0) or obj.active(t1 - 1)):
                err = np.maximum(err, obj.eddy_error(self, k, grid, p, R) / max(coil_ss, 1e-30))
        bad = np.nonzero(err >= tol)[0]
        if bad.size == 0:
            return t0
        last_bad = int(bad[-1])
        return int(grid[last_bad]) + step_us if last_bad + 1 < grid.size else t1

    def settle_bound_us(self, tol: float = 1e-3) -> float:
        """Rough upper bound of the settle time after an edge, ``max(tau) ln(1/tol)`` (us), over the
        coil L/R constants and the eddy time constants of the objects (first mode for spheres)."""
        taus = [c.tau_us for c in self.currents]
        for o in self.objects:
            if isinstance(o, EddyObject):
                taus.append(o.conductor.tau_s * 1e6)
            elif isinstance(o, ConductingSphereObject):
                taus.append(o.sphere.tau1 * 1e6)
            elif isinstance(o, MetalObject) and o.sigma > 0.0:
                taus.append(o.tau1_s * 1e6)
        return max(taus) * math.log(1.0 / tol)

    # ------------------------------------------------------------ a moving source
    @property
    def source_moving(self) -> bool:
        """True when the source follows a trajectory of its own (body-worn scenarios)."""
        return self.source_trajectory is not None

    def earth_source_frame(self, t_us: int) -> np.ndarray:
        """The earth field in the source frame at ``t_us`` (T): ``R_s^T B_earth`` with the
        source's world orientation ``R_s`` (a new array; ``earth`` itself for a fixed source)."""
        if self.source_trajectory is None:
            return self.earth.copy()
        Rs = self._src_R.get(int(t_us))
        if Rs is None:
            _, Rs = self.source_trajectory.pose(int(t_us))
        return Rs.T @ self.earth

    def source_kinematics(self, t_us):
        """The source's world kinematics ``(p, v, a, R, w_world, al_world)`` at integer
        microseconds ``t_us`` (arrays of n times: (n, 3), (n, 3, 3)); a fixed source: at the
        origin, level, at rest. ``R`` maps source-frame vectors to the world."""
        from .motion import _time_s

        t, _ = _time_s(t_us)
        n = t.shape[0]
        if self.source_trajectory is None:
            z = np.zeros((n, 3))
            return z, z.copy(), z.copy(), np.tile(np.eye(3), (n, 1, 1)), z.copy(), z.copy()
        if hasattr(self.source_trajectory, "full"):
            return self.source_trajectory.full(t)
        k = self.source_trajectory.kinematics(np.atleast_1d(np.asarray(t_us, dtype=np.int64)))
        w = np.einsum("nij,nj->ni", k.R, k.angular_velocity)
        return k.position, k.velocity, k.acceleration, k.R, w, np.zeros((n, 3))

    def sensor_kinematics(self, t_us):
        """The sensor's kinematics in the world frame (``hil.motion.Kinematics``; what its IMU
        measures: specific force ``R^T (a - g)``, rate ``w``). A fixed source: the trajectory's
        own (source frame = world frame). A moving one: the given world trajectory, or
        ``trajectory`` composed with the source's motion: ``r = R_s q``,
        ``a = a_s + al x r + w x (w x r) + 2 w x R_s q' + R_s q''``, ``R = R_s R_q``,
        body rate ``R_q^T R_s^T w + w_q``."""
        if self.source_trajectory is None:
            return self.trajectory.kinematics(t_us)
        if self.sensor_world_trajectory is not None:
            return self.sensor_world_trajectory.kinematics(t_us)
        from .motion import Kinematics

        scalar = np.ndim(t_us) == 0
        tt = np.atleast_1d(np.asarray(t_us, dtype=np.int64))
        ps, vs, as_, Rs, w, al = self.source_kinematics(tt)
        k = self.trajectory.kinematics(tt)
        r = np.einsum("nij,nj->ni", Rs, k.position)
        rv = np.einsum("nij,nj->ni", Rs, k.velocity)
        ra = np.einsum("nij,nj->ni", Rs, k.acceleration)
        p = ps + r
        v = vs + np.cross(w, r) + rv
        a = as_ + np.cross(al, r) + np.cross(w, np.cross(w, r)) + 2.0 * np.cross(w, rv) + ra
        R = Rs @ k.R
        wb = np.einsum("nji,nj->ni", R, w) + k.angular_velocity
        if scalar:
            return Kinematics(p[0], v[0], a[0], R[0], wb[0])
        return Kinematics(p, v, a, R, wb)

    def source_module_kinematics(self, offset, t_us):
        """World acceleration (n, 3), source rotation (n, 3, 3) and body rate (n, 3, source
        frame) of a module fixed on the source at ``offset`` (m, source frame):
        ``a = a_s + al x (R_s d) + w x (w x R_s d)``."""
        ps, vs, as_, Rs, w, al = self.source_kinematics(t_us)
        d = np.einsum("nij,j->ni", Rs, np.asarray(offset, dtype=float).reshape(3))
        a = as_ + np.cross(al, d) + np.cross(w, np.cross(w, d))
        return a, Rs, np.einsum("nji,nj->ni", Rs, w)
