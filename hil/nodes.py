"""Emulated nodes: the coil driver and the sensor node, plus the recorder
that plays the host and keeps ground truth for the report.

Each node speaks only protocol messages; the emulator (``hil.emulator``)
routes decoded messages to them and frames what they send.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol import MSG, PROTOCOL_VERSION, SCHEMA_HASH
from protocol.schema import (COIL_FAULT_DUTY_LIMIT, COIL_FAULT_LATE, COIL_FAULT_OPEN_CIRCUIT,
                             COIL_FAULT_OVER_CURRENT, COIL_FAULT_REFUSED, CURRENT_LSB_A,
                             MAG_LSB_T, ROLE_COIL_DRIVER, ROLE_SENSOR, STATE_RUNNING)

from .clock import NodeClock

Heartbeat = MSG["HEARTBEAT"]
CoilStatus = MSG["COIL_STATUS"]
MagSample = MSG["MAG_SAMPLE"]


class Node:
    node_id = 0
    role = 0

    def __init__(self):
        self.next_heartbeat_us = 0
        self.boot_us = 0

    def on_message(self, msg, now_us: int, send) -> None:
        pass

    def step(self, now_us: int, send) -> None:
        if now_us >= self.next_heartbeat_us:
            send(self, Heartbeat(self.node_id, self.role, STATE_RUNNING, PROTOCOL_VERSION,
                                 SCHEMA_HASH, now_us - self.boot_us, 0))
            self.next_heartbeat_us = now_us + 1_000_000


@dataclass
class DriverLimits:
    """Limits a coil driver enforces whatever it is told."""
    max_current_a: float = 2.0
    max_pulse_us: int = 200_000
    max_duty: float = 0.5          # fraction of time a coil may be on, over duty_window_us
    duty_window_us: int = 1_200_000
    min_lead_us: int = 200         # a command must arrive at least this early


class CoilDriverNode(Node):
    """Executes scheduled pulse commands on the world's coil currents.

    After each pulse it reports the measured steady-state current and the
    actual edges (on the master clock) in COIL_STATUS. It refuses commands
    that break its limits or arrive late, and reports the refusal.
    """
    role = ROLE_COIL_DRIVER

    def __init__(self, node_id: int, world, limits: DriverLimits | None = None, seed: int = 0,
                 current_noise_a: float = 1e-3):
        super().__init__()
        self.node_id = node_id
        self.world = world
        self.limits = limits or DriverLimits()
        self.rng = np.random.default_rng(seed)
        self.current_noise_a = current_noise_a
        self.pending: list[tuple[int, int, int, int, float]] = []   # (end_us, coil, pulse_id, start_us, amps)
        self.history: list[tuple[int, int, int]] = [[] for _ in world.coils]  # per coil (start, end)
        self.open_circuit = [False] * len(world.coils)
        self.sag = 1.0                  # supply sag factor on the achieved current
        self.executed: list[dict] = []  # ground truth of every pulse
        self.refused = 0

    def _duty(self, coil: int, start: int, dur: int) -> float:
        w0 = start + dur - self.limits.duty_window_us
        on = dur + sum(min(e, start + dur) - max(s, w0) for s, e in self.history[coil] if e > w0)
        return on / self.limits.duty_window_us

    def on_message(self, msg, now_us: int, send) -> None:
        if msg.ID != MSG["COIL_PULSE_CMD"].ID:
            return
        c, amps = msg.coil, msg.current_ma * CURRENT_LSB_A
        fault = 0
        if c >= len(self.world.coils):
            fault = COIL_FAULT_REFUSED
        elif abs(amps) > self.limits.max_current_a + 1e-9:
            fault = COIL_FAULT_REFUSED | COIL_FAULT_OVER_CURRENT
        elif msg.duration_us > self.limits.max_pulse_us or msg.duration_us <= 0:
            fault = COIL_FAULT_REFUSED
        elif msg.start_us < now_us + self.limits.min_lead_us:
            fault = COIL_FAULT_REFUSED | COIL_FAULT_LATE
        elif self._duty(c, msg.start_us, msg.duration_us) > self.limits.max_duty:
            fault = COIL_FAULT_REFUSED | COIL_FAULT_DUTY_LIMIT
        if fault:
            self.refused += 1
            send(self, CoilStatus(min(c, 255), msg.pulse_id, 0, msg.start_us, msg.start_us, fault))
            return
        achieved = 0.0 if self.open_circuit[c] else amps * self.sag
        self.world.currents[c].schedule(msg.start_us, msg.duration_us, achieved)
        self.history[c].append((msg.start_us, msg.start_us + msg.duration_us))
        if len(self.history[c]) > 64:
            del self.history[c][:32]
        self.pending.append((msg.start_us + msg.duration_us, c, msg.pulse_id, msg.start_us, achieved))
        self.pending.sort()

    def step(self, now_us: int, send) -> None:
        super().step(now_us, send)
        while self.pending and self.pending[0][0] <= now_us:
            end, c, pid, start, amps = self.pending.pop(0)
            measured = self.world.currents[c].current_at(end - 1) + self.rng.normal(0.0, self.current_noise_a)
            faults = COIL_FAULT_OPEN_CIRCUIT if self.open_circuit[c] else 0
            send(self, CoilStatus(c, pid, int(round(measured / CURRENT_LSB_A)), start, end, faults))
            tau_us = self.world.currents[c].tau_us
            self.executed.append({"coil": c, "pulse_id": pid, "start_us": start, "end_us": end,
                                  "current_a": amps, "tau_us": tau_us})


class SensorNode(Node):
    """A 3-axis magnetometer (optionally an IMU beside it) with its own clock.

    Samples the true field at the node's sample instants, adds white noise
    (``noise_t`` rms per axis), quantises to 16 bits of ``MAG_LSB_T`` and
    clips at the range (reporting saturation).
    """
    role = ROLE_SENSOR

    def __init__(self, node_id: int, world, rate_hz: float = 120.0, noise_t: float = 0.5e-7,
                 range_t: float = 32767 * MAG_LSB_T, seed: int = 0, clock: NodeClock | None = None):
        super().__init__()
        self.node_id = node_id
        self.world = world
        self.period_us = int(round(1e6 / rate_hz))
        self.noise_t = noise_t
        self.range_t = min(range_t, 32767 * MAG_LSB_T)
        self.rng = np.random.default_rng(seed)
        self.clock = clock or NodeClock()
        # first sample at a seeded phase within one period
        self.next_sample_us = int(self.rng.integers(0, self.period_us))
        self.flip = 1
        self.samples = 0
        self.saturations = 0

    def step(self, now_us: int, send) -> None:
        super().step(now_us, send)
        while self.next_sample_us <= now_us:
            t = self.next_sample_us
            self.next_sample_us += self.period_us
            B = self.world.field_sensor_frame(t) + self.rng.normal(0.0, self.noise_t, 3)
            sat = bool(np.any(np.abs(B) > self.range_t))
            if sat:
                self.saturations += 1
            counts = np.clip(np.round(B / MAG_LSB_T), -32768, 32767).astype(int)
            self.samples += 1
            send(self, MagSample(self.node_id, self.clock.local(t), int(counts[0]), int(counts[1]),
                                 int(counts[2]), (self.flip & 1) | (2 if sat else 0)))


class Recorder:
    """Plays the host: keeps every POSE, PULSE_WINDOW and FAULT_EVENT with
    the true sensor pose at its time stamp, for the report."""

    def __init__(self, world):
        self.world = world
        self.poses: list[dict] = []
        self.windows: list = []
        self.events: list = []
        self.heartbeats: list = []

    def on_message(self, msg, now_us: int) -> None:
        name = msg.NAME
        if name == "POSE":
            p, R = self.world.pose(msg.t_us)
            self.poses.append({"msg": msg, "rx_us": now_us, "true_p": np.array(p), "true_R": np.array(R)})
        elif name == "PULSE_WINDOW":
            self.windows.append((now_us, msg))
        elif name == "FAULT_EVENT":
            self.events.append((now_us, msg))
        elif name == "HEARTBEAT":
            self.heartbeats.append((now_us, msg))
