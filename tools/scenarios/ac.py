"""Scenarios of AC excitation (issue 12): ``raab-ac`` and ``ac-vs-dc-metal``.

Raab et al. 1979 (``004_86267342cd7488ce.txt``) excite the source with AC and
demodulate synchronously; here the three thesis coils run at their own
frequencies (frequency division, 215 / 315 / 465 Hz, 1.5 A amplitude), the
sensor is the MMC5983MA at 1 kHz (``hil/magnetometers.py``: 1.2 mG rms,
0.5 ms averaging), one magnetic pose per 9 ms hop from 18 ms blocks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from coiltrack.firmware.config import FirmwareConfig

from coiltrack.tools.scenarios.base import Family, _hil, Scenario, SensorSpec

SCENARIOS = Family()        # this family's scenarios (listed in scenarios/__init__.py)
register = SCENARIOS.add


#: MMC5983MA at BW = 11, 1 kHz: 1.2 mG rms per axis (data sheet; hil/magnetometers.py)
MMC_NOISE_T = 1.2e-7
MMC_RATE_HZ = 1000.0
MMC_INTEGRATION_US = 500


@dataclass(frozen=True)
class ACSensorSpec(SensorSpec):
    """The fast magnetometer of AC excitation; the bench is built of the AC nodes (``hil.ac_nodes``)."""
    rate_hz: float = MMC_RATE_HZ
    noise_t: float = MMC_NOISE_T
    flip_every: int = 0
    excitation: str = "ac"

    def node_kinds(self):
        """The bench's nodes (``hil.bench.assemble(kinds=...)``): the AC driver and the fast magnetometer."""
        from coiltrack.hil.ac_nodes import ACNodeKinds
        from coiltrack.hil.magnetometers import FastMagProfile

        return ACNodeKinds(FastMagProfile.mmc5983ma(0b11, self.rate_hz))

    def amplitude_sigma(self, cfg):
        """Per-element standard deviation of the signal matrix (T, (n,)) for the CRLB of the report."""
        if cfg.ac.excitation != "ac":
            return None
        from coiltrack.hil.ac_nodes import ac_amplitude_sigma

        return ac_amplitude_sigma(cfg.ac.ac_freqs_hz, self.rate_hz, cfg.ac.ac_window_us * 1e-6, self.noise_t,
                                  MMC_INTEGRATION_US * 1e-6)


def ac_config(fusion: bool = True, **kw) -> FirmwareConfig:
    """AC frequency division with the MMC5983MA; with ``fusion`` an IMU at 1 kHz and the ch. 6 filter."""
    base = dict(excitation="ac", mag_rate_hz=MMC_RATE_HZ, mag_sigma_t=MMC_NOISE_T,
                mag_integration_us=MMC_INTEGRATION_US, fusion=fusion)
    if fusion:
        # MTx-class IMU at 1 kHz: the densities of the thesis set-up (2e-3 m/s^2/sqrt(Hz), 0.05 deg/s/sqrt(Hz))
        base.update(imu_rate_hz=1000.0, imu_acc_sigma=2e-3 * math.sqrt(500.0),
                    imu_gyro_sigma=8.7e-4 * math.sqrt(500.0), fusion_replay_capacity=1024,
                    fusion_history_capacity=1024, replay_budget_steps=16, imu_timeout_us=20_000)
    base.update(kw)
    return FirmwareConfig().with_keys(**base)


def _raab_world(seed: int, duration_s: float):
    World, motion, physics = _hil()
    return World(physics.thesis_source(),
                 motion.HandMovedBench(seed=seed, duration_s=duration_s, r_min=0.15, r_max=0.60, v_max=0.12,
                                       w_max_deg=30.0))


_AC_PARAMETERS = {"coils": "3 orthogonal, 50 turns, r=5.5 cm (thesis source), 1.5 A amplitude",
                  "frequencies_hz": [215.0, 315.0, 465.0], "block_ms": 18, "hop_ms": 9,
                  "magnetometer": "MMC5983MA, 1 kHz, 1.2 mG rms, 0.5 ms averaging", "imu_rate_hz": 1000}

register(Scenario(
    name="raab-ac",
    summary="AC frequency division, fast magnetometer, hand-moved 15-60 cm, IMU fusion at 1 kHz",
    description="AC excitation (Raab 1979): the three coils at 215, 315 and 465 Hz all the time, a 1 kHz "
                "MMC5983MA demodulated synchronously in 18 ms blocks every 9 ms (111 magnetic poses/s), "
                "an IMU at 1 kHz fused by the thesis ch. 6 filter (fused poses at 1 kHz); hand-moved 15-60 cm.",
    duration_s=60.0,
    build_world=_raab_world,
    firmware_config=ac_config,
    sensor=ACSensorSpec(imu_rate_hz=1000.0),
    parameters=_AC_PARAMETERS,
))


#: the aluminium plate of ac-vs-dc-metal, 8 cm behind the source (the plane x = -0.08 m), as the
#: lumped eddy loop of its image: a conducting plane answers a dipole with its mirror image
#: (normal component equal, tangential ones reversed, so that the normal field vanishes on the
#: plane), here at 16 cm behind the source, a finite plate's fraction PLATE_COUPLING of it, with one
#: relaxation time (a 3 mm aluminium plate of 20-30 cm: a few ms)
PLATE_PLANE_X = -0.08
PLATE_POSITION = (2 * PLATE_PLANE_X, 0.0, 0.0)
PLATE_COUPLING = 0.3
PLATE_TAU_S = 2e-3


def _metal_world(seed: int, duration_s: float):
    World, motion, physics = _hil()
    import numpy as np

    from coiltrack.hil.world import EddyObject

    # EddyConductor's moment is -coupling @ m_c: the image keeps m_x (normal) and reverses m_y, m_z
    kappa = PLATE_COUPLING * np.diag([-1.0, 1.0, 1.0])
    plate = EddyObject(physics.EddyConductor(np.array(PLATE_POSITION), coupling=kappa, tau_s=PLATE_TAU_S))
    return World(physics.thesis_source(),
                 motion.HandMovedBench(seed=seed, duration_s=duration_s, r_min=0.15, r_max=0.45, v_max=0.08,
                                       w_max_deg=20.0),
                 objects=[plate])


def _metal_dc_config() -> FirmwareConfig:
    # pulsed DC, magnetic only, the same magnetometer; settle and fall cover L/R and the plate's
    # eddy field (tau 2 ms: e^-7, 1e-3 of it) after each edge; pulses 120 ms apart to keep the
    # trailing baseline clear of the next pulse
    return FirmwareConfig().with_(
        pulse={"mag_rate_hz": MMC_RATE_HZ, "mag_sigma_t": MMC_NOISE_T, "settle_us": 14_000, "fall_us": 14_000},
        timing={"spacing_us": 120_000},
        fusion={"fusion": False})


register(Scenario(
    name="ac-vs-dc-metal",
    summary="an aluminium plate behind the source: AC frequency division against pulsed DC, same run",
    description="An aluminium plate 8 cm behind the source (its image, a lumped eddy loop of coupling 0.3 and "
                "tau 2 ms, 16 cm behind); "
                "the sensor hand-moved 15-45 cm. AC frequency division (magnetic only, this run) and the "
                "pulsed-DC X, Y, Z cycle (fixed_*) on the same trajectory and seed, the same magnetometer; "
                "the AC blocks' quadrature is the distortion indicator.",
    duration_s=60.0,
    build_world=_metal_world,
    firmware_config=lambda: ac_config(fusion=False),
    sensor=ACSensorSpec(),
    parameters={**_AC_PARAMETERS, "imu_rate_hz": 0,
                "plate": f"plane x = {PLATE_PLANE_X} m: image eddy loop at {PLATE_POSITION} m, coupling "
                         f"{PLATE_COUPLING} (normal kept, tangential reversed), tau {PLATE_TAU_S} s",
                "dc": "60 ms pulses 120 ms apart, 600 ms cycle, settle and fall 14 ms"},
    fixed_config=_metal_dc_config,
))


def _clean_world(seed: int, duration_s: float):
    World, motion, physics = _hil()
    return World(physics.thesis_source(),
                 motion.HandMovedBench(seed=seed, duration_s=duration_s, r_min=0.15, r_max=0.45, v_max=0.08,
                                       w_max_deg=20.0))


register(Scenario(
    name="ac-vs-dc-clean",
    summary="ac-vs-dc-metal without the plate: what AC and pulsed DC reach on that trajectory",
    description="The ac-vs-dc-metal trajectory, seed and magnetometer without the aluminium plate: AC frequency "
                "division (this run) and the pulsed-DC cycle (fixed_*), the reference the plate's effect is "
                "measured against.",
    duration_s=60.0,
    build_world=_clean_world,
    firmware_config=lambda: ac_config(fusion=False),
    sensor=ACSensorSpec(),
    parameters={**_AC_PARAMETERS, "imu_rate_hz": 0, "dc": "60 ms pulses 120 ms apart, 600 ms cycle, settle and fall 14 ms"},
    fixed_config=_metal_dc_config,
))
