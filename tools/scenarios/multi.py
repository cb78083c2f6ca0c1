"""Many sensors around one source: ``multi16``.

Sixteen sensor nodes (ids 16..31, the whole sensor address range of the 11-bit CAN identifiers)
each moved by hand on a trajectory of its own (thesis sec 5.3 motion model, 20-40 cm), all
measuring the same pulses of the thesis source. Flock of Birds ran 30 receivers on one source;
this is the firmware's many-sensor case: one burst serves every sensor, and the tracker solves
them one after the other within its per-tick budget.

A sensor's trajectory, clock and noise depend on its node id only (``hil.bench.assemble``), so
``--config`` with ``[link] sensor_ids = [N]`` runs sensor N alone on the very same trajectory and
samples: the per-sensor figures of ``multi16`` against those runs show what sharing costs.
"""
from __future__ import annotations

from coiltrack.firmware.config import FirmwareConfig

from .base import Family, _hil, Scenario, SensorSpec

SCENARIOS = Family()        # this family's scenarios (listed in scenarios/__init__.py)
register = SCENARIOS.add


SENSORS = tuple(range(16, 32))


def _trajectory(seed: int, duration_s: float, sid: int):
    _, motion, _ = _hil()
    return motion.HandMovedBench(seed=seed * 1000 + sid, duration_s=duration_s, r_min=0.20, r_max=0.40,
                                 v_max=0.10, w_max_deg=30.0)


def _world(seed: int, duration_s: float):
    World, _, physics = _hil()
    return World(physics.thesis_source(), _trajectory(seed, duration_s, SENSORS[0]))


def _views(world, seed: int, duration_s: float, sensor_ids):
    return {sid: world.view(_trajectory(seed, duration_s, sid)) for sid in sensor_ids}


def _config() -> FirmwareConfig:
    return FirmwareConfig().with_(link={"sensor_ids": SENSORS})


register(Scenario(
    name="multi16",
    summary="16 sensors, each on its own hand-moved path 20-40 cm from one source, magnetic only",
    description="Sixteen sensor nodes (16..31) around the thesis source, each moved by hand on its own "
                "trajectory 20-40 cm away; one X, Y, Z burst serves them all; magnetic only. "
                "Per-sensor figures in 'sensors'.",
    duration_s=30.0,
    build_world=_world,
    firmware_config=_config,
    sensor=SensorSpec(),
    sensor_worlds=_views,
    parameters={"sensors": len(SENSORS), "node_ids": "16..31", "motion": "hand-moved, 20-40 cm, peak 10 cm/s, "
                "30 deg/s, one seeded trajectory per node"},
))
