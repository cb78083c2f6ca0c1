"""The body-worn experiments of the thesis (``002_cd7f1fdb7fc67471.txt`` sec
5.3, 6.3, Tables 5.1 and 6.1): the source on the lower back moves with the
person (``hil.body``), the sensor on the back (first thoracic vertebra), the
upper arm or the upper leg; the source's own IMU and magnetometer module
gives its orientation ``Phi`` (a ch. 2 filter) and its acceleration for
``a_net = a_sensor - a_source`` (eq 6.8).

Every row has five scenarios on the same motion and seed:

* ``roetenberg-<movement>-<segment>``: the tightly coupled tracker
  (``tight.tight_fusion``: every pulse window a measurement at its own time,
  eq 6.8 in the source frame, the source IMU's offsets as states); the
  report carries the magnetic-only figures of the same run (``magnetic_*``)
  and ``source_moving: true``;
* ``...-loose``: the loosely coupled ch. 6 filter (one burst solution per
  cycle, eq 6.8 with ``Phi`` from the source module's ch. 2 filter);
* ``...-noanet``: the loose one with the source's acceleration left out of
  eq 6.8 (``body.source_acceleration = false``): the difference is eq 6.8's;
* ``...-nooffset``: the tight one with the source's accelerometer without
  offset or random walk (sec 6.5: "the acceleration of the source is now
  related to orientation errors of the source Phi"): what that offset costs;
* ``...-nomc``: the loose one without the motion compensation within the
  burst (sec 6.5).

Every body scenario turns each pulse window's samples with the sensor's
gyroscope before the baseline fit (``body.baseline_gyro``) and raises
the ch. 2 filters' inclination variance with the measured motion
(``body.acc_adapt_gain``); see ``docs/bodyworn.md``.
"""
from __future__ import annotations

from coiltrack.firmware.config import FirmwareConfig

from .base import Family, Scenario, SensorSpec

SCENARIOS = Family()        # this family's scenarios (listed in scenarios/__init__.py)
register = SCENARIOS.add


#: per row: movement (hil.body.MOVEMENTS), scenario name, thesis figures (Table 5.1 magnetic
#: position mm / orientation deg, Table 6.1 fused position mm / orientation deg), hemisphere
BODY_ROWS = (
    ("back-flexion", "roetenberg-flexion-back", "Back, flexion", (5.9, 4.9, 4.8, 2.4)),
    ("back-latero-flexion", "roetenberg-lateroflexion-back", "Back, latero-flexion", (6.3, 5.2, 5.0, 2.6)),
    ("back-rotation", "roetenberg-rotation-back", "Back, rotation", (5.9, 5.1, 4.9, 2.6)),
    ("back-walking", "roetenberg-walking-back", "Back, walking", (8.6, 6.8, 5.6, 3.0)),
    ("arm-flexion", "roetenberg-flexion-arm", "Arm, flexion", (7.8, 6.6, 5.1, 2.4)),
    ("arm-abduction", "roetenberg-abduction-arm", "Arm, abduction", (7.2, 6.2, 5.0, 2.3)),
    ("arm-walking", "roetenberg-walking-arm", "Arm, walking", (11.7, 7.4, 7.9, 3.1)),
    ("leg-walking", "roetenberg-walking-leg", "Leg, walking", (15.0, 8.7, 8.6, 3.2)),
)

#: the ch. 2 filters' motion acceleration (``orientation.acc_motion_sigma``, m/s^2): segment
#: accelerations on the body are 0.3-2 m/s^2, the bench's 0.05 m/s^2 makes the inclination updates
#: of both filters (sensor Xi, source Phi) reject the motion and drift
BODY_ACC_MOTION_SIGMA = 0.5
#: the error of ``Phi f_source`` in eq 6.8 (``body.source_acc_sigma``, m/s^2 per sample): a source
#: orientation error of about 1 deg times g, held over a 0.6 s cycle, as white noise at 120 Hz
#: (0.17 m/s^2 x sqrt(72))
BODY_SOURCE_ACC_SIGMA = 1.5

#: the ch. 2 filters' adaptive motion variance (``body.acc_adapt_gain``): the inclination
#: variance grows with the measured variance of ``y_A - g Z`` (walking trunk 1-3 m/s^2 at 0.9-1.8 Hz;
#: on roetenberg-walking-back, 20 s, seed 1, the sensor's tilt error 8.9 -> 2.4 deg rms)
BODY_ACC_ADAPT_GAIN = 1.0

#: the tight tracker's fused poses are valid while its position std is at most this (``tight.tight_valid_sigma_m``,
#: m): between cycles it reaches 25-30 mm on the trunk once converged; above it only the first seconds after a start
BODY_VALID_SIGMA_M = 0.05

#: the sensor's half-space seen from the source (the dipole ambiguity, ``source.hemisphere``):
#: above the source for the back and arm sites, below it for the thigh
_HEMISPHERE = {"trunk": (0.0, 0.0, 1.0), "upper_arm": (0.0, 0.0, 1.0), "thigh": (0.0, 0.0, -1.0)}
#: the tight tracker's velocity std at a start (``tight.tight_init_sigma_vel``, m/s): the segment's speed
#: relative to the source, 1 m/s for the swinging arm and thigh in walking (with 0.2 m/s both lose the
#: track again and again in the first seconds: arm walking, 20 s, seed 1, 9 restarts, 624 mm fused;
#: with 1.0: none, 70.6 mm), 0.2 m/s otherwise (1.0 makes a trunk's start 3x worse)
_START_SIGMA_VEL = {"arm-walking": 1.0, "leg-walking": 1.0}


def _body_world(movement: str):
    def build(seed: int, duration_s: float):
        from coiltrack.hil import physics
        from coiltrack.hil.body import body_worn
        from coiltrack.hil.world import World

        src, sen, rel = body_worn(movement, seed, duration_s)
        return World(physics.thesis_source(), rel, source_trajectory=src, sensor_world_trajectory=sen)
    return build


def _body_config(movement: str, **kw):
    def make() -> FirmwareConfig:
        from coiltrack.hil.body import MOVEMENTS
        from coiltrack.hil.imu import NODE_SOURCE_IMU

        base = dict(imu_rate_hz=120.0, source_imu_id=NODE_SOURCE_IMU, hemisphere=_HEMISPHERE[MOVEMENTS[movement]],
                    acc_motion_sigma=BODY_ACC_MOTION_SIGMA, source_acc_sigma=BODY_SOURCE_ACC_SIGMA,
                    baseline_gyro=True, acc_adapt_gain=BODY_ACC_ADAPT_GAIN,
                    tight_init_sigma_vel=_START_SIGMA_VEL.get(movement, 0.2), tight_valid_sigma_m=BODY_VALID_SIGMA_M)
        base.update(kw)
        return FirmwareConfig().with_keys(**base)
    return make


def _reference(label: str, fig) -> dict:
    return {"source": f"Roetenberg 2006, Table 6.1 (fusion) and Table 5.1 (magnetic), {label}",
            "position_rms_mm": fig[2], "orientation_rms_deg": fig[3],
            "magnetic_position_rms_mm": fig[0], "magnetic_orientation_rms_deg": fig[1]}


_PARAMETERS = {"coils": "3 orthogonal, 50 turns, r=5.5 cm, 1.5 A", "pulse_ms": 60, "cycle_ms": 600,
               "mag_rate_hz": 120, "mag_noise_t": 0.5e-7, "imu_rate_hz": 120,
               "imu": "MTx-class: acc 2e-3 m/s^2/sqrt(Hz), gyro 0.05 deg/s/sqrt(Hz), seeded offsets",
               "source": "on the lower back, moving with the body (hil.body), its own IMU and magnetometer module",
               "measurement_model": "eq 6.21 (position, magnetic and inertial-magnetic orientation)"}

#: the tightly coupled tracker (``[tight]``, ``firmware_py/track/tight_fusion.py``): every pulse window
#: a measurement at its own time in the relative inertial filter (eq 6.8 in the source frame)
_TIGHT = {"tight_fusion": True}

_VARIANTS = (
    ("", "tightly coupled: each pulse window a measurement at its own time, eq 6.8 in the source frame",
     _TIGHT, True),
    ("-loose", "loosely coupled: one burst solution per cycle into the ch. 6 filter (eq 6.8)", {}, True),
    ("-noanet", "loosely coupled, the source's acceleration left out of eq 6.8", {"source_acceleration": False}, True),
    ("-nooffset", "tightly coupled, the source's accelerometer without offset (sec 6.5)", _TIGHT, False),
    ("-nomc", "loosely coupled, without the motion compensation within the burst (sec 6.5)",
     {"motion_compensation": False}, True),
)

for _movement, _name, _label, _fig in BODY_ROWS:
    for _suffix, _what, _kw, _offset in _VARIANTS:
        register(Scenario(
            name=_name + _suffix,
            summary=f"body-worn, {_label.lower()}: {_what} (thesis Tables 5.1, 6.1)",
            description=f"Thesis sec 5.3 / 6.3 body-worn test, {_label.lower()}: source on the lower back, "
                        f"moving with the body, with its own IMU and magnetometer module; {_what}; "
                        f"magnetic-only and fused figures of the same run.",
            duration_s=60.0,
            build_world=_body_world(_movement),
            firmware_config=_body_config(_movement, **_kw),
            sensor=SensorSpec(imu_rate_hz=120.0, source_imu_id=8, source_acc_offset=_offset),
            reference=_reference(_label, _fig),
            parameters={**_PARAMETERS, "movement": _movement},
        ))
