"""Extracted pulse amplitudes are statistically consistent with the truth.

The sensor visits a grid of static poses (distance 10-60 cm, random
orientations), jumping between poses in the quiet part of each cycle. For
every pulse window the firmware reports the amplitude (sensor frame) and its
variance; the truth is the steady-state field change that the coil, at the
current the driver really produced, makes at the true pose
(``World.steady_amplitude``: magpylib finite-winding coil plus the response of
a ferromagnetic object in the world). The normalised errors
``z = (amp - truth) / sqrt(var)`` must have zero mean and unit variance:

* mean within 4 standard errors of 0;
* variance within +-0.15 of 1 (540 values: 60 poses x 3 coils x 3 axes; the
  sample variance has a standard error of sqrt(2/540) = 0.061, a little more
  because windows that share a baseline are correlated: +-0.15 is about 2.5
  of those; over seeds 1-5 the variance was 0.98-1.08).

A run with the magnetometer noise doubled (firmware still assuming the
nominal noise) gives variance ~4, showing the test has power.
"""
from __future__ import annotations

import numpy as np
import pytest

from coiltrack.firmware.config import FirmwareConfig
from coiltrack.hil import motion
from coiltrack.hil import physics as ph
from coiltrack.hil.world import FerroObject, World
from coiltrack.protocol import MSG
from coiltrack.tools.scenarios.base import Scenario, SensorSpec

CYCLE_US, FIRST_US, SWITCH_US = 600_000, 200_000, 380_000


class PiecewiseStatic(motion.Trajectory):
    """Static poses, one per firmware cycle, switching ``SWITCH_US`` after each cycle start
    (after the burst's trailing baseline, before the flip and the next burst)."""

    def __init__(self, poses):
        self.P = np.array([p.p for p in poses])
        self.R = np.array([p.R for p in poses])

    def index(self, t_s):
        k = np.floor((t_s * 1e6 - FIRST_US - SWITCH_US) / CYCLE_US).astype(int) + 1
        return np.clip(k, 0, len(self.P) - 1)

    def _eval(self, t):
        i = self.index(t)
        z = np.zeros((t.shape[0], 3))
        return self.P[i], z, z.copy(), self.R[i], z.copy()


def _scenario(noise_t=0.5e-7, poses=None):
    poses = poses or motion.static_grid((0.10, 0.2, 0.35, 0.6), n_directions=15, max_angle_deg=50.0, seed=11)
    ferro = FerroObject(ph.FerroSphere(np.array([0.12, -0.3, 0.1]), radius=0.012, mu_r=400.0))

    def world(seed, duration_s):
        return World(ph.thesis_source(), PiecewiseStatic(poses), objects=[ferro])

    return Scenario(name="amplitude-grid", description="static grid", duration_s=20.0, build_world=world,
                    firmware_config=FirmwareConfig, sensor=SensorSpec(noise_t=noise_t))


def _z_scores(run_bench, noise_t, cycles=60):
    captured = []

    def capture(fw, bench):
        orig = fw.tx.pulse_window          # every PULSE_WINDOW leaves through it (either core)
        channels = {ch.node: ch for ch in fw.channels}

        def pulse_window(*fields):
            msg = MSG["PULSE_WINDOW"](*fields)
            tr = channels[msg.node]
            captured.append((msg, tr.S[:, msg.coil].copy(), tr.var[:, msg.coil].copy()))
            orig(*fields)

        fw.tx.pulse_window = pulse_window

    sc = _scenario(noise_t)
    run = run_bench(scenario_obj=sc, seed=2, duration_s=0.2 + 0.6 * cycles, setup=capture)
    b = run.bench
    ex = {(e["coil"], e["pulse_id"]): e for e in b.driver.executed}
    z = []
    for msg, amp, var in captured:
        if msg.flags or msg.n_used == 0:
            continue
        e = ex[(msg.coil, msg.pulse_id)]
        t0 = b.sensor.true_time_of(msg.first_us)
        t1 = b.sensor.true_time_of(msg.last_us)
        truth = b.world.steady_amplitude(msg.coil, (t0 + t1) // 2, e["current_a"])
        z.append((amp - truth) / np.sqrt(var))
    return np.array(z).ravel(), len(captured), run


def test_normalised_amplitude_errors_have_unit_variance(bench_runner):
    z, n_windows, run = _z_scores(bench_runner, 0.5e-7)
    assert n_windows >= 3 * 59
    assert z.size >= 0.95 * 3 * n_windows            # almost no window flagged
    se = 1.0 / np.sqrt(z.size)
    assert abs(z.mean()) < 4 * se, z.mean()
    assert abs(z.var() - 1.0) < 0.15, z.var()
    # heavy tails would show here: nothing beyond 5 sigma
    assert np.max(np.abs(z)) < 5.0
    assert run.rep["pulse_window_violations"] == 0


def test_the_consistency_check_has_power(bench_runner):
    """Sensor noise twice what the firmware assumes: variance about 4."""
    z, _, _ = _z_scores(bench_runner, 1.0e-7, cycles=20)
    assert 3.0 < z.var() < 5.5
