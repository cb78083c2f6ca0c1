"""The emulated world: source coils and their currents, the earth field,
disturbers and the sensor's motion. Fields come from magpylib through
``hil.physics``; nothing here borrows the firmware's field code.

Frames: the source frame is the world frame (the source is fixed); a
trajectory gives the sensor pose ``(p, R)`` with ``R`` mapping sensor-frame
vectors to the source frame.
"""
from __future__ import annotations

import numpy as np

from . import physics

EARTH_FIELD_T = physics.EARTH_FIELD_T


class World:
    def __init__(self, coils, trajectory, earth_field_t=EARTH_FIELD_T, disturbers=(),
                 supply_v: float = 6.0):
        self.coils = list(coils)
        self.source = physics.Source(self.coils)
        self.trajectory = trajectory
        self.earth = np.asarray(earth_field_t, dtype=float)
        self.disturbers = list(disturbers)
        self.currents = [physics.CoilCurrent(resistance=c.resistance, inductance=c.inductance)
                         for c in self.coils]
        self.supply_v = supply_v
        self._unit_cache_t = None
        self._unit_cache = None

    def pose(self, t_us: int):
        return self.trajectory.pose(t_us)

    def coil_currents(self, t_us: int) -> np.ndarray:
        return np.array([c.current_at(t_us) for c in self.currents])

    def unit_fields(self, p) -> np.ndarray:
        """(ncoils, 3) field per ampere of each coil at source-frame point p."""
        p = np.asarray(p, dtype=float).reshape(1, 3)
        return self.source.unit_fields(p)[:, 0, :]

    def field_source_frame(self, t_us: int, p=None) -> np.ndarray:
        """Total field (coils + earth + disturbers) at the sensor, source frame."""
        if p is None:
            p, _ = self.pose(t_us)
        I = self.coil_currents(t_us)
        B = self.earth.copy()
        if np.any(I != 0.0):
            B += I @ self.unit_fields(p)
        for d in self.disturbers:
            B += d.field_at(t_us, p, self)
        return B

    def field_sensor_frame(self, t_us: int) -> np.ndarray:
        p, R = self.pose(t_us)
        return R.T @ self.field_source_frame(t_us, p)
