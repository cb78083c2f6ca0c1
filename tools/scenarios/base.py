"""What a scenario is: :class:`Scenario` (a world, its sensors and a firmware configuration),
the :class:`Family` each scenario module collects its own in, and the :class:`Experiment` of a
scenario whose runs are measurement-level experiments instead of bench runs.

Nothing here knows a scenario by name: the families are listed, and their scenarios and
experiments joined into the registry, in ``scenarios/__init__.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from coiltrack.firmware.config import FirmwareConfig, qualified


def _hil():
    """The world's modules (magpylib underneath), imported when a world is built, so that
    the scenarios can be listed without the bench extra."""
    from coiltrack.hil import motion, physics
    from coiltrack.hil.world import World

    return World, motion, physics


@dataclass(frozen=True)
class SensorSpec:
    rate_hz: float = 120.0
    noise_t: float = 0.5e-7
    imu_rate_hz: float = 0.0          # IMU beside the magnetometer (0: none)
    flip_every: int = 8               # autonomous set/reset every N samples until the firmware commands flips
    clock_drift_ppm: float = 50.0     # node clocks drift uniformly within +-this (seeded)
    source_imu_id: int = 0            # an IMU + magnetometer module on the source (hil.imu; 0: none)
    source_acc_offset: bool = True    # the source module's accelerometer has its seeded offset and random walk
    imu_delta_rate_hz: float = 0.0    # the IMU sent as IMU_DELTA pairs at this rate (0: IMU_SAMPLE at imu_rate_hz)


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    duration_s: float
    build_world: Callable[[int, float], World]
    firmware_config: Callable[[], FirmwareConfig]
    sensor: SensorSpec = SensorSpec()
    reference: dict = field(default_factory=dict)
    parameters: dict = field(default_factory=dict)
    #: a fixed X, Y, Z cycle configuration the report also runs on the same trajectory and seed
    #: (its figures appear as ``fixed_*``), for scenarios about the actuation policy
    fixed_config: Callable[[], FirmwareConfig] | None = None
    #: one line for ``coiltrack bench --help`` (default: the description)
    summary: str = ""
    #: several sensors moving apart: ``(world, seed, duration_s, sensor_ids) -> {id: World.view}``
    sensor_worlds: Callable | None = None
    #: extra report figures, ``(bench, report, cfg) -> dict`` (e.g. ``scenarios.raab.tracking_figures``)
    report_extra: Callable | None = None


class Family(list):
    """The scenarios of one family module, in the order it defines them (``scenarios/__init__.py``
    joins every family's into the registry)."""

    def add(self, s: Scenario) -> Scenario:
        self.append(s)
        return s


@dataclass(frozen=True)
class Experiment:
    """A scenario whose runs are a measurement-level experiment instead of bench runs (its
    family module lists it in its ``EXPERIMENTS``, joined into the registry's).

    ``run(scenario, seed, duration_s, overrides) -> figures``; ``check(scenario, overrides)``
    raises a ConfigError naming a bad key; ``tables(scenario, runs) -> dict`` gives extra keys
    of the sweep's JSON document, ``format(tables) -> str`` their printed form;
    ``headline``: the figures of the printed summary; ``plot(doc, path)`` replaces the default plot."""
    run: Callable
    check: Callable
    tables: Callable
    format: Callable
    headline: tuple = ()
    plot: Callable | None = None


def override_dict(overrides) -> dict:
    """((key, value), ...) -> the dict :func:`config_from_dict` takes: ``section.key`` nests
    as {section: {key: value}}; a plain key is put in its own section
    (``pulse_us`` -> ``timing.pulse_us``), an unknown one is left for
    :func:`config_from_dict` to refuse by name."""
    d: dict = {}
    for key, value in overrides:
        section, dot, name = qualified(key).rpartition(".")
        (d.setdefault(section, {}) if dot else d)[name] = value
    return d
