"""A kinematic body model for the body-worn experiments: the source on the
lower back moves with the person, the sensor on the trunk, arm or leg.

Thesis ``002_cd7f1fdb7fc67471.txt`` sec 5.3 and 6.3: "the three
perpendicular coils were attached to the lower back. One sensor was placed on
the back of a subject, at the level of the first thoracic vertebra and one
sensor was placed on the proximal part of the upper arm ... the sensor was
placed on the upper leg, just above the knee" (Tables 5.1 and 6.1).

Segments (each a rigid frame, x forward, y to the subject's left, z up when
standing): ``pelvis`` (carries the source), ``trunk`` (lumbar joint),
``upper_arm`` (right shoulder), ``forearm`` (elbow), ``thigh`` (right hip),
``shank`` (knee). The pelvis moves in the world (walking progression with
its vertical bounce and lateral sway, or rotation about the hips when
standing); every other segment hangs on its parent through elementary
rotations driven by seeded periodic profiles (:func:`movement`).
:class:`SegmentPoint` gives the world kinematics of a point on a segment,
including the angular acceleration, all analytic (chain rule through sums of
sinusoids, ``hil.motion._chain``); :class:`RelativeTrajectory` the pose of
the sensor in the source frame, what the magnetic system measures and what
``hil.world.World.trajectory`` is.

Amplitudes and frequencies (cited in :func:`movement`): gait after Perry &
Burnfield, *Gait Analysis: Normal and Pathological Function* (2nd ed. 2010,
ch. 2-4: cadence ~110 steps/min, hip flexion +30 / -10 deg, knee 0-60 deg,
pelvic rotation and obliquity about +-4 deg, pelvic tilt +-2 deg, vertical
excursion of the pelvis ~4-5 cm peak to peak at the step frequency, lateral
~4 cm at the stride frequency); walking speed 1.2-1.4 m/s (Bohannon,
*Age Ageing* 26:15, 1997, comfortable speed); arm swing about +-15-20 deg
of shoulder flexion in anti-phase with the ipsilateral leg (Collins et al.,
*Proc. R. Soc. B* 276:3679, 2009); forward bending shared by the hips and
the lumbar spine (lumbopelvic rhythm, Esola et al., *Spine* 21:71, 1996:
lumbar about 40 deg and hip about 25-30 deg early in the bend); lateral
flexion 25-35 deg and axial rotation 20-30 deg of the thoracolumbar spine
(AAOS normal ranges, Greene & Heckman 1994); standing postural sway a few
mm at 0.1-0.5 Hz (Prieto et al., *IEEE TBME* 43:956, 1996).

Times are integer microseconds, as for every ``hil.motion.Trajectory``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .motion import Trajectory, _attached, _chain, _cross, _harmonics, _mount, _SinSum, _time_s

_EX = np.array([1.0, 0.0, 0.0])
_EY = np.array([0.0, 1.0, 0.0])
_EZ = np.array([0.0, 0.0, 1.0])

#: segment geometry (m): joint centres in the parent's frame; the pelvis frame's
#: origin is the source's centre on the lower back (sacrum)
LUMBAR = np.array([0.0, 0.0, 0.05])             # L5/S1, pelvis frame
HIP_CENTRE = np.array([0.10, 0.0, -0.10])       # midpoint of the hip joints, pelvis frame (standing pivot)
RIGHT_HIP = np.array([0.10, -0.09, -0.10])      # pelvis frame (as hil.motion.RIGHT_HIP)
RIGHT_SHOULDER = np.array([0.06, -0.18, 0.40])  # trunk frame (45 cm above the source, as hil.motion)
ELBOW = np.array([0.0, 0.0, -0.30])             # upper-arm frame
KNEE = np.array([0.0, 0.0, -0.42])              # thigh frame
#: sensor sites (m) and mounts (segment -> sensor rotation)
T1_SITE = np.array([0.06, -0.05, 0.40])         # trunk frame: thesis sec 5.4 (45 cm up, 5 cm right, 6 cm fwd)
UPPER_ARM_SITE = np.array([0.05, -0.05, -0.12])  # upper-arm frame, proximal lateral
THIGH_SITE = np.array([0.07, -0.02, -0.38])     # thigh frame, anterior, just above the knee
T1_MOUNT = _mount([0.0, 0.0, 1.0], [-1.0, 0.0, 0.0])
ARM_MOUNT = _mount([0.0, 0.0, -1.0], [0.0, -1.0, 0.0])
THIGH_MOUNT = _mount([0.0, 0.0, -1.0], [1.0, 0.0, 0.0])
#: pelvis height of a standing adult (m, world frame)
PELVIS_HEIGHT = 1.0

#: parent, joint offset (parent frame) and rotation axes of each segment below the pelvis
SEGMENTS = {
    "trunk": ("pelvis", LUMBAR, (_EY, _EX, _EZ)),              # flexion, right lateral flexion, left rotation
    "upper_arm": ("trunk", RIGHT_SHOULDER, (-_EY, -_EX, _EZ)),  # flexion, abduction, rotation
    "forearm": ("upper_arm", ELBOW, (-_EY,)),                 # elbow flexion
    "thigh": ("pelvis", RIGHT_HIP, (-_EY, -_EX, _EZ)),          # hip flexion, abduction, rotation
    "shank": ("thigh", KNEE, (_EY,)),                         # knee flexion
}


def _zero() -> _SinSum:
    return _SinSum([0.0], [0.0], [0.0], 0.0)


@dataclass
class BodyMotion:
    """Profiles of one movement: angles in rad (``_SinSum``), positions in m.

    ``pelvis_translation``: three functions of the pelvis origin (world x, y,
    z, added to ``speed_mps * t`` along x and :data:`PELVIS_HEIGHT` along z);
    ``pelvis_angles``: ``Rot(z, yaw) Rot(x, obliquity) Rot(y, tilt)``;
    ``pelvis_pivot``: None (the pelvis rotates about its origin, walking) or a
    point of the pelvis frame fixed in the world (standing: the hips);
    ``joints``: per segment the angle functions of :data:`SEGMENTS` axes
    (missing ones are zero).
    """

    speed_mps: float = 0.0
    pelvis_translation: tuple = field(default_factory=lambda: (_zero(), _zero(), _zero()))
    pelvis_angles: tuple = field(default_factory=lambda: (_zero(), _zero(), _zero()))
    pelvis_pivot: np.ndarray | None = None
    joints: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SegmentState:
    """World kinematics of a segment frame at n times: origin ``p`` (n, 3) m,
    ``v`` m/s, ``a`` m/s^2, rotation ``R`` (n, 3, 3) segment -> world,
    angular velocity ``w`` and acceleration ``al`` (n, 3), world frame."""

    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    R: np.ndarray
    w: np.ndarray
    al: np.ndarray


class Body:
    """The kinematic chain of :data:`SEGMENTS` driven by a :class:`BodyMotion`."""

    def __init__(self, motion: BodyMotion):
        self.motion = motion

    def pelvis(self, t: np.ndarray) -> SegmentState:
        m = self.motion
        n = t.shape[0]
        z3 = np.zeros((n, 3))
        ang = [f(t) for f in m.pelvis_angles]
        R, w, al = _chain((_EZ, _EX, _EY), ang, np.broadcast_to(np.eye(3), (n, 3, 3)), z3, z3)
        tr = [f(t) for f in m.pelvis_translation]
        p = np.stack([tr[0][0] + m.speed_mps * t, tr[1][0], tr[2][0] + PELVIS_HEIGHT], axis=-1)
        v = np.stack([tr[0][1] + m.speed_mps, tr[1][1], tr[2][1]], axis=-1)
        a = np.stack([tr[0][2], tr[1][2], tr[2][2]], axis=-1)
        if m.pelvis_pivot is not None:
            # the pivot (hips) follows the translation; the origin hangs on it
            p, v, a = _attached(R, w, al, p, v, a, -np.asarray(m.pelvis_pivot, float))
        return SegmentState(p, v, a, np.asarray(R), w, al)

    def segment(self, name: str, t: np.ndarray) -> SegmentState:
        if name == "pelvis":
            return self.pelvis(t)
        parent, offset, axes = SEGMENTS[name]
        s = self.segment(parent, t)
        p, v, a = _attached(s.R, s.w, s.al, s.p, s.v, s.a, offset)
        fns = self.motion.joints.get(name, ())
        angles = [(fns[k] if k < len(fns) else _zero())(t) for k in range(len(axes))]
        R, w, al = _chain(axes, angles, s.R, s.w, s.al)
        return SegmentState(p, v, a, R, w, al)


class SegmentPoint(Trajectory):
    """World pose of a frame fixed on a segment: ``p = p_seg + R_seg d``,
    ``R = R_seg M`` (``d`` m in the segment frame, ``M`` segment -> point
    frame). ``_eval`` follows ``hil.motion.Trajectory`` (world frame, body
    rate); :meth:`full` also gives the world angular velocity and acceleration."""

    def __init__(self, body: Body, segment: str, offset=(0.0, 0.0, 0.0), mount=None, duration_s: float = 60.0):
        self.body = body
        self.segment_name = segment
        self.offset = np.asarray(offset, float).reshape(3)
        self.mount = np.eye(3) if mount is None else np.asarray(mount, float).reshape(3, 3)
        self.duration_us = int(round(duration_s * 1e6))

    def full(self, t: np.ndarray):
        """``(p, v, a, R, w_world, al_world)`` at float seconds ``t`` (n,)."""
        s = self.body.segment(self.segment_name, t)
        p, v, a = _attached(s.R, s.w, s.al, s.p, s.v, s.a, self.offset)
        return p, v, a, s.R @ self.mount, s.w, s.al

    def full_us(self, t_us):
        t, _ = _time_s(t_us)
        return self.full(t)

    def _eval(self, t):
        p, v, a, R, w, _ = self.full(t)
        return p, v, a, R, np.einsum("nji,nj->ni", R, w)


class RelativeTrajectory(Trajectory):
    """The sensor's pose in the source frame from the world kinematics of both.

    With ``d = p_x - p_s`` (world), ``w``, ``al`` the source's world angular
    velocity and acceleration: ``q = R_s^T d``,
    ``q' = R_s^T (d' - w x d)``,
    ``q'' = R_s^T (d'' - al x d - 2 w x d' + w x (w x d))``,
    ``R = R_s^T R_x`` and the relative body rate ``R_x^T (w_x - w_s)``
    (``R^T dR/dt = [R_x^T (w_x - w_s)]x``).
    """

    def __init__(self, source: SegmentPoint, sensor: SegmentPoint):
        self.source = source
        self.sensor = sensor
        self.duration_us = sensor.duration_us

    def _eval(self, t):
        ps, vs, as_, Rs, ws, als = self.source.full(t)
        px, vx, ax, Rx, wx, _ = self.sensor.full(t)
        d, dd, ddd = px - ps, vx - vs, ax - as_
        RsT = np.swapaxes(Rs, -1, -2)
        q = np.einsum("nij,nj->ni", RsT, d)
        qd = np.einsum("nij,nj->ni", RsT, dd - _cross(ws, d))
        qdd = np.einsum("nij,nj->ni", RsT, ddd - _cross(als, d) - 2.0 * _cross(ws, dd) + _cross(ws, _cross(ws, d)))
        R = RsT @ Rx
        wb = np.einsum("nji,nj->ni", Rx, wx - ws)
        return q, qd, qdd, R, wb


# ---------------------------------------------------------------------------
# Movement profiles
# ---------------------------------------------------------------------------

#: the movements of Tables 5.1 / 6.1 and the segment that carries the sensor
MOVEMENTS = {
    "back-flexion": "trunk", "back-latero-flexion": "trunk", "back-rotation": "trunk", "back-walking": "trunk",
    "arm-flexion": "upper_arm", "arm-abduction": "upper_arm", "arm-walking": "upper_arm",
    "leg-walking": "thigh",
}
SENSOR_SITES = {"trunk": (T1_SITE, T1_MOUNT), "upper_arm": (UPPER_ARM_SITE, ARM_MOUNT),
                "thigh": (THIGH_SITE, THIGH_MOUNT)}


def _bend(rng, period_s: float, max_deg: float, var_deg: float) -> _SinSum:
    """0 -> ``max_deg`` -> 0 each period (``max/2 (1 - cos)``) plus seeded 2nd/3rd harmonics."""
    f0 = 1.0 / period_s
    half = np.radians(0.5 * max_deg)
    v = np.radians(var_deg)
    return _SinSum([half, v * rng.uniform(0.3, 1.0), v * rng.uniform(0.3, 1.0)],
                   2.0 * np.pi * f0 * np.array([1.0, 2.0, 3.0]),
                   np.concatenate([[-0.5 * np.pi], rng.uniform(0.0, 2.0 * np.pi, 2)]), half)


def _sway(rng, amp_m: float, f_lo: float = 0.1, f_hi: float = 0.5) -> _SinSum:
    """Postural sway: two seeded components, ``|x| <= amp_m`` (Prieto et al. 1996: a few mm, 0.1-0.5 Hz)."""
    return _SinSum.random(rng, 2, amp_m, f_lo, f_hi)


def _wobble(rng, amp_deg: float, f_lo: float, f_hi: float) -> _SinSum:
    return _SinSum.random(rng, 2, np.radians(amp_deg), f_lo, f_hi)


def movement(name: str, seed: int = 0) -> BodyMotion:
    """The :class:`BodyMotion` of one row of Tables 5.1 / 6.1 (seeded).

    Standing tasks (``back-*`` but walking, ``arm-flexion``, ``arm-abduction``):
    the pelvis pivots about the hips (:data:`HIP_CENTRE`) with a few degrees
    of tilt and sways 5 mm; each bend takes ``period`` s (the thesis' subjects
    did two or three per trial, Fig. 5.7, Fig. 6.5):

    * back flexion: lumbar flexion 0 -> 40 deg, pelvic (hip) tilt 0 -> 25 deg
      (Esola et al. 1996), 6 s;
    * back latero-flexion: lumbar lateral flexion +-25 deg (right, then
      left), pelvic obliquity +-3 deg, 6 s;
    * back rotation: trunk axial rotation +-20 deg, the pelvis -+5 deg, 6 s
      (the sensor stays in the source's +x half-space);
    * arm flexion / abduction: shoulder 0 -> 90 deg and back, 4 s, flexion or
      abduction wobble and humeral rotation of a few degrees.

    Walking (``*-walking``): stride frequency 0.9 Hz (cadence 108 steps/min),
    1.25 m/s forward; pelvis bounce 2.2 cm peak to peak at 2 f (half the 4-5 cm
    cited above: a conservative choice, the accelerations scale with it), sway
    +-2 cm at f, rotation
    +-4 deg and obliquity +-4 deg at f, tilt +-2 deg at 2 f; trunk
    counter-rotation +-6 deg against the pelvis at f; hip flexion 10 +- 20 deg
    (2nd harmonic 3 deg), knee 25 +- 25 deg (2nd harmonic 10 deg); right arm
    swing 5 +- 16 deg in anti-phase with the right hip, abduction 8 deg;
    elbow 20 +- 8 deg (Perry & Burnfield 2010, Collins et al. 2009).
    Stride-to-stride variability: seeded harmonic phases and amplitude jitter.
    """
    rng = np.random.default_rng(seed)
    if name.endswith("walking"):
        return _walking(rng)
    sway = (_sway(rng, 0.005), _sway(rng, 0.005), _zero())
    task = _STANDING.get(name)
    if task is None:
        raise ValueError(f"unknown movement '{name}'; known: {', '.join(MOVEMENTS)}")
    return task(rng, sway, name)


def _walking(rng) -> BodyMotion:
    """Walking: the gait of :func:`movement`'s docstring (seeded phases and jitter)."""
    f = 0.9
    return BodyMotion(
        speed_mps=1.25,
        pelvis_translation=(_zero(),                                       # steady progression (speed_mps)
                            _SinSum([0.02], [2 * np.pi * f], [0.0]),    # lateral sway at f
                            _SinSum([0.011], [4 * np.pi * f], [np.pi / 2])),  # bounce 2.2 cm p-p at 2 f
        pelvis_angles=(_harmonics(rng, f, 0.0, [4.0], 0.0, jitter_deg=0.5),     # rotation
                       _harmonics(rng, f, 0.0, [4.0], np.pi / 2, jitter_deg=0.5),  # obliquity
                       _harmonics(rng, 2 * f, 0.0, [2.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.3)),
        joints={
            "trunk": (_harmonics(rng, 2 * f, 2.0, [1.5], rng.uniform(0, 2 * np.pi), jitter_deg=0.3),
                      _harmonics(rng, f, 0.0, [2.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.3),
                      _harmonics(rng, f, 0.0, [6.0], np.pi, jitter_deg=0.5)),
            "thigh": (_harmonics(rng, f, 10.0, [20.0, 3.0], 0.0, jitter_deg=1.5),
                      _harmonics(rng, f, 0.0, [4.0, 1.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.5),
                      _harmonics(rng, f, 0.0, [5.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.5)),
            "shank": (_harmonics(rng, f, 25.0, [25.0, 10.0], -0.5 * np.pi, jitter_deg=2.0),),
            "upper_arm": (_harmonics(rng, f, 5.0, [16.0, 2.0], np.pi, jitter_deg=1.5),
                          _harmonics(rng, f, 8.0, [2.0], rng.uniform(0, 2 * np.pi), jitter_deg=0.5)),
            "forearm": (_harmonics(rng, f, 20.0, [8.0], np.pi, jitter_deg=1.0),),
        })


def _back_flexion(rng, sway, name: str) -> BodyMotion:
    per = 6.0
    return BodyMotion(pelvis_translation=sway, pelvis_pivot=HIP_CENTRE,
                      pelvis_angles=(_zero(), _zero(), _bend(rng, per, 25.0, 2.0)),
                      joints={"trunk": (_bend(rng, per, 40.0, 3.0), _wobble(rng, 3.0, 0.1, 0.3),
                                        _wobble(rng, 3.0, 0.1, 0.3))})


def _back_latero_flexion(rng, sway, name: str) -> BodyMotion:
    per = 6.0
    lat = _SinSum([np.radians(25.0), np.radians(2.0) * rng.uniform(0.3, 1.0)],
                  2 * np.pi / per * np.array([1.0, 2.0]), [0.0, rng.uniform(0, 2 * np.pi)])
    obl = _SinSum([np.radians(3.0)], [2 * np.pi / per], [np.pi])
    return BodyMotion(pelvis_translation=sway, pelvis_pivot=HIP_CENTRE, pelvis_angles=(_zero(), obl, _zero()),
                      joints={"trunk": (_wobble(rng, 4.0, 0.1, 0.3), lat, _wobble(rng, 3.0, 0.1, 0.3))})


def _back_rotation(rng, sway, name: str) -> BodyMotion:
    per = 6.0
    rot = _SinSum([np.radians(20.0), np.radians(2.0) * rng.uniform(0.3, 1.0)],
                  2 * np.pi / per * np.array([1.0, 2.0]), [0.0, rng.uniform(0, 2 * np.pi)])
    yaw = _SinSum([np.radians(5.0)], [2 * np.pi / per], [np.pi])
    return BodyMotion(pelvis_translation=sway, pelvis_pivot=HIP_CENTRE, pelvis_angles=(yaw, _zero(), _zero()),
                      joints={"trunk": (_wobble(rng, 4.0, 0.1, 0.3), _wobble(rng, 3.0, 0.1, 0.3), rot)})


def _arm(rng, sway, name: str) -> BodyMotion:
    per = 4.0
    main = _bend(rng, per, 90.0, 3.0)
    other = _wobble(rng, 6.0, 0.5 / per, 1.5 / per)
    hum = _wobble(rng, 5.0, 0.5 / per, 1.5 / per)
    arm = (main, other, hum) if name == "arm-flexion" else (other, main, hum)
    return BodyMotion(pelvis_translation=sway, pelvis_pivot=HIP_CENTRE,
                      pelvis_angles=(_wobble(rng, 1.0, 0.1, 0.4), _wobble(rng, 1.0, 0.1, 0.4),
                                     _wobble(rng, 1.0, 0.1, 0.4)),
                      joints={"trunk": (_wobble(rng, 2.0, 0.1, 0.4), _wobble(rng, 2.0, 0.1, 0.4),
                                        _wobble(rng, 2.0, 0.1, 0.4)),
                              "upper_arm": arm})


#: the standing tasks of :func:`movement` (pelvis pivoting about the hips, 5 mm sway)
_STANDING = {"back-flexion": _back_flexion, "back-latero-flexion": _back_latero_flexion,
             "back-rotation": _back_rotation, "arm-flexion": _arm, "arm-abduction": _arm}


def body_worn(name: str, seed: int = 0, duration_s: float = 60.0):
    """``(source, sensor, relative)`` trajectories of movement ``name``: the
    source on the pelvis (its frame), the sensor on the movement's segment
    (:data:`MOVEMENTS`, :data:`SENSOR_SITES`), and the sensor in the source
    frame (:class:`RelativeTrajectory`)."""
    body = Body(movement(name, seed))
    seg = MOVEMENTS[name]
    site, mount = SENSOR_SITES[seg]
    src = SegmentPoint(body, "pelvis", duration_s=duration_s)
    sen = SegmentPoint(body, seg, site, mount, duration_s=duration_s)
    return src, sen, RelativeTrajectory(src, sen)
