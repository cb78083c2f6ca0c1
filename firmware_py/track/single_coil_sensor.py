"""Per-sensor tracking state of the single-coil mode (``track.single_coil_tracker``).

One error-state EKF per sensor and IMU (``estimate.single_coil.SchepersEKF``,
Schepers & Veltink 2010, ``seeds/000_e46ec0e8bf7ea271.txt`` sec. 2.1), its NIS
monitor and the bookkeeping of its updates. The tracker owns these records;
the actuation policy and the acquisition read them. All arrays are allocated
here, at start-up.
"""
from __future__ import annotations

import numpy as np

from coiltrack.firmware.actuate.accuracy import FixedCycleReference
from coiltrack.firmware.estimate.single_coil_update import CoilMeasurement
from coiltrack.firmware.measure.imu import ImuRing

__all__ = ["SensorTrack"]


class SensorTrack:
    """One tracked sensor: its channel, filter, monitor and the state of its updates."""

    def __init__(self, index: int, channel, cfg, ekf, monitor):
        self.index = index
        self.track = channel
        self.node = channel.node
        self.ekf = ekf
        self.monitor = monitor
        self.mon_t = 0                             # when the monitor last heard an update
        self.acc = np.zeros(3)
        self.gyr = np.zeros(3)
        self.imu = ImuRing(cfg.imu.imu_ring_capacity)
        self.meas = CoilMeasurement()              # the pulse being applied (a value refilled per update)
        self.last_update_us = 0
        self.last_imu_us: int | None = None
        self.imu_samples = 0
        self.gated_in_row = 0
        self.bits = 0                  # sticky POSE_* bits of the last magnetic update
        self.distorted = False
        self.updates = 0
        self.gated = 0
        self.ref: FixedCycleReference | None = None     # accuracy_target = "fixed"
        self.ref_start_us = 0

    def stamp(self) -> int:
        """Changes whenever an IMU sample or an update has moved the filter."""
        return self.imu_samples + self.updates + self.gated
