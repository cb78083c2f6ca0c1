"""Sensor motion for the emulated bench.

Every trajectory gives the pose of the sensor in the source frame at an
integer microsecond time ``t_us``:

* ``pose(t_us) -> (position (3,) m, R (3, 3))`` where ``R`` maps sensor-frame
  vectors to source-frame vectors (``v_source = R @ v_sensor``);
* ``velocity(t_us)`` and ``acceleration(t_us)``: first and second time
  derivative of the position, in the source frame (m/s, m/s^2). The source is
  fixed in the world here, so this is also the world-frame kinematic
  acceleration an accelerometer sees (before gravity is added);
* ``angular_velocity(t_us)``: rad/s in the sensor frame, i.e. the vector
  ``w`` with ``R^T dR/dt = [w]x`` (what a gyroscope measures);
* ``kinematics(t_us)``: all of the above in one call.

All of them accept a scalar time (giving ``(3,)`` / ``(3, 3)`` results) or an
array of ``n`` times (giving ``(n, 3)`` / ``(n, 3, 3)``). Derivatives are
analytic (chain rule through sums of sinusoids, elementary rotation chains
and, for the Brownian model, piecewise cubic Hermite interpolation).

Source frame convention for the body-worn scenarios (thesis
``002_cd7f1fdb7fc67471.txt`` Fig. 5.7 / sec 6.4): x forward (anterior),
y to the subject's left, z up; the source sits on the lower back. The tracker
resolves the dipole hemisphere ambiguity (Raab ``004_86267342cd7488ce.txt``)
by assuming the sensor stays in the +x half-space, so every trajectory here
keeps ``x > 0.05 m`` except the paper's own runs, which are reproduced as
published: the helix (:class:`Helix`) and the unbounded
:meth:`BrownianMotion.gietler` (documented there).

The trajectories here give only the *relative* pose of sensor and source;
the body-worn scenarios move the source as well (``hil.body``: a kinematic
body model whose pelvis carries the source, ``World.source_trajectory``), so
that the IMUs measure world-frame motion and the fusion needs the relative
acceleration ``a_net = a_sensor - a_source`` (thesis sec 6.2.3, eq 6.8).

Rotation helpers (no scipy at run time) are at the top of this module:
rotation vector <-> matrix, quaternions (scalar first, ``[w, x, y, z]``),
elementary rotations and the Z-Y-X Euler sequence of Gietler et al.
(``003_93f59c2e1c5b6c59.txt`` eqs 3-4).

Every random trajectory draws from ``numpy.random.default_rng(seed)`` only,
so a seed reproduces it exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = [
    # rotation helpers
    "skew",
    "vee",
    "rot_x",
    "rot_y",
    "rot_z",
    "axis_angle_to_matrix",
    "rotvec_to_matrix",
    "matrix_to_rotvec",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_multiply",
    "quat_conjugate",
    "rotvec_to_quat",
    "quat_to_rotvec",
    "euler_zyx_to_matrix",
    "right_jacobian",
    "random_rotation",
    "rotation_angle",
    # trajectories
    "Kinematics",
    "Trajectory",
    "StaticPose",
    "static_grid",
    "HandMovedBench",
    "ArmAbduction",
    "Walking",
    "BrownianMotion",
    "Helix",
]

_EX = np.array([1.0, 0.0, 0.0])
_EY = np.array([0.0, 1.0, 0.0])
_EZ = np.array([0.0, 0.0, 1.0])


# ---------------------------------------------------------------------------
# Rotation helpers (vectorised over leading dimensions)
# ---------------------------------------------------------------------------


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x`` with ``[v]x @ u == cross(v, u)``; (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def vee(S: np.ndarray) -> np.ndarray:
    """Inverse of :func:`skew` (antisymmetric part); (..., 3, 3) -> (..., 3)."""
    S = np.asarray(S, dtype=float)
    return 0.5 * np.stack(
        [S[..., 2, 1] - S[..., 1, 2], S[..., 0, 2] - S[..., 2, 0], S[..., 1, 0] - S[..., 0, 1]],
        axis=-1,
    )


def _elementary(angle, i: int, j: int) -> np.ndarray:
    a = np.asarray(angle, dtype=float)
    c, s = np.cos(a), np.sin(a)
    k = 3 - i - j
    out = np.zeros(a.shape + (3, 3))
    out[..., k, k] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., i, j] = -s
    out[..., j, i] = s
    return out


def rot_x(angle) -> np.ndarray:
    """Rotation about x by ``angle`` rad (Gietler eq 4, ``R_x``)."""
    return _elementary(angle, 1, 2)


def rot_y(angle) -> np.ndarray:
    """Rotation about y by ``angle`` rad (Gietler eq 4, ``R_y``)."""
    return _elementary(angle, 2, 0)


def rot_z(angle) -> np.ndarray:
    """Rotation about z by ``angle`` rad (Gietler eq 4, ``R_z``)."""
    return _elementary(angle, 0, 1)


def axis_angle_to_matrix(axis: np.ndarray, angle) -> np.ndarray:
    """Rotation by ``angle`` (rad, shape (...)) about the unit vector ``axis`` (3,) (Rodrigues)."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    a = np.asarray(angle, dtype=float)[..., None, None]
    K = skew(axis)
    return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * (K @ K)


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad) to rotation matrix; (..., 3) -> (..., 3, 3).

    Rodrigues' formula with Taylor series near zero angle.
    """
    v = np.asarray(v, dtype=float)
    th2 = np.sum(v * v, axis=-1)
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(ths)) / (ths * ths))
    K = skew(v)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix to unit quaternion ``[w, x, y, z]`` with ``w >= 0`` (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    cand = np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=-1)
    choice = np.argmax(cand, axis=-1)
    q = np.empty((R.shape[0], 4))
    # w largest
    m = choice == 0
    s = np.sqrt(1.0 + tr[m]) * 2.0
    q[m, 0] = 0.25 * s
    q[m, 1] = (R[m, 2, 1] - R[m, 1, 2]) / s
    q[m, 2] = (R[m, 0, 2] - R[m, 2, 0]) / s
    q[m, 3] = (R[m, 1, 0] - R[m, 0, 1]) / s
    m = choice == 1
    s = np.sqrt(1.0 + R[m, 0, 0] - R[m, 1, 1] - R[m, 2, 2]) * 2.0
    q[m, 0] = (R[m, 2, 1] - R[m, 1, 2]) / s
    q[m, 1] = 0.25 * s
    q[m, 2] = (R[m, 0, 1] + R[m, 1, 0]) / s
    q[m, 3] = (R[m, 0, 2] + R[m, 2, 0]) / s
    m = choice == 2
    s = np.sqrt(1.0 + R[m, 1, 1] - R[m, 0, 0] - R[m, 2, 2]) * 2.0
    q[m, 0] = (R[m, 0, 2] - R[m, 2, 0]) / s
    q[m, 1] = (R[m, 0, 1] + R[m, 1, 0]) / s
    q[m, 2] = 0.25 * s
    q[m, 3] = (R[m, 1, 2] + R[m, 2, 1]) / s
    m = choice == 3
    s = np.sqrt(1.0 + R[m, 2, 2] - R[m, 0, 0] - R[m, 1, 1]) * 2.0
    q[m, 0] = (R[m, 1, 0] - R[m, 0, 1]) / s
    q[m, 1] = (R[m, 0, 2] + R[m, 2, 0]) / s
    q[m, 2] = (R[m, 1, 2] + R[m, 2, 1]) / s
    q[m, 3] = 0.25 * s
    q *= np.where(q[:, :1] < 0.0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q.reshape(shape + (4,))


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternion ``[w, x, y, z]`` (normalised here) to rotation matrix; (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p * q`` (so that ``R(p*q) = R(p) @ R(q)``)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion)."""
    q = np.array(q, dtype=float)
    q[..., 1:] *= -1.0
    return q


def rotvec_to_quat(v: np.ndarray) -> np.ndarray:
    """Rotation vector to unit quaternion ``[w, x, y, z]``."""
    v = np.asarray(v, dtype=float)
    th = np.linalg.norm(v, axis=-1)
    half = 0.5 * th
    small = th < 1e-6
    k = np.where(small, 0.5 - th * th / 48.0, np.sin(half) / np.where(small, 1.0, th))
    return np.concatenate([np.cos(half)[..., None], k[..., None] * v], axis=-1)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Unit quaternion to rotation vector with angle in [0, pi]."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = q * np.where(q[..., :1] < 0.0, -1.0, 1.0)
    xyz = q[..., 1:]
    s = np.linalg.norm(xyz, axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 0])
    small = s < 1e-9
    factor = np.where(small, 2.0 / np.maximum(q[..., 0], 1e-300), angle / np.where(small, 1.0, s))
    return factor[..., None] * xyz


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix to rotation vector (angle in [0, pi]); robust near 0 and pi."""
    return quat_to_rotvec(matrix_to_quat(R))


def euler_zyx_to_matrix(theta: np.ndarray) -> np.ndarray:
    """``R = R_z(theta_3) R_y(theta_2) R_x(theta_1)``: Gietler ``003_93f59c2e1c5b6c59.txt`` eqs 3-4."""
    theta = np.asarray(theta, dtype=float)
    return rot_z(theta[..., 2]) @ rot_y(theta[..., 1]) @ rot_x(theta[..., 0])


def right_jacobian(v: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3): for ``R = exp([v]x)``, ``R^T dR/dt = [J_r(v) dv/dt]x``.

    ``J_r(v) = I - (1 - cos t)/t^2 [v]x + (t - sin t)/t^3 [v]x^2`` with ``t = |v|``.
    """
    v = np.asarray(v, dtype=float)
    th2 = np.sum(v * v, axis=-1)
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / (ths * ths))
    c = np.where(small, 1.0 / 6.0 - th2 / 120.0, (ths - np.sin(ths)) / (ths**3))
    K = skew(v)
    return np.eye(3) - b[..., None, None] * K + c[..., None, None] * (K @ K)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly distributed rotation matrix drawn from ``rng`` (normalised Gaussian quaternion)."""
    q = rng.standard_normal(4)
    return quat_to_matrix(q / np.linalg.norm(q))


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Smallest angle (rad) rotating ``R_a`` onto ``R_b`` (thesis sec 5.4 orientation error)."""
    Rd = np.swapaxes(np.asarray(R_a), -1, -2) @ np.asarray(R_b)
    return np.linalg.norm(matrix_to_rotvec(Rd), axis=-1)


# ---------------------------------------------------------------------------
# Kinematic building blocks
# ---------------------------------------------------------------------------


class _SinSum:
    """``offset + sum_k amp_k sin(omega_k t + phase_k)`` with analytic derivatives."""

    def __init__(self, amp, omega, phase, offset: float = 0.0):
        self.amp = np.atleast_1d(np.asarray(amp, dtype=float))
        self.omega = np.atleast_1d(np.asarray(omega, dtype=float))
        self.phase = np.atleast_1d(np.asarray(phase, dtype=float))
        self.offset = float(offset)

    def scaled_time(self, lam: float) -> "_SinSum":
        return _SinSum(self.amp, self.omega * lam, self.phase, self.offset)

    def __call__(self, t: np.ndarray):
        arg = np.multiply.outer(t, self.omega) + self.phase
        s, c = np.sin(arg), np.cos(arg)
        v = self.offset + s @ self.amp
        d1 = c @ (self.amp * self.omega)
        d2 = -(s @ (self.amp * self.omega**2))
        return v, d1, d2

    @classmethod
    def random(cls, rng: np.random.Generator, n: int, amplitude: float, f_lo: float, f_hi: float,
               offset: float = 0.0) -> "_SinSum":
        """``n`` components with weights summing to ``amplitude`` (so ``|value - offset| <= amplitude``)."""
        w = rng.uniform(0.2, 1.0, n)
        w *= amplitude / w.sum()
        f = rng.uniform(f_lo, f_hi, n)
        ph = rng.uniform(0.0, 2.0 * np.pi, n)
        return cls(w, 2.0 * np.pi * f, ph, offset)


def _cross(a, b):
    return np.cross(a, b)


def _chain(axes: Sequence[np.ndarray], angles: Sequence[tuple], R0, w0, al0):
    """Compose elementary rotations ``R = R0 Rot(a_0, th_0) Rot(a_1, th_1) ...``.

    ``angles[j] = (th, thd, thdd)`` arrays of shape (n,). Returns the rotation,
    its world angular velocity and angular acceleration:
    ``w = w0 + sum_j thd_j u_j`` and ``al = al0 + sum_j (thdd_j u_j + thd_j w_{<j} x u_j)``
    with ``u_j = R_{<j} a_j``.
    """
    R, w, al = R0, w0, al0
    for a, (th, thd, thdd) in zip(axes, angles):
        u = R @ a
        al = al + thdd[:, None] * u + thd[:, None] * _cross(w, u)
        w = w + thd[:, None] * u
        R = R @ axis_angle_to_matrix(a, th)
    return R, w, al


def _attached(R, w, al, p, pd, pdd, d, dd=None, ddd=None):
    """Point ``q = p + R d`` (``d`` in the rotating frame, optionally moving) and its derivatives."""
    Rd = np.einsum("nij,j->ni", R, d) if np.ndim(d) == 1 else np.einsum("nij,nj->ni", R, d)
    q = p + Rd
    qd = pd + _cross(w, Rd)
    qdd = pdd + _cross(al, Rd) + _cross(w, _cross(w, Rd))
    if dd is not None:
        Rdd = np.einsum("nij,nj->ni", R, dd)
        qd = qd + Rdd
        qdd = qdd + 2.0 * _cross(w, Rdd)
        if ddd is not None:
            qdd = qdd + np.einsum("nij,nj->ni", R, ddd)
    return q, qd, qdd


def _time_s(t_us) -> tuple[np.ndarray, bool]:
    """Integer microseconds (scalar or array) -> float seconds (n,) and a scalar flag."""
    arr = np.asarray(t_us)
    if arr.dtype.kind not in "iu":
        if arr.dtype.kind != "f" or not np.all(arr == np.round(arr)):
            raise ValueError("time is an integer count of microseconds")
    scalar = arr.ndim == 0
    t = np.atleast_1d(arr).astype(np.float64).ravel() * 1e-6
    return t, scalar


@dataclass(frozen=True)
class Kinematics:
    """Full kinematic state at one or more times (source frame unless noted)."""

    position: np.ndarray  # (3,) or (n, 3), m
    velocity: np.ndarray  # m/s
    acceleration: np.ndarray  # m/s^2
    R: np.ndarray  # (3, 3) or (n, 3, 3), sensor -> source
    angular_velocity: np.ndarray  # rad/s, sensor frame


class Trajectory:
    """Base class. Subclasses implement ``_eval(t_s) -> (p, v, a, R, w_body)`` for float seconds (n,)."""

    #: nominal duration in microseconds (trajectories stay defined beyond it)
    duration_us: int | None = None

    def _eval(self, t: np.ndarray):  # pragma: no cover - abstract
        raise NotImplementedError

    def kinematics(self, t_us) -> Kinematics:
        t, scalar = _time_s(t_us)
        p, v, a, R, w = self._eval(t)
        if scalar:
            return Kinematics(p[0], v[0], a[0], R[0], w[0])
        return Kinematics(p, v, a, R, w)

    def pose(self, t_us):
        """``(position (3,) m, R (3, 3) sensor -> source)``; arrays of n times give (n, 3), (n, 3, 3)."""
        k = self.kinematics(t_us)
        return k.position, k.R

    def position(self, t_us) -> np.ndarray:
        return self.kinematics(t_us).position

    def velocity(self, t_us) -> np.ndarray:
        return self.kinematics(t_us).velocity

    def acceleration(self, t_us) -> np.ndarray:
        """Second derivative of the position (m/s^2, source/world frame)."""
        return self.kinematics(t_us).acceleration

    def angular_velocity(self, t_us) -> np.ndarray:
        """Angular velocity in the sensor frame (rad/s)."""
        return self.kinematics(t_us).angular_velocity


# ---------------------------------------------------------------------------
# Static poses
# ---------------------------------------------------------------------------


class StaticPose(Trajectory):
    """Sensor at rest at ``position`` (m, source frame) with orientation ``R`` (sensor -> source)."""

    def __init__(self, position, R=None):
        self.p = np.asarray(position, dtype=float).reshape(3)
        self.R = np.eye(3) if R is None else np.asarray(R, dtype=float).reshape(3, 3)

    def _eval(self, t):
        n = t.shape[0]
        z = np.zeros((n, 3))
        return np.tile(self.p, (n, 1)), z, z.copy(), np.tile(self.R, (n, 1, 1)), z.copy()

    def __repr__(self) -> str:
        return f"StaticPose(position={self.p.tolist()})"


def _hemisphere_directions(n: int, max_angle_rad: float) -> np.ndarray:
    """``n`` near-uniform unit vectors within ``max_angle_rad`` of +x (Fibonacci spiral on a cap)."""
    i = np.arange(n) + 0.5
    cos_lo = np.cos(max_angle_rad)
    c = 1.0 - (1.0 - cos_lo) * i / n  # cos of the angle from +x, uniform in area
    s = np.sqrt(np.clip(1.0 - c * c, 0.0, None))
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.stack([c, s * np.cos(phi), s * np.sin(phi)], axis=-1)


def static_grid(
    distances: Sequence[float] = (0.10, 0.15, 0.20, 0.30, 0.40, 0.50, 0.60, 0.70, 0.80),
    n_directions: int = 12,
    max_angle_deg: float = 55.0,
    seed: int | None = None,
) -> list[StaticPose]:
    """Static poses on a grid of distances (m) times directions in the +x hemisphere.

    Directions are a Fibonacci spiral within ``max_angle_deg`` of +x, so with
    the default 55 deg every pose has ``x >= cos(55 deg) * min(distances)``
    (0.057 m at 10 cm). Orientation is the identity when ``seed`` is None,
    else a uniformly random rotation per pose drawn from ``default_rng(seed)``.
    Order: distance-major.
    """
    dirs = _hemisphere_directions(n_directions, np.radians(max_angle_deg))
    rng = None if seed is None else np.random.default_rng(seed)
    out = []
    for r in distances:
        for u in dirs:
            R = np.eye(3) if rng is None else random_rotation(rng)
            out.append(StaticPose(float(r) * u, R))
    return out


# ---------------------------------------------------------------------------
# Thesis sec 5.3 bench test: sensor moved by hand around the fixed source
# ---------------------------------------------------------------------------


class HandMovedBench(Trajectory):
    """Thesis ``002_cd7f1fdb7fc67471.txt`` sec 5.3 / Fig. 5.6 bench test.

    The sensor is "moved by hand around the fixed source from approximately
    15 cm to 80 cm" and "rotated along all axes". Model: spherical coordinates
    around the source,

        p(t) = r(t) * (cos el cos az, cos el sin az, sin el)
        R(t) = R0 @ exp([v(t)]x)

    where ``az``, ``el`` and the three components of the rotation vector ``v``
    are each a sum of three seeded low-frequency sinusoids whose weights sum
    to the stated amplitude, and ``r = r_c + r_a tanh(2 s(t))`` with ``s`` such
    a sum of unit amplitude (the tanh spends more time near the ends of the
    range, like the sweeps of thesis Fig. 5.6), so the bounds hold exactly
    for all t:

    * ``r_min <= r <= r_max`` (default 0.15..0.80 m, never closer than 12 cm);
    * ``|az| <= 55 deg``, ``|el| <= 45 deg``, hence
      ``x >= r_min cos 45 cos 55 = 0.061 m`` (+x hemisphere);
    * ``|v_i| <= rot_amplitude`` (default 1.2 rad, i.e. rotations about all axes).

    Frequencies are drawn in 0.02-0.06 Hz (distance) and 0.02-0.08 Hz
    (direction, rotation), then the position and the rotation time bases are
    stretched so the peak speed over ``[0, duration]`` is at most ``v_max``
    (default 0.20 m/s) and the peak angular rate at most ``w_max_deg`` (60 deg/s);
    over a 60 s run the peak speed is typically 0.1-0.2 m/s and the mean
    speed a few cm/s. ``duration_s`` only sets the window for that time
    scaling; the trajectory is defined (and bounded) for all t.
    ``R0`` is a seeded uniform random rotation.
    """

    def __init__(
        self,
        seed: int,
        duration_s: float = 60.0,
        r_min: float = 0.15,
        r_max: float = 0.80,
        v_max: float = 0.20,
        w_max_deg: float = 60.0,
        az_max_deg: float = 55.0,
        el_max_deg: float = 45.0,
        rot_amplitude: float = 1.2,
    ):
        if not (0.0 < r_min < r_max):
            raise ValueError("need 0 < r_min < r_max")
        rng = np.random.default_rng(seed)
        self.seed = seed
        self.duration_us = int(round(duration_s * 1e6))
        rc, ra = 0.5 * (r_min + r_max), 0.5 * (r_max - r_min)
        r = _SinSum.random(rng, 3, 1.0, 0.02, 0.06)
        az = _SinSum.random(rng, 3, np.radians(az_max_deg), 0.02, 0.08)
        el = _SinSum.random(rng, 3, np.radians(el_max_deg), 0.02, 0.08)
        rot = [_SinSum.random(rng, 3, rot_amplitude, 0.02, 0.08) for _ in range(3)]
        self.R0 = random_rotation(rng)
        # stretch the time bases: peak over a window 4x the duration bounds the
        # peak over [0, duration] for any stretch factor <= 4
        u = np.arange(0.0, 4.0 * max(duration_s, 1.0), 0.02)
        self._r, self._az, self._el, self._rot = r, az, el, rot
        self._rc, self._ra, self._r_gain = rc, ra, 2.0
        _, v, _, _, w = self._eval(u)
        lam_p = np.clip(v_max / np.max(np.linalg.norm(v, axis=1)), 0.25, 4.0)
        lam_r = np.clip(np.radians(w_max_deg) / np.max(np.linalg.norm(w, axis=1)), 0.25, 4.0)
        self._r, self._az, self._el = (f.scaled_time(lam_p) for f in (r, az, el))
        self._rot = [f.scaled_time(lam_r) for f in rot]
        self.r_min, self.r_max = r_min, r_max
        self.v_max, self.w_max = v_max, np.radians(w_max_deg)

    def _eval(self, t):
        n = t.shape[0]
        s, sd, sdd = self._r(t)
        g = self._r_gain
        th = np.tanh(g * s)
        sech2 = 1.0 - th * th
        r = self._rc + self._ra * th
        rd = self._ra * g * sech2 * sd
        rdd = self._ra * (g * sech2 * sdd - 2.0 * g * g * th * sech2 * sd * sd)
        az = self._az(t)
        el = self._el(t)
        # position: p = Rz(az) Ry(-el) (r, 0, 0)
        zero = np.zeros((n, 3))
        Rp, wp, alp = _chain(
            [_EZ, -_EY], [az, el], np.broadcast_to(np.eye(3), (n, 3, 3)), zero, zero
        )
        d = np.zeros((n, 3))
        dd = np.zeros((n, 3))
        ddd = np.zeros((n, 3))
        d[:, 0], dd[:, 0], ddd[:, 0] = r, rd, rdd
        p, pv, pa = _attached(Rp, wp, alp, zero, zero, zero, d, dd, ddd)
        # orientation: R = R0 exp([v]x), body rate J_r(v) v'
        vv = np.stack([f(t)[0] for f in self._rot], axis=-1)
        vd = np.stack([f(t)[1] for f in self._rot], axis=-1)
        R = self.R0 @ rotvec_to_matrix(vv)
        w = np.einsum("nij,nj->ni", right_jacobian(vv), vd)
        return p, pv, pa, R, w


# ---------------------------------------------------------------------------
# Body-worn scenarios (thesis sec 5.3 / 6.3): segments on joint chains
# ---------------------------------------------------------------------------


@dataclass
class _Level:
    """One joint: offset from the parent joint (parent frame), then elementary rotations."""

    offset: np.ndarray
    axes: list
    angles: list  # list of _SinSum


class _SegmentChain(Trajectory):
    """Sensor rigidly mounted on the last segment of a chain of joints.

    ``p = o_1 + R_1 (o_2 + R_2 (... + d))``, ``R_sensor = R_1 R_2 ... M``, with
    analytic velocity, acceleration and angular velocity.
    """

    levels: list[_Level]
    sensor_offset: np.ndarray
    mount: np.ndarray

    def _eval(self, t):
        n = t.shape[0]
        R = np.broadcast_to(np.eye(3), (n, 3, 3))
        w = np.zeros((n, 3))
        al = np.zeros((n, 3))
        p = np.zeros((n, 3))
        pv = np.zeros((n, 3))
        pa = np.zeros((n, 3))
        for lev in self.levels:
            p, pv, pa = _attached(R, w, al, p, pv, pa, lev.offset)
            R, w, al = _chain(lev.axes, [f(t) for f in lev.angles], R, w, al)
        q, qv, qa = _attached(R, w, al, p, pv, pa, self.sensor_offset)
        Rs = R @ self.mount
        wb = np.einsum("nji,nj->ni", Rs, w)
        return q, qv, qa, Rs, wb


def _mount(x_axis, z_axis) -> np.ndarray:
    x = np.asarray(x_axis, float)
    z = np.asarray(z_axis, float)
    x /= np.linalg.norm(x)
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def _harmonics(rng, f0: float, mean_deg: float, amps_deg: Sequence[float], phase0: float = 0.0,
               jitter_deg: float = 0.0) -> _SinSum:
    """Periodic angle: mean + sum_k A_k sin(2 pi k f0 t + phi_k); first phase fixed, others seeded."""
    k = np.arange(1, len(amps_deg) + 1)
    amps = np.radians(np.asarray(amps_deg, float))
    if jitter_deg:
        amps = amps + np.radians(jitter_deg) * rng.uniform(-1.0, 1.0, len(amps))
    ph = np.concatenate([[phase0], rng.uniform(0.0, 2.0 * np.pi, len(amps) - 1)])
    return _SinSum(amps, 2.0 * np.pi * f0 * k, ph, np.radians(mean_deg))


#: right shoulder joint centre relative to a source on the lower back (m, source frame)
RIGHT_SHOULDER = np.array([0.06, -0.18, 0.45])
#: sensor on the proximal lateral upper arm, arm frame (arm hanging along -z)
UPPER_ARM_SENSOR = np.array([0.05, -0.05, -0.12])
#: right hip joint centre relative to a source on the lower back
RIGHT_HIP = np.array([0.10, -0.09, -0.10])
#: sensor on the anterior upper leg just above the knee, thigh frame (thigh along -z)
THIGH_SENSOR = np.array([0.07, -0.02, -0.38])
#: sensor on the back at the first thoracic vertebra (thesis sec 5.4: ~45 cm up, 5 cm right, 6 cm forward)
T1_SENSOR = np.array([0.06, -0.05, 0.45])


class ArmAbduction(_SegmentChain):
    """Thesis ``002_cd7f1fdb7fc67471.txt`` sec 5.3 / 6.3 arm abduction-adduction.

    Source on the lower back, sensor on the proximal part of the right upper
    arm. The arm rotates about the right shoulder joint (:data:`RIGHT_SHOULDER`)
    with the chain ``Rot(-x, abduction) Rot(-y, flexion) Rot(z, humeral rotation)``
    (source frame: x forward, y left, z up):

    * abduction ``= max/2 (1 - cos(2 pi t / period))`` plus seeded 2nd/3rd
      harmonics (``variability`` deg), 0 -> ``max_abduction_deg`` -> 0 each period;
    * flexion wobble and humeral rotation: seeded sinusoids of a few degrees.

    Abduction turns about the x axis, so x stays near the shoulder's
    ``0.06 + 0.05`` m give or take the flexion wobble: ``x > 0.08 m``.
    """

    def __init__(self, seed: int = 0, duration_s: float = 60.0, period_s: float = 4.0,
                 max_abduction_deg: float = 90.0, variability_deg: float = 3.0):
        rng = np.random.default_rng(seed)
        self.seed = seed
        self.duration_us = int(round(duration_s * 1e6))
        f0 = 1.0 / period_s
        half = 0.5 * max_abduction_deg
        abd = _SinSum(
            np.radians([half, variability_deg * rng.uniform(0.3, 1.0), variability_deg * rng.uniform(0.3, 1.0)]),
            2.0 * np.pi * f0 * np.array([1.0, 2.0, 3.0]),
            np.concatenate([[-0.5 * np.pi], rng.uniform(0, 2 * np.pi, 2)]),
            np.radians(half),
        )
        flex = _SinSum.random(rng, 2, np.radians(6.0), 0.5 * f0, 1.5 * f0)
        rot = _SinSum.random(rng, 2, np.radians(5.0), 0.5 * f0, 1.5 * f0)
        self.levels = [_Level(RIGHT_SHOULDER, [-_EX, -_EY, _EZ], [abd, flex, rot])]
        self.sensor_offset = UPPER_ARM_SENSOR
        # sensor x along the arm (towards the elbow), z pointing laterally out
        self.mount = _mount([0.0, 0.0, -1.0], [0.0, -1.0, 0.0])


class Walking(_SegmentChain):
    """Thesis ``002_cd7f1fdb7fc67471.txt`` sec 5.3 / 6.3 walking trials (Table 5.1 rows "Walking").

    Periodic gait at ``stride_hz`` (default 1 Hz: one full gait cycle per
    second), source on the lower back, sensor on

    * ``segment="leg"`` (default): anterior upper leg just above the knee;
      hip flexion 8 +/- 18 deg (+ seeded 2nd harmonic), ab/adduction and rotation
      a few degrees about :data:`RIGHT_HIP`;
    * ``segment="arm"``: proximal upper arm; trunk counter-rotation at the
      lower back, then arm swing about the shoulder in anti-phase with the leg;
    * ``segment="back"``: first thoracic vertebra; small trunk rotation,
      lateral sway (stride frequency) and flexion (step frequency, 2 f).

    Stride-to-stride variability: seeded harmonic phases and small amplitude
    jitter. All three keep ``x > 0.05 m`` (checked in the tests).
    """

    def __init__(self, seed: int = 0, duration_s: float = 30.0, segment: str = "leg",
                 stride_hz: float = 1.0):
        rng = np.random.default_rng(seed)
        self.seed = seed
        self.segment = segment
        self.duration_us = int(round(duration_s * 1e6))
        f = stride_hz
        if segment == "leg":
            flex = _harmonics(rng, f, 8.0, [18.0, 3.0], 0.0, jitter_deg=1.5)
            abd = _harmonics(rng, f, 0.0, [4.0, 1.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.5)
            rot = _harmonics(rng, f, 0.0, [5.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.5)
            self.levels = [_Level(RIGHT_HIP, [-_EY, -_EX, _EZ], [flex, abd, rot])]
            self.sensor_offset = THIGH_SENSOR
            self.mount = _mount([0.0, 0.0, -1.0], [1.0, 0.0, 0.0])
        elif segment == "arm":
            trunk = _harmonics(rng, f, 0.0, [4.0], np.pi, jitter_deg=0.5)
            swing = _harmonics(rng, f, 5.0, [15.0, 2.0], np.pi, jitter_deg=1.5)
            abd = _harmonics(rng, f, 8.0, [2.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.5)
            self.levels = [
                _Level(np.zeros(3), [_EZ], [trunk]),
                _Level(RIGHT_SHOULDER, [-_EY, -_EX], [swing, abd]),
            ]
            self.sensor_offset = UPPER_ARM_SENSOR
            self.mount = _mount([0.0, 0.0, -1.0], [0.0, -1.0, 0.0])
        elif segment == "back":
            rot = _harmonics(rng, f, 0.0, [4.0], 0.0, jitter_deg=0.5)
            sway = _harmonics(rng, f, 0.0, [3.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.5)
            flex = _harmonics(rng, 2.0 * f, 4.0, [2.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.5)
            # trunk flexion about +y moves T1 (above the source) forward
            self.levels = [_Level(np.zeros(3), [_EZ, -_EX, _EY], [rot, sway, flex])]
            self.sensor_offset = T1_SENSOR
            self.mount = _mount([0.0, 0.0, 1.0], [-1.0, 0.0, 0.0])
        else:
            raise ValueError("segment must be 'leg', 'arm' or 'back'")


# ---------------------------------------------------------------------------
# Gietler et al. 2019: Brownian motion model and helix
# ---------------------------------------------------------------------------


def _euler_zyx_kinematics(th, thd, thdd):
    """R, body angular velocity, for ``R = Rz(th3) Ry(th2) Rx(th1)`` with Euler-angle rates."""
    n = th.shape[0]
    zero = np.zeros((n, 3))
    R, w, _ = _chain(
        [_EZ, _EY, _EX],
        [(th[:, 2], thd[:, 2], thdd[:, 2]), (th[:, 1], thd[:, 1], thdd[:, 1]), (th[:, 0], thd[:, 0], thdd[:, 0])],
        np.broadcast_to(np.eye(3), (n, 3, 3)),
        zero,
        zero,
    )
    wb = np.einsum("nji,nj->ni", R, w)
    return R, wb


class BrownianMotion(Trajectory):
    """Gietler ``003_93f59c2e1c5b6c59.txt`` Brownian-motion model, eqs 6-12.

    Velocity and Euler-angle rate are Wiener processes (eqs 6-7): continuous
    white-noise acceleration with intensities ``sigma_v`` (m s^-3/2) and
    ``sigma_w`` (rad s^-3/2). Sampled exactly at steps of ``dt_s`` by eq 8:
    ``v_t = v_{t-1} + alpha_t``, ``z_t = z_{t-1} + v_{t-1} dt + beta_t`` and the
    same for ``(omega, theta)``, with the increments ``U_t`` (eq 9) Gaussian of
    covariance eq 10 (per axis ``[[s^2 dt, s^2 dt^2/2], [s^2 dt^2/2, s^2 dt^3/3]]``),
    i.e. the state recursion eqs 11-12. (Eq 8 prints ``theta_t = theta_{t-1} +
    v_{t-1} dt + delta_t``; eq 12's transition matrix shows ``omega_{t-1}`` is meant.)
    ``theta`` are the Z-Y-X Euler angles of eqs 3-4: ``R = Rz Ry Rx``.

    Working-volume bound (not in the paper, which lets the target drift): a
    deterministic acceleration, held constant over each step and added to
    eq 8 (``v += a dt``, ``z += a dt^2/2``),

        a = -stiffness (z - center) - damping v + wall(z)

    where ``wall`` pushes back with ``wall_stiffness`` times the penetration
    of the soft walls ``x >= x_min``, ``r_min <= |z| <= r_max``; likewise
    ``-angular_damping omega`` on the Euler-angle rates (angles are free).
    With ``stiffness = damping = wall_stiffness = angular_damping = 0`` the
    process is exactly eq 8; :meth:`gietler` builds the paper's sec III-C run.

    Between nodes the pose is the cubic Hermite interpolant of the node
    positions and velocities (angles and rates), so position is C1 and the
    acceleration is piecewise linear (it jumps at nodes, as white-noise
    acceleration must). Nodes are generated lazily in fixed blocks in time
    order, so results do not depend on the query pattern; times must be >= 0.

    Defaults: the paper's ``sigma_v = 0.01``, ``sigma_w = 0.1``, ``dt = 0.1 s``
    and initial state (sec III-C) with the restoring terms on: stationary
    per-axis position std ``sigma_v / sqrt(2 damping stiffness)`` = 0.05 m about
    ``center`` (default ``z0``), speed std ``sigma_v / sqrt(2 damping)`` = 0.016 m/s,
    Euler-rate std ``sigma_w / sqrt(2 angular_damping)`` = 0.22 rad/s, and the
    soft walls keep ``x`` above about 0.09 m (checked over long runs in the tests).
    """

    _BLOCK = 256

    def __init__(
        self,
        seed: int,
        duration_s: float = 20.0,
        dt_s: float = 0.1,
        sigma_v: float = 0.01,
        sigma_w: float = 0.1,
        z0=(0.2, -0.2, 0.3),
        v0=(0.01, 0.0, -0.005),
        theta0=(0.02, -0.05, np.pi / 4),
        omega0=(0.0, 0.0, 0.0),
        center=None,
        stiffness: float = 0.1,
        damping: float = 0.2,
        angular_damping: float = 0.1,
        wall_stiffness: float = 2.0,
        x_min: float = 0.10,
        r_min: float = 0.15,
        r_max: float = 0.80,
    ):
        dt_us = int(round(dt_s * 1e6))
        if dt_us <= 0 or abs(dt_us * 1e-6 - dt_s) > 1e-12:
            raise ValueError("dt_s must be a positive whole number of microseconds")
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.duration_us = int(round(duration_s * 1e6))
        self.dt_us = dt_us
        self.dt = dt_us * 1e-6
        self.sigma_v, self.sigma_w = float(sigma_v), float(sigma_w)
        self.center = np.asarray(z0 if center is None else center, dtype=float)
        self.k, self.c, self.cw = float(stiffness), float(damping), float(angular_damping)
        self.k_wall, self.x_min, self.r_min, self.r_max = float(wall_stiffness), x_min, r_min, r_max
        dt = self.dt
        cov = np.array([[dt, dt * dt / 2.0], [dt * dt / 2.0, dt**3 / 3.0]])  # eq 10 block / sigma^2
        self._chol = np.linalg.cholesky(cov)
        z = np.asarray(z0, float)
        v = np.asarray(v0, float)
        th = np.asarray(theta0, float)
        om = np.asarray(omega0, float)
        self._nodes = [np.concatenate([z, v, th, om])[None, :]]
        self._arr = self._nodes[0]
        self._state = (z.copy(), v.copy(), th.copy(), om.copy())

    @classmethod
    def gietler(cls, seed: int) -> "BrownianMotion":
        """Sec III-C run: 20 s, dt 0.1 s, sigma_v 0.01, sigma_w 0.1, paper X_0, no restoring terms.

        Unbounded (position std grows as sigma_v t^1.5 / sqrt(3), 0.5 m at 20 s),
        so it can leave the +x half-space.
        """
        return cls(seed, 20.0, 0.1, 0.01, 0.1, stiffness=0.0, damping=0.0, angular_damping=0.0,
                   wall_stiffness=0.0)

    # -- node generation ---------------------------------------------------

    def _wall(self, z: np.ndarray) -> np.ndarray:
        if self.k_wall == 0.0:
            return np.zeros(3)
        f = np.zeros(3)
        if z[0] < self.x_min:
            f[0] += self.k_wall * (self.x_min - z[0])
        r = np.linalg.norm(z)
        if r < self.r_min:
            f += self.k_wall * (self.r_min - r) * z / max(r, 1e-9)
        elif r > self.r_max:
            f -= self.k_wall * (r - self.r_max) * z / r
        return f

    def _extend(self, n_nodes: int) -> None:
        dt = self.dt
        while self._arr.shape[0] < n_nodes:
            e = self.rng.standard_normal((self._BLOCK, 4, 3))
            # (alpha, beta) and (gamma, delta) per axis with covariance eq 10
            ab = self.sigma_v * np.einsum("ij,njk->nik", self._chol, e[:, 0:2, :])
            gd = self.sigma_w * np.einsum("ij,njk->nik", self._chol, e[:, 2:4, :])
            z, v, th, om = self._state
            rows = np.empty((self._BLOCK, 12))
            for i in range(self._BLOCK):
                a = -self.k * (z - self.center) - self.c * v + self._wall(z)
                aw = -self.cw * om
                z_new = z + v * dt + 0.5 * a * dt * dt + ab[i, 1]
                v_new = v + a * dt + ab[i, 0]
                th_new = th + om * dt + 0.5 * aw * dt * dt + gd[i, 1]
                om_new = om + aw * dt + gd[i, 0]
                z, v, th, om = z_new, v_new, th_new, om_new
                rows[i, 0:3], rows[i, 3:6], rows[i, 6:9], rows[i, 9:12] = z, v, th, om
            self._state = (z, v, th, om)
            self._nodes.append(rows)
            self._arr = np.concatenate(self._nodes, axis=0)
            self._nodes = [self._arr]

    def nodes(self, n: int | None = None) -> dict:
        """Node states ``t_us, z, v, theta, omega`` (eq 11 order rearranged) for the first ``n`` nodes."""
        if n is None:
            n = self.duration_us // self.dt_us + 1
        self._extend(n)
        a = self._arr[:n]
        return {
            "t_us": np.arange(n, dtype=np.int64) * self.dt_us,
            "z": a[:, 0:3],
            "v": a[:, 3:6],
            "theta": a[:, 6:9],
            "omega": a[:, 9:12],
        }

    # -- evaluation ----------------------------------------------------------

    def _eval(self, t):
        if np.any(t < 0.0):
            raise ValueError("BrownianMotion is defined for t >= 0")
        dt = self.dt
        k = np.floor(t / dt).astype(np.int64)
        self._extend(int(k.max()) + 2)
        A = self._arr
        s = (t - k * dt) / dt
        s = s[:, None]
        a0, a1 = A[k], A[k + 1]
        h00 = 2 * s**3 - 3 * s**2 + 1
        h10 = s**3 - 2 * s**2 + s
        h01 = -2 * s**3 + 3 * s**2
        h11 = s**3 - s**2
        d_h00 = (6 * s**2 - 6 * s) / dt
        d_h10 = 3 * s**2 - 4 * s + 1
        d_h01 = (-6 * s**2 + 6 * s) / dt
        d_h11 = 3 * s**2 - 2 * s
        dd_h00 = (12 * s - 6) / dt**2
        dd_h10 = (6 * s - 4) / dt
        dd_h01 = (-12 * s + 6) / dt**2
        dd_h11 = (6 * s - 2) / dt

        def herm(x0, m0, x1, m1):
            val = h00 * x0 + h10 * dt * m0 + h01 * x1 + h11 * dt * m1
            d1 = d_h00 * x0 + d_h10 * m0 + d_h01 * x1 + d_h11 * m1
            d2 = dd_h00 * x0 + dd_h10 * m0 + dd_h01 * x1 + dd_h11 * m1
            return val, d1, d2

        p, pv, pa = herm(a0[:, 0:3], a0[:, 3:6], a1[:, 0:3], a1[:, 3:6])
        th, thd, thdd = herm(a0[:, 6:9], a0[:, 9:12], a1[:, 6:9], a1[:, 9:12])
        R, wb = _euler_zyx_kinematics(th, thd, thdd)
        return p, pv, pa, R, wb


class Helix(Trajectory):
    """Gietler ``003_93f59c2e1c5b6c59.txt`` eq 33 (sec V, 80 s flight):

        z(t) = (0.6 cos 0.2t, 0.6 sin 0.2t, 0.01 t),  theta(t) = (0.0831, 0, 0.02 t)

    with ``R = Rz(theta_3) Ry(theta_2) Rx(theta_1)`` (eqs 3-4); position and
    angles are exact closed forms, derivatives analytic. In the paper this is
    the emitter relative to a receiver at the origin; here it is the sensor
    relative to the source (the relative geometry is what matters).
    (The paper's listed X_0 has ``v_0 = (0, 0.12, 0.02)`` and
    ``theta_0 = (0.1662, 0, 0.02)``, which do not match eq 33; eq 33 is used.)

    The paper helix circles the origin, so it leaves the +x half-space for
    ``t`` in (7.85 s, 23.6 s) and (39.3 s, 55.0 s): a tracker that resolves the
    hemisphere ambiguity by assuming x > 0 must track through it by
    continuity. Pass ``center`` to shift it (e.g. ``(0.8, 0, 0)`` keeps x > 0.2 m
    but changes the geometry).
    """

    def __init__(self, radius: float = 0.6, omega: float = 0.2, climb: float = 0.01,
                 roll: float = 0.0831, yaw_rate: float = 0.02, duration_s: float = 80.0,
                 center=(0.0, 0.0, 0.0)):
        self.radius, self.omega, self.climb = radius, omega, climb
        self.roll, self.yaw_rate = roll, yaw_rate
        self.center = np.asarray(center, dtype=float)
        self.duration_us = int(round(duration_s * 1e6))

    def _eval(self, t):
        n = t.shape[0]
        a, w = self.radius, self.omega
        c, s = np.cos(w * t), np.sin(w * t)
        p = self.center + np.stack([a * c, a * s, self.climb * t], axis=-1)
        pv = np.stack([-a * w * s, a * w * c, np.full(n, self.climb)], axis=-1)
        pa = np.stack([-a * w * w * c, -a * w * w * s, np.zeros(n)], axis=-1)
        th = np.stack([np.full(n, self.roll), np.zeros(n), self.yaw_rate * t], axis=-1)
        thd = np.zeros((n, 3))
        thd[:, 2] = self.yaw_rate
        R, wb = _euler_zyx_kinematics(th, thd, np.zeros((n, 3)))
        return p, pv, pa, R, wb

