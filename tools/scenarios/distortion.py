"""Static metal in the room: the ``steel-table`` scenario.

The roetenberg-bench set-up (thesis ``seeds/002_cd7f1fdb7fc67471.txt`` sec 5.3: the hand-moved
sensor around the fixed three-coil source, magnetic only) over a steel table: a
1.6 m x 1.2 m x 5 mm mild-steel sheet (mu_r 200), the source standing on it with +x up, its centre
25-27 cm above the sheet, seeded placement (``hil.room.SteelTable``). The table's static distortion
of the coil fields grows from ~0.1 % of the coil field near the source to ~10 % at 80 cm (the coil
field falls as r^-3, the table's much slower). The sensor stays within 15-60 cm: beyond that the
magnetic-only solution is noise-limited (its Cramer-Rao bound passes 100 mm at 70-80 cm), and two
runs that differ only by the table's field drift tens of millimetres apart whatever the map does,
so the table's own error cannot be measured there.

The report (:func:`distortion_figures`) adds, on the same trajectory and seed:

* ``uncorrected_position_rms_mm`` (this run, no correction: the scenario's firmware
  configuration), ``corrected_position_rms_mm`` (the firmware with the map fitted by the survey,
  ``coiltrack calibrate --method survey``: ``tools.calibration.survey``), ``clean_position_rms_mm`` (the same
  run without the table), with the orientation figures and ``distortion_correction_ratio``
  (uncorrected over corrected);
* the survey's residual and size (``survey``).
"""
from __future__ import annotations

import dataclasses

from coiltrack.firmware.config import FirmwareConfig
from coiltrack.tools.calibration import survey
from coiltrack.tools.scenarios.base import Family, _hil, Scenario

SCENARIOS = Family()        # this family's scenarios (listed in scenarios/__init__.py)
register = SCENARIOS.add


__all__ = ["steel_table_world", "clean_world", "distortion_figures", "STEEL_TABLE"]


def _trajectory(seed: int, duration_s: float):
    _, motion, _ = _hil()
    # the roetenberg-bench hand motion (tools.scenarios.thesis._roetenberg_world) within 15-60 cm
    return motion.HandMovedBench(seed=seed, duration_s=duration_s, r_min=0.15, r_max=0.60, v_max=0.12,
                                 w_max_deg=30.0)


#: the earth field in the source frame of a source standing with +x up (T): 45 uT down, 20 uT
#: horizontal (the default world's field, turned with the source)
EARTH_X_UP_T = (-45e-6, 0.0, 20e-6)


def steel_table_world(seed: int, duration_s: float):
    """The roetenberg-bench world over the seeded steel table."""
    World, _, physics = _hil()
    from coiltrack.hil.room import SteelTable

    return World(physics.thesis_source(), _trajectory(seed, duration_s), earth_field_t=EARTH_X_UP_T,
                 objects=[SteelTable(seed=seed)])


def clean_world(seed: int, duration_s: float):
    """The same trajectory and source without the table."""
    World, _, physics = _hil()
    return World(physics.thesis_source(), _trajectory(seed, duration_s), earth_field_t=EARTH_X_UP_T)


def distortion_figures(bench, rep: dict, cfg) -> dict:
    """The corrected and clean runs beside this one (module docstring)."""
    return survey.correction_report(bench, rep, cfg, CLEAN)


STEEL_TABLE = register(Scenario(
    name="steel-table",
    summary="roetenberg-bench over a steel table: uncorrected, survey-corrected and clean runs",
    description="The roetenberg-bench set-up (thesis sec 5.3, sensor at 15-60 cm) over a 1.6 m x 1.2 m x 5 mm "
                "steel table, the source standing on it 25 cm above the sheet (seeded placement, hil.room): "
                "the static distortion without "
                "correction, with the survey's residual-field map (coiltrack calibrate --method survey) "
                "and without the table, on the same trajectory and seed.",
    duration_s=60.0,
    build_world=steel_table_world,
    firmware_config=FirmwareConfig,
    reference={"source": "Roetenberg 2006, Table 5.1, bench test (no metal)",
               "position_rms_mm": 7.6, "orientation_rms_deg": 5.9},
    parameters={"table": "mild steel sheet 1.6 x 1.2 m, 5 mm, mu_r 200, the source's centre 25-27 cm above it",
                "cells": "40 x 30 cuboids, polarisation solved self-consistently (magpylib)",
                "survey": "jig grid over the working volume, equivalent-dipole map per coil"},
    report_extra=distortion_figures,
))

#: the clean variant used by the report (not listed: no table, no extra runs)
CLEAN = dataclasses.replace(STEEL_TABLE, name="steel-table-clean", build_world=clean_world, report_extra=None)
