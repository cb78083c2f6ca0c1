"""An inertial and magnetic sensor module fixed to the source (thesis
``002_cd7f1fdb7fc67471.txt`` sec 5.3 and 6.2.3: "One MTx sensor module was
attached to the assembly of the three coils to measure its orientation").

:class:`SourceImuNode` streams ``IMU_SAMPLE`` (or ``IMU_DELTA`` pairs when
``ImuSpec.delta_rate_hz`` is set; specific force and angular
rate of the source, sensor frame = source frame) and ``MAG_PACKED`` (the
field at the module: earth field plus the coils' field, which saturates the
magnetometer during every pulse, a few centimetres from the windings; the
magnetometer is flipped every ``MagSpec.flip_every`` samples and keeps the
residual offset ``s o`` of :class:`hil.nodes.MagSpec`). The
firmware uses them for the source orientation ``Phi`` and the source
acceleration of ``a_net = a_sensor - a_source`` (eq 6.8).

The bench's source is fixed in the world and level (``hil.world``) unless
the world gives it a trajectory (``World.source_trajectory``, the body-worn
scenarios, ``hil.body``): fixed, the module measures gravity, the earth field
and its own noise and offsets; moving, it measures the specific force
``R_s^T (a - g)`` at its own position on the source and the source's rate
(``World.source_module_kinematics``) and the earth field turned into the
source frame (``World.earth_source_frame``); the
sensor models are those of :class:`hil.nodes.ImuSpec` and
:class:`hil.nodes.MagSpec` (seeded white noise, seeded offsets with random
walk, 16-bit quantisation, clipping at the parts' full scales: a clipped
IMU axis goes out as +-``IMU_CLIP_COUNTS``, a clipped field with the
saturated stamp bit), and the node takes part in time synchronisation
like every other node (:class:`hil.nodes.Node`).
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.protocol import MSG
from coiltrack.protocol.schema import MAG_LSB_T, ROLE_SENSOR, STAMP_FLIP, STAMP_LSB_US, \
    STAMP_SATURATED, pack_stamp

from .imu_delta import DeltaIntegrator
from .nodes import ImuSpec, MagSpec, Node, send_imu

ImuSample = MSG["IMU_SAMPLE"]
MagSample = MSG["MAG_SAMPLE"]
MagPacked = MSG["MAG_PACKED"]

#: default node id of the source module (below the sensor range 16.., above driver 2)
NODE_SOURCE_IMU = 8


class SourceImuNode(Node):
    """IMU + magnetometer module on the (fixed) source.

    Parameters
    ----------
    node_id : int
    world : hil.world.World
    imu : ImuSpec
    mag : MagSpec
    position : array_like (3,)
        Module position in the source frame, m (default 6 cm below the coil
        centre: inside the coils' near field).
    seed : int
    clock : hil.clock.NodeClock, optional
    """
    role = ROLE_SENSOR

    def __init__(self, node_id: int, world, imu: ImuSpec | None = None, mag: MagSpec | None = None,
                 position=(0.0, 0.0, -0.06), seed: int = 0, clock=None, faults=None):
        super().__init__(clock, faults, seed)
        self.node_id = node_id
        self.world = world
        self.imu = imu or ImuSpec(rate_hz=120.0)
        self.mag = mag or MagSpec()
        self.position = np.asarray(position, dtype=float).reshape(3)
        self.rng = np.random.default_rng(seed)
        self.acc_bias = self.rng.normal(0.0, self.imu.acc_bias_sigma, 3)
        self.gyro_bias = self.rng.normal(0.0, self.imu.gyro_bias_sigma, 3)
        self.mag_offset = self.rng.normal(0.0, self.mag.offset_t, 3)
        self.flip_state = 1
        self._unit = None                 # coil fields per ampere at the module
        self._schedule(0)
        self.delta = (DeltaIntegrator(max(1, int(round(self.imu.rate_hz / self.imu.delta_rate_hz))),
                                      self._imu_period * 1e-6) if self.imu.delta_rate_hz else None)
        self.imu_deltas = 0
        self.imu_samples = 0
        self.mag_samples = 0
        self.saturations = 0
        self.imu_saturated = 0            # IMU samples with an axis clipped at its full scale

    def _schedule(self, t0: int) -> None:
        self._imu_period = 1e6 / self.imu.rate_hz / self.clock.rate
        self._mag_period = 1e6 / self.mag.rate_hz / self.clock.rate
        self._imu_base = t0 + float(self.rng.uniform(0.0, self._imu_period))
        self._mag_base = t0 + float(self.rng.uniform(0.0, self._mag_period))
        self._imu_k = 0
        self._mag_k = 0

    def on_power_on(self, now_us: int) -> None:
        self._schedule(now_us)

    def _imu_t(self, k: int) -> int:
        return int(round(self._imu_base + k * self._imu_period))

    def _mag_t(self, k: int) -> int:
        return int(round(self._mag_base + k * self._mag_period))

    def step(self, now_us: int, send) -> None:
        if not self.sync.synced:
            while self._imu_t(self._imu_k) <= now_us:
                self._imu_k += 1
            while self._mag_t(self._mag_k) <= now_us:
                self._mag_k += 1
            return
        # samples taken before the node had the master's time are not sent (as SensorNode.step)
        while self._imu_t(self._imu_k) < self.synced_since_us:
            self._imu_k += 1
        while self._mag_t(self._mag_k) < self.synced_since_us:
            self._mag_k += 1
        while self._imu_t(self._imu_k) <= now_us:
            self._imu_sample(self._imu_t(self._imu_k), send)
            self._imu_k += 1
        while self._mag_t(self._mag_k) <= now_us:
            self._mag_sample(self._mag_t(self._mag_k), send)
            self._mag_k += 1

    def _imu_sample(self, t: int, send) -> None:
        imu = self.imu
        dt = self._imu_period * 1e-6
        self.acc_bias += self.rng.normal(0.0, imu.acc_bias_rw * math.sqrt(dt), 3)
        self.gyro_bias += self.rng.normal(0.0, imu.gyro_bias_rw * math.sqrt(dt), 3)
        if self.world.source_moving:
            # the module moves with the source: specific force R_s^T (a - g), rate in the source frame
            a, Rs, wb = self.world.source_module_kinematics(self.position, t)
            f = Rs[0].T @ (a[0] - np.array([0.0, 0.0, -imu.gravity])) + self.acc_bias \
                + self.rng.normal(0.0, imu.acc_sigma, 3)
            w = wb[0] + self.gyro_bias + self.rng.normal(0.0, imu.gyro_sigma, 3)
        else:
            # fixed, level source: specific force -g = (0, 0, +g), no rotation
            f = np.array([0.0, 0.0, imu.gravity]) + self.acc_bias + self.rng.normal(0.0, imu.acc_sigma, 3)
            w = self.gyro_bias + self.rng.normal(0.0, imu.gyro_sigma, 3)
        self.imu_samples += 1
        send_imu(self, imu, self._imu_k, t, f, w, send)

    def _mag_sample(self, t: int, send) -> None:
        m = self.mag
        if self._unit is None:
            self._unit = self.world.unit_fields(self.position)          # (ncoils, 3), T/A
        # set/reset flipping every flip_every samples: the residual offset follows the flip state
        if m.flip_every and self._mag_k % m.flip_every == 0:
            self.flip_state = -self.flip_state
        I = self.world.coil_currents(t)
        B = (self.world.earth_source_frame(t) + I @ self._unit + self.flip_state * self.mag_offset
             + self.rng.normal(0.0, m.noise_t, 3))
        full = min(m.range_t, 32767 * MAG_LSB_T)       # the part's range or the field's (as SensorNode)
        sat = bool(np.any(~(np.abs(B) <= full)))
        if sat:
            self.saturations += 1
        lim = full / MAG_LSB_T
        counts = np.clip(np.round(B / MAG_LSB_T), -lim, lim)
        self.mag_samples += 1
        stamp = max(0, self.master(t) + STAMP_LSB_US // 2) // STAMP_LSB_US * STAMP_LSB_US
        send(self, MagPacked(self.node_id, int(counts[0]), int(counts[1]), int(counts[2]),
                             pack_stamp(stamp) | (STAMP_FLIP if self.flip_state > 0 else 0)
                             | (STAMP_SATURATED if sat else 0)))
