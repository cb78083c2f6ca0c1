"""Scenarios of an imperfect bench (issue 14): ``imperfect-bench`` and ``imperfect-fusion``.

The world and the sensor nodes carry the imperfections of ``hil.imperfections`` (source coils
tilted, moved and of unequal gain; the magnetometer's soft and hard iron, temperature offset and
non-linearity; the IMU's scale, misalignment, g-sensitivity and bias instability; the
magnetometer-to-IMU misalignment), drawn from the seed :data:`BENCH_UNIT`: they belong to the
hardware, so every run seed sees the same unit and one calibration file serves all runs.

A run of these scenarios is made three times on the same trajectory and seed
(:func:`add_imperfect_comparison`): the imperfect bench with the firmware's calibration file
(``calibration_file``; the run itself), the imperfect bench without it (``uncalibrated_*``), and
the perfect bench (``perfect_*``: the same motion, sensor noise and clocks, no imperfection).
Without a calibration file the first two are the same run and the uncalibrated figures are the
run's own.

The motion. ``imperfect-fusion``: the roetenberg-bench hand motion (peak 12 cm/s, 30 deg/s) over
15-40 cm (Schepers' table area), where the perfect bench's fused error is about 1 cm and 0.3 deg;
over roetenberg-bench's 15-80 cm the noise at the far end (CRB 88 mm) would hide the imperfections.
``imperfect-bench`` (magnetic only) moves the sensor slowly (peak 2 cm/s, 4 deg/s) over 15-25 cm,
within 30 deg azimuth and 25 deg elevation of +x, turned up to 0.6 rad about each axis:
a magnetic-only pose is made of three pulses 100 ms apart, so at the hand motion's 12 cm/s and
30 deg/s the motion within the burst (some mm, some deg) would hide the calibration's few mm and
degrees; slow motion close to the source is where a calibration matters to a magnetic-only user.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from coiltrack.firmware.config import FirmwareConfig
from coiltrack.tools.scenarios.base import Family, _hil, Scenario, SensorSpec
from coiltrack.tools.scenarios.thesis import _fusion_config

SCENARIOS = Family()        # this family's scenarios (listed in scenarios/__init__.py)
register = SCENARIOS.add

#: the imperfection seed of the emulated hardware (one unit: source, sensor board and IMU)
BENCH_UNIT = 1

#: the hand motion of imperfect-fusion (roetenberg-bench's speeds, 15-40 cm)
MOTION = dict(r_min=0.15, r_max=0.40, v_max=0.12, w_max_deg=30.0)
#: the slow motion of imperfect-bench (magnetic only: motion within the burst kept below the imperfections)
SLOW_MOTION = dict(r_min=0.15, r_max=0.25, v_max=0.02, w_max_deg=4.0, az_max_deg=30.0, el_max_deg=25.0,
                   rot_amplitude=0.6)


def bench_imperfections(unit: int = BENCH_UNIT, spec=None, sensor_ids=(16,)):
    """The imperfections of hardware unit ``unit`` for the thesis source (``hil.imperfections``)."""
    World, motion, physics = _hil()
    from coiltrack.hil.imperfections import Imperfections

    return Imperfections.draw(unit, physics.thesis_source().coils, sensor_ids=sensor_ids, spec=spec)


def write_truth_calibration(path, unit: int = BENCH_UNIT, spec=None, sensors: bool = True) -> dict:
    """Write the true imperfections of hardware ``unit`` as a calibration file (TOML, the
    firmware's ``calibration.dumps_toml``; sigmas zero, ``meta.method = "truth"``): the best a
    calibration can do, for checking the calibrated path end to end. ``sensors=False``: the
    ``[source]`` rows only. Returns the table."""
    from coiltrack.firmware.calibration import dumps_toml

    tab = bench_imperfections(unit, spec).as_calibration_table()
    if not sensors:
        tab.pop("sensor")
    with open(path, "w") as fh:
        fh.write(dumps_toml(tab))
    return tab


def imperfect_world_builder(imperfect: bool = True, unit: int = BENCH_UNIT, spec=None, motion=None):
    """``build_world(seed, duration_s)`` of the scenarios: the thesis source (its coils as built
    when ``imperfect``) and the hand motion :data:`MOTION` drawn from ``seed``; the world keeps
    its :class:`hil.imperfections.Imperfections` as ``world.imperfections`` (None: perfect)."""
    def build(seed: int, duration_s: float):
        World, motion_mod, physics = _hil()

        nominal = physics.thesis_source().coils
        imp = bench_imperfections(unit, spec) if imperfect else None
        coils = imp.apply_source(nominal) if imp is not None else nominal
        world = World(coils, motion_mod.HandMovedBench(seed=seed, duration_s=duration_s, **(motion or MOTION)))
        world.imperfections = imp
        return world
    return build


@dataclass(frozen=True)
class ImperfectSensorSpec(SensorSpec):
    """The sensor nodes get the world's sensor imperfections (magnetometer, IMU) once built."""

    def install(self, bench, seed_driver: int, seed_sensor: int) -> None:
        imp = getattr(bench.world, "imperfections", None)
        if imp is not None:
            imp.install(bench.sensors)


def imperfection_figures(bench, rep: dict, cfg) -> dict:
    """Report keys of an imperfect run: ``imperfections`` (each with its value) and
    ``calibration`` (the firmware's calibration file, None without)."""
    imp = getattr(bench.world, "imperfections", None)
    return {"imperfections": imp.listing() if imp is not None else [],
            "calibration": getattr(getattr(cfg, "calibration", None), "calibration_file", "") or None}


#: report keys copied from the comparison runs
COMPARE_KEYS = ("position_rms_mm", "orientation_rms_deg")

#: scenario name -> (its perfect twin: the same trajectory, nodes and firmware, no imperfection)
PERFECT: dict[str, Scenario] = {}


def add_imperfect_comparison(rep: dict, scenario: Scenario, seed: int, duration_s: float, cfg=None,
                             faults=None, transport: str = "inproc") -> dict:
    """For ``imperfect-bench`` / ``imperfect-fusion``: add ``uncalibrated_*`` (the imperfect bench
    with the firmware's calibration file removed; the run's own figures when it had none) and
    ``perfect_*`` (the perfect twin) to ``rep``, each run on the same trajectory and seed (simulated
    clock), with the ratios ``uncalibrated_over_calibrated_position`` and
    ``calibrated_over_perfect_position`` (and ``_orientation``). Other scenarios: ``rep`` unchanged."""
    if scenario.name not in PERFECT:
        return rep
    # imported where used here and below: the world's physics (magpylib) loads only when a run starts
    from ..bench.runner import run_inproc

    cfg = cfg or scenario.firmware_config()
    tr = transport if transport in ("inproc", "can") else "inproc"
    if getattr(getattr(cfg, "calibration", None), "calibration_file", ""):
        unc = run_inproc(scenario, seed, duration_s, faults=faults, transport=tr,
                         cfg=cfg.with_(calibration={"calibration_file": ""}))
    else:
        unc = rep
    per = run_inproc(PERFECT[scenario.name], seed, duration_s, faults=faults, transport=tr, cfg=cfg_perfect(cfg))
    for k in COMPARE_KEYS:
        rep["uncalibrated_" + k] = unc.get(k)
        rep["perfect_" + k] = per.get(k)
    ratio = lambda a, b: round(a / b, 3) if a is not None and b else None  # noqa: E731
    for k, name in (("position_rms_mm", "position"), ("orientation_rms_deg", "orientation")):
        rep["uncalibrated_over_calibrated_" + name] = ratio(rep.get("uncalibrated_" + k), rep.get(k))
        rep["calibrated_over_perfect_" + name] = ratio(rep.get(k), rep.get("perfect_" + k))
    return rep


def cfg_perfect(cfg):
    """The firmware configuration of the perfect run: the same, without a calibration file (a
    perfect bench is the nominal one)."""
    if getattr(getattr(cfg, "calibration", None), "calibration_file", ""):
        return cfg.with_(calibration={"calibration_file": ""})
    return cfg


_PARAMETERS = {"coils": "thesis source as built: tilts <= 2 deg, gains 1 + N(0, 2 %), centres N(0, 1 mm)",
               "magnetometer": "soft iron I + N(0, 2 %) diag + N(0, 1 %) cross, hard iron N(0, 3 uT), "
                               "offset N(0, 10 nT/K) over a warm-up, cubic non-linearity <= 0.5 % at range",
               "bench_unit": BENCH_UNIT}


def _register(name: str, summary: str, description: str, config, sensor: SensorSpec, params: dict,
              motion: dict) -> None:
    sc = register(Scenario(name=name, summary=summary, description=description, duration_s=60.0,
                           build_world=imperfect_world_builder(True, motion=motion), firmware_config=config,
                           sensor=ImperfectSensorSpec(**dataclasses.asdict(sensor)),
                           parameters={**_PARAMETERS, **params}, report_extra=imperfection_figures))
    PERFECT[name] = dataclasses.replace(sc, name=name + "(perfect)", sensor=sensor, report_extra=None,
                                        build_world=imperfect_world_builder(False, motion=motion))


_register("imperfect-bench",
          "slow hand motion at 15-25 cm on an imperfect source and magnetometer, calibrated or not",
          "A slow hand motion (15-25 cm, peak 2 cm/s and 4 deg/s, turns up to 0.6 rad) with the source coils, "
          "the magnetometer and its board as built (hil.imperfections, unit BENCH_UNIT), magnetic only; the "
          "report adds the same run without calibration (uncalibrated_*) and on the perfect bench (perfect_*).",
          FirmwareConfig, SensorSpec(),
          {"motion": "hand-moved, 15-25 cm, az +-30 deg, el +-25 deg, turns +-0.6 rad, peak 2 cm/s and 4 deg/s"},
          SLOW_MOTION)
_register("imperfect-fusion",
          "hand motion at 15-40 cm on the imperfect bench with an imperfect IMU, fused, calibrated or not",
          "The roetenberg-fusion hand motion (15-40 cm, peak 12 cm/s and 30 deg/s) on imperfect-bench's "
          "hardware, with an MTx-class IMU beside the magnetometer (120 Hz) whose accelerometer and "
          "gyroscope have scale and misalignment errors, g-sensitivity and bias instability, mounted "
          "misaligned to the magnetometer; 21-state magnetic-inertial fusion (roetenberg-fusion's filter).",
          _fusion_config(), SensorSpec(imu_rate_hz=120.0),
          {"imu": "scale N(0, 1 %), cross-axis N(0, 0.5 %), g-sensitivity N(0, 0.1 deg/s/g), Gauss-Markov bias "
                  "instability 0.01 deg/s / 2e-3 m/s^2 (100 s), mag-to-IMU N(0, 0.5 deg) per axis",
           "motion": "hand-moved, 15-40 cm, peak 12 cm/s and 30 deg/s"}, MOTION)
