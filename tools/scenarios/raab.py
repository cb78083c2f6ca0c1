"""Scenarios of Raab's iterative tracker (Raab et al. 1979,
``seeds/004_86267342cd7488ce.txt``) on the pulsed-DC bench; the AC
excitation reuses them. Each reports, besides the usual figures,
``acquisition_updates`` and ``hemisphere_flips`` (:func:`tracking_figures`).

* ``raab-acquire``: Fig. 8, the tracker started far from the truth: a sensor
  at rest 30 cm from the thesis source, the tracker's start 90 deg away in
  direction, 90 deg turned and 50 % too far (``[pose] raab_start_*``), one
  update per X, Y, Z burst (``raab_iterations = raab_acquire_iterations =
  1``: the paper's tracker, one update per excitation pattern).
* ``helix-hemisphere``: Gietler's helix (``seeds/003_93f59c2e1c5b6c59.txt``
  eq 33, ``hil.motion.Helix``: its angular rate, climb, roll and yaw rate)
  at 0.3 m radius around the source's z axis, from 30 cm below to 30 cm
  above it: the sensor crosses the plane x = 0 of the configured hemisphere
  (+x) four times in 60 s (t = 7.9, 23.6, 39.3, 55.0 s), 30-42 cm from the
  source.

Compare the solvers on the same runs with ``coiltrack sweep --scenario NAME
--seeds 1-8 --set pose.pose_solver=lm,raab`` (README, *Raab's iterative
tracker*).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.config import FirmwareConfig
from coiltrack.tools.scenarios.base import Family, Scenario

SCENARIOS = Family()        # this family's scenarios (listed in scenarios/__init__.py)
register = SCENARIOS.add


__all__ = ["tracking_figures", "ACQUIRE_TRUTH_P", "ACQUIRE_START_P"]

#: raab-acquire: the sensor at 30 cm, 45 deg from +x in the xy plane; the start 90 deg away
#: (-45 deg) at 45 cm (50 % too far); both on the +x side of the hemisphere plane
ACQUIRE_TRUTH_P = (0.3 * math.cos(math.pi / 4), 0.3 * math.sin(math.pi / 4), 0.0)
ACQUIRE_START_P = (0.45 * math.cos(math.pi / 4), -0.45 * math.sin(math.pi / 4), 0.0)
#: the sensor's orientation: 90 deg about (1, 1, 1) / sqrt 3 from the start's (zero angles)
ACQUIRE_TRUTH_ROTVEC = tuple(math.pi / 2 / math.sqrt(3.0) for _ in range(3))


def _hil():
    from coiltrack.hil import motion, physics
    from coiltrack.hil.world import World

    return World, motion, physics


def tracking_figures(bench, rep: dict, cfg) -> dict:
    """``acquisition_updates``: magnetic updates until the estimate stays
    within three standard deviations of the truth (position error within 3x
    the Cramer-Rao bound's RMS radius and orientation error within 3x its
    orientation RMS, the bound from the bench's own magpylib physics,
    ``hil.crlb``), ``None`` if it never does; ``hemisphere_flips``: how often
    the magnetic estimate went over to the mirror solution (closer to
    ``-p_true`` than to ``p_true``, Raab footnote 3), and ``mirrored_poses``;
    position RMS, its bound and orientation RMS of the updates after the
    acquisition (``after_acquisition_*``)."""
    from coiltrack.firmware.rotation import matrix_from_quat
    from coiltrack.hil.crlb import crlb
    from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID

    rec = bench.recorder
    n_used = [w.n_used for _, w in rec.windows if w.n_used]
    n_base = [w.n_base for _, w in rec.windows if w.n_base]
    nu = float(np.median(n_used)) if n_used else 1.0
    nb = float(np.median(n_base)) if n_base else 1.0
    sigma = bench.scenario.sensor.noise_t * math.sqrt(1.0 / nu + 1.0 / nb)
    currents = np.array([c.current for c in cfg.source.coils])
    inside, flips, mirrored, was = [], 0, 0, False
    errs = []                       # (position error, its bound's RMS radius, orientation error) per update
    for rp in rec.poses:
        m = rp["msg"]
        if m.status & POSE_FUSED:
            continue
        p_true, R_true = rp["true_p"], rp["true_R"]
        if not m.status & POSE_VALID:
            inside.append(False)
            errs.append(None)
            continue
        p = np.array([m.px, m.py, m.pz])
        R = matrix_from_quat(np.array([m.qw, m.qx, m.qy, m.qz]))
        C = crlb(bench.world, p_true, R_true, currents, sigma)
        sp = math.sqrt(max(float(np.trace(C[:3, :3])), 0.0))
        so = math.sqrt(max(float(np.trace(C[3:, 3:])), 0.0))
        c = (float(np.trace(R.T @ R_true)) - 1.0) * 0.5
        ang = math.acos(max(-1.0, min(1.0, c)))
        inside.append(float(np.linalg.norm(p - p_true)) <= 3 * sp and ang <= 3 * so)
        errs.append((float(np.linalg.norm(p - p_true)), sp, ang))
        mir = float(np.linalg.norm(p + p_true)) < float(np.linalg.norm(p - p_true))
        mirrored += mir
        flips += mir and not was
        was = mir
    first = None
    for k in range(len(inside)):
        if all(inside[k:]):
            first = k + 1
            break
    after = [e for e in errs[first:] if e is not None] if first is not None else []
    rms = lambda v: round(math.sqrt(sum(x * x for x in v) / len(v)), 3) if v else None  # noqa: E731
    return {"acquisition_updates": first, "hemisphere_flips": flips, "mirrored_poses": mirrored,
            "pose_solver": cfg.pose.pose_solver,
            "after_acquisition_position_rms_mm": rms([e[0] * 1e3 for e in after]),
            "after_acquisition_crlb_position_rms_mm": rms([e[1] * 1e3 for e in after]),
            "after_acquisition_orientation_rms_deg": rms([math.degrees(e[2]) for e in after])}


# ------------------------------------------------------------------ raab-acquire
def _acquire_world(seed: int, duration_s: float):
    World, motion, physics = _hil()
    R = motion.rotvec_to_matrix(np.array(ACQUIRE_TRUTH_ROTVEC))
    return World(physics.thesis_source(), motion.StaticPose(np.array(ACQUIRE_TRUTH_P), R))


def _acquire_config(**kw) -> FirmwareConfig:
    base = dict(pose_solver="raab", raab_iterations=1, raab_acquire_iterations=1, fusion=False,
                raab_start_position=ACQUIRE_START_P, raab_start_euler_deg=(0.0, 0.0, 0.0))
    base.update(kw)
    return FirmwareConfig().with_keys(**base)


register(Scenario(
    name="raab-acquire",
    summary="Raab's tracker started 90 deg and 50 % range off, one update per burst (Raab Fig. 8)",
    description="Raab 1979 Fig. 8: a sensor at rest 30 cm from the thesis source; Raab's tracker starts 90 deg "
                "away in direction, 90 deg turned and 50 % too far, one update per X, Y, Z burst; reports "
                "acquisition_updates (updates until the estimate stays within 3 sigma of the truth).",
    duration_s=30.0,
    build_world=_acquire_world,
    firmware_config=_acquire_config,
    report_extra=tracking_figures,
    reference={"source": "Raab et al. 1979, Fig. 8: tracking within a few iterations after a large error"},
    parameters={"truth": "0.3 m at 45 deg azimuth, turned 90 deg about (1,1,1)",
                "start": "0.45 m at -45 deg azimuth (90 deg, +50 %), zero orientation angles",
                "updates": "one per 600 ms burst", "report": "acquisition_updates, hemisphere_flips"},
))


# ------------------------------------------------------------------ helix-hemisphere
def _helix_world(seed: int, duration_s: float):
    World, motion, physics = _hil()
    return World(physics.thesis_source(),
                 motion.Helix(radius=0.3, duration_s=max(duration_s, 1.0), center=(0.0, 0.0, -0.3)))


def _helix_config(**kw) -> FirmwareConfig:
    base = dict(pose_solver="raab", fusion=False)
    base.update(kw)
    return FirmwareConfig().with_keys(**base)


register(Scenario(
    name="helix-hemisphere",
    summary="Gietler's helix around the source, crossing the hemisphere plane x = 0 four times (Raab's tracker)",
    description="Gietler 2019 eq 33 helix (0.2 rad/s, 1 cm/s climb, roll 0.0831 rad, yaw 0.02 rad/s) at 0.3 m "
                "radius around the source's z axis, z from -0.3 to +0.3 m: the sensor crosses the configured "
                "hemisphere's plane (x = 0) four times in 60 s; Raab's tracker must follow by continuity "
                "(report hemisphere_flips, 0).",
    duration_s=60.0,
    build_world=_helix_world,
    firmware_config=_helix_config,
    report_extra=tracking_figures,
    reference={"source": "Gietler et al. 2019 eq 33 (helix); Raab et al. 1979 footnote 3 (180 deg ambiguity)"},
    parameters={"helix": "radius 0.3 m (paper 0.6), omega 0.2 rad/s, climb 0.01 m/s, centre (0, 0, -0.3) m",
                "hemisphere": "+x configured; continuity after acquisition", "range_cm": "30-42",
                "report": "acquisition_updates, hemisphere_flips"},
))
