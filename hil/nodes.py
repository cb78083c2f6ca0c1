"""Emulated nodes: the coil driver and the sensor node (magnetometer with an
IMU beside it), plus the recorder that plays the host and keeps ground truth
for the report.

Each node speaks only protocol messages; the emulator (``hil.emulator``)
routes decoded messages to :meth:`Node.handle` and calls :meth:`Node.tick`
every step. Each node has its own clock (:class:`hil.clock.NodeClock`:
offset, drift, steps) and learns the master (firmware) time from the
``TIME_SYNC`` broadcasts (:class:`hil.clock.NodeSync`); it answers each with
``TIME_SYNC_REPLY``. Times passed to the nodes (``now_us``) are *true* time;
times on the wire are the node's estimate of master time. A sensor streams
samples only once it is synchronised (its heartbeat says ``STATE_READY``
until then, ``STATE_RUNNING`` after).

Ground truth kept for the report and the HIL tests: every pulse the driver
executed with its true edges (``CoilDriverNode.executed``), every sample
with its true time and its time stamp (``SensorNode.stamps``/``true_times``),
every set/reset flip (``SensorNode.flip_log``).
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from coiltrack.protocol import MSG, PROTOCOL_VERSION, SCHEMA_HASH
from coiltrack.protocol.schema import (ACC_LSB, IMU_CLIP_COUNTS, POSE_FUSED,
                             COIL_FAULT_CURRENT_SAG, COIL_FAULT_DUTY_LIMIT, COIL_FAULT_LATE,
                             COIL_FAULT_OPEN_CIRCUIT, COIL_FAULT_OVER_CURRENT, COIL_FAULT_OVER_TEMPERATURE,
                             COIL_FAULT_REFUSED, COIL_FAULT_SUPPLY_LOW,
                             CURRENT_LSB_A, GYR_LSB, MAG_LSB_T, ROLE_COIL_DRIVER, ROLE_SENSOR, STAMP_DVEL,
                             STAMP_FLIP, STAMP_LSB_US, STAMP_SATURATED, STATE_READY, STATE_RUNNING, pack_stamp)

from .clock import NodeClock, NodeSync
from .imu_delta import DeltaIntegrator

Heartbeat = MSG["HEARTBEAT"]
CoilStatus = MSG["COIL_STATUS"]
MagSample = MSG["MAG_SAMPLE"]
ImuSample = MSG["IMU_SAMPLE"]
MagPacked = MSG["MAG_PACKED"]
ImuDelta = MSG["IMU_DELTA"]
TimeSyncReply = MSG["TIME_SYNC_REPLY"]

HEARTBEAT_US = 1_000_000
_I32 = (1 << 31) - 1


def _i32(v: int) -> int:
    return max(-_I32 - 1, min(_I32, int(v)))


def _i16(v: float) -> int:
    return max(-32768, min(32767, int(round(v))))


def send_delta(node, integ: DeltaIntegrator, k: int, t: int, w, f, send, sat_w: bool = False,
               sat_f: bool = False) -> None:
    """Add IMU sample ``k`` (true time ``t``, rate ``w`` rad/s, specific force ``f`` m/s^2, as
    the parts output them: clipped, ``sat_w`` / ``sat_f`` when they clipped) to the node's delta
    interval; a complete interval goes out as an IMU_DELTA pair stamped with the interval's end
    on the master clock, each frame with the saturated bit when its sensor clipped in the
    interval (or the interval's delta was beyond a frame's range). A gap in the samples starts
    a fresh interval."""
    if getattr(integ, "last_k", None) is not None and k != integ.last_k + 1:
        integ.reset()
    integ.last_k = k
    out = integ.add(w, f, sat_w, sat_f)
    if out is None:
        return
    a, v = out
    st = pack_stamp(max(0, node.master(t + int(round(integ.dt * 5e5)))))
    send(node, ImuDelta(node.node_id, int(a[0]), int(a[1]), int(a[2]),
                        st | (STAMP_SATURATED if integ.sat_a else 0)))
    send(node, ImuDelta(node.node_id, int(v[0]), int(v[1]), int(v[2]),
                        st | STAMP_DVEL | (STAMP_SATURATED if integ.sat_v else 0)))
    node.imu_deltas += 1


def send_imu(node, imu: ImuSpec, k: int, t: int, f, w, send) -> None:
    """IMU sample ``k`` of ``node`` (true time ``t``; specific force ``f`` m/s^2 and rate ``w``
    rad/s as the parts see them) through the parts' full scales (:meth:`ImuSpec.clip`; a
    saturated sample is counted in ``node.imu_saturated``) to the wire: into the node's delta
    interval, or as an IMU_SAMPLE stamped on the master clock (a sample the node cannot stamp,
    its master time before the master's zero, is not sent)."""
    if node.delta is not None:
        f, w, sat_f, sat_w = imu.clip(f, w)
        if sat_f or sat_w:
            node.imu_saturated += 1
        send_delta(node, node.delta, k, t, w, f, send, sat_w, sat_f)
        return
    tm = node.master(t)
    counts, sat_f, sat_w = imu.sample_counts(f, w)
    if sat_f or sat_w:
        node.imu_saturated += 1
    if tm < 0:
        return
    send(node, ImuSample(node.node_id, tm, *counts))


class Node:
    """Common node behaviour: clock, time sync, heartbeat, power (off windows and reboot).

    Subclasses implement :meth:`on_message` and :meth:`step`.
    """
    node_id = 0
    role = 0

    def __init__(self, clock: NodeClock | None = None, faults=None, seed: int = 0):
        self.clock = clock or NodeClock()
        self.sync = NodeSync()
        self.faults = faults
        self.online = True
        self.off_windows: list[tuple[int, int]] = []
        self.boot_true_us = 0
        self.next_heartbeat_local: int | None = None
        self.reboots = 0
        self.sync_rx = 0
        self.synced_since_us = 0
        self._power_rng = np.random.default_rng(seed + 7919)

    # --- time
    def master(self, true_us: int) -> int:
        """This node's estimate of master time at true time ``true_us``."""
        return self.sync.to_master(self.clock.local(true_us))

    def true_of_master(self, master_us: int, after_us: int) -> int:
        """True time at which this node's timer for master time ``master_us`` fires."""
        return self.clock.true(self.sync.to_local(master_us), after_us)

    # --- power
    def add_off_window(self, t0_us: int, t1_us: int) -> None:
        self.off_windows.append((int(t0_us), int(t1_us)))

    def _update_power(self, now_us: int) -> None:
        off = any(t0 <= now_us < t1 for t0, t1 in self.off_windows)
        if self.online and off:
            self.online = False
            self.on_power_off(now_us)
        elif not self.online and not off:
            self.online = True
            self.reboots += 1
            self.clock.reboot(now_us, int(self._power_rng.integers(1_000, 50_000)))
            self.sync.reset()
            self.boot_true_us = now_us
            self.next_heartbeat_local = None
            self.on_power_on(now_us)

    def on_power_off(self, now_us: int) -> None:
        pass

    def on_power_on(self, now_us: int) -> None:
        pass

    # --- messages
    def handle(self, msg, now_us: int, send) -> None:
        if not self.online:
            return
        if msg.NAME == "TIME_SYNC":
            loc = self.clock.local(now_us)
            if not self.sync.synced:
                self.synced_since_us = now_us
            self.sync.update(loc, msg.master_time_us)
            self.sync_rx += 1
            send(self, TimeSyncReply(self.node_id, msg.sync_seq, max(0, loc), _i32(self.sync.offset_us),
                                     _i32(self.sync.drift_ppb)))
            return
        self.on_message(msg, now_us, send)

    def on_message(self, msg, now_us: int, send) -> None:
        pass

    def tick(self, now_us: int, send) -> None:
        self._update_power(now_us)
        if not self.online:
            return
        loc = self.clock.local(now_us)
        nh = self.next_heartbeat_local
        if nh is None or loc >= nh or nh - loc > 2 * HEARTBEAT_US:
            state = STATE_RUNNING if self.sync.synced else STATE_READY
            send(self, Heartbeat(self.node_id, self.role, state, PROTOCOL_VERSION, SCHEMA_HASH, 0))
            self.next_heartbeat_local = loc + HEARTBEAT_US
        self.step(now_us, send)

    def step(self, now_us: int, send) -> None:
        pass


# ---------------------------------------------------------------------------
# Coil driver
# ---------------------------------------------------------------------------


@dataclass
class DriverLimits:
    """Limits a coil driver enforces whatever it is told."""
    max_current_a: float = 2.0
    max_pulse_us: int = 200_000
    max_duty: float = 0.5          # fraction of time a coil may be on, over duty_window_us
    duty_window_us: int = 1_200_000
    min_lead_us: int = 200         # a command must arrive at least this early (master time)
    sag_fraction: float = 0.9      # measured below this fraction of the target: COIL_FAULT_CURRENT_SAG
    open_fraction: float = 0.2     # measured below this fraction: COIL_FAULT_OPEN_CIRCUIT
    supply_low_fraction: float = 0.85  # supply below this fraction of nominal at a pulse: COIL_FAULT_SUPPLY_LOW
    trip_us: int = 200             # over-current trip time of the short-circuit protection
    short_resistance_factor: float = 0.05
    max_temp_c: float = 90.0       # winding temperature above which pulses are refused
    ambient_c: float = 25.0
    thermal_r_k_per_w: float = 20.0    # winding to ambient
    thermal_tau_s: float = 120.0       # winding thermal time constant (C_th = tau / R_th)


#: copper's temperature coefficient of resistance at 20 C (1/K; annealed copper, IEC 60028: 0.00393)
COPPER_ALPHA_PER_K = 0.00393


@dataclass
class DriverAccuracy:
    """How far a coil driver's regulated current is from its set point, and the winding's heating.

    A linear current regulator senses the coil current on a shunt with a current-sense
    amplifier and holds the sensed value at the set point. Its errors (seeded draws):

    * ``gain_error_max``: a static gain error per coil, uniform in +-0.3 %: the sense
      amplifier's gain error (TI INA240 data sheet, SBOS662: +-0.20 % max) plus a 0.1 %
      shunt. The driver measures its own current through the same amplifier, so this
      part is invisible in ``COIL_STATUS``: the reported current holds it, the true one
      does not (it is a source gain error the firmware cannot see).
    * ``pulse_gain_sigma`` (0.1 %) and ``pulse_offset_sigma_a`` (1 mA): the set point's
      error per pulse (reference and DAC noise, the loop's residual: a 12-bit DAC over
      2 A is 0.5 mA a step); the reported current shows it.
    * ripple: the residual of a ``pwm_hz`` (20 kHz) bridge through a second-order output
      filter at ``filter_hz`` (2 kHz): the bridge's peak-to-peak ripple on the coil
      ``V D (1 - D) / (L f_pwm)`` (duty ``D = I R / V``) attenuated by
      ``(filter_hz / pwm_hz)^2``, as a sine of half that amplitude at ``pwm_hz`` with a
      random phase per pulse (0.05 % p-p of 1.5 A for the thesis coil at 6 V).
    * the winding's resistance rises with its temperature, ``R(T) = R_a (1 + alpha (T - 20))
      / (1 + alpha (T_a - 20))`` (copper, ``alpha = 0.393 %/K``, ``R_a`` the coil's
      resistance at the ambient ``T_a``); the winding heats with ``I^2 R(T)`` through the
      driver's first-order thermal model (:class:`DriverLimits` ``thermal_r_k_per_w``,
      ``thermal_tau_s``), so a pulse's L/R is ``L / R(T)`` and the regulation holds the
      current until ``I R(T)`` reaches the supply: beyond, the current is ``V / R(T)``.

    :meth:`ideal` switches all of it off (the current equals its set point, constant R).
    """
    gain_error_max: float = 3e-3
    pulse_gain_sigma: float = 1e-3
    pulse_offset_sigma_a: float = 1e-3
    pwm_hz: float = 20_000.0
    filter_hz: float = 2_000.0
    ripple: bool = True
    alpha_per_k: float = COPPER_ALPHA_PER_K

    @classmethod
    def ideal(cls) -> "DriverAccuracy":
        return cls(0.0, 0.0, 0.0, ripple=False, alpha_per_k=0.0)

    def resistance(self, r_ambient: float, temp_c: float, ambient_c: float) -> float:
        """Winding resistance (ohm) at ``temp_c`` of a coil of ``r_ambient`` at ``ambient_c``."""
        a = self.alpha_per_k
        return r_ambient * (1.0 + a * (temp_c - 20.0)) / (1.0 + a * (ambient_c - 20.0))

    def ripple_pp_a(self, current_a: float, r_ohm: float, l_h: float, v: float) -> float:
        """Peak-to-peak ripple (A) of the filtered bridge output at ``current_a``."""
        if not self.ripple or v <= 0.0 or l_h <= 0.0:
            return 0.0
        d = min(1.0, abs(current_a) * r_ohm / v)
        return v * d * (1.0 - d) / (l_h * self.pwm_hz) * (self.filter_hz / self.pwm_hz) ** 2


class CoilDriverNode(Node):
    """Executes scheduled pulse commands on the world's coil currents.

    A ``COIL_PULSE_CMD`` gives the start on the master clock; the driver fires
    when its own synchronised clock reaches it (so the true edges carry the
    driver's sync error). The current follows L/R towards the target, limited
    by the supply (``V/R``, with sag). After each pulse the driver reports the
    current it measured near the end and the edges (its estimate of master
    time) in ``COIL_STATUS``, with fault bits: open circuit (measured ~0),
    over-current (short: tripped after ``trip_us``), current sag (measured
    below ``sag_fraction`` of the target). A first-order thermal model of
    each winding (I^2 R heating, ``thermal_r_k_per_w``, ``thermal_tau_s``)
    makes it refuse pulses (over-temperature) above ``max_temp_c``; ``accuracy``
    (:class:`DriverAccuracy`) sets the regulation error, ripple and the resistance's
    rise with the winding temperature. It refuses commands that break its
    limits, arrive late, duplicate a pulse id, or come before it is
    synchronised, and reports the refusal. Pulses are committed to the world
    ``commit_horizon_us`` before they start.
    """
    role = ROLE_COIL_DRIVER

    def __init__(self, node_id: int, world, limits: DriverLimits | None = None, seed: int = 0,
                 current_noise_a: float = 1e-3, clock: NodeClock | None = None, faults=None,
                 commit_horizon_us: int = 2_000, accuracy: DriverAccuracy | None = None):
        super().__init__(clock, faults, seed)
        self.node_id = node_id
        self.world = world
        self.limits = limits or DriverLimits()
        self.rng = np.random.default_rng(seed)
        self.accuracy = accuracy or DriverAccuracy()
        # regulation errors: their own stream, so the report noise draws stay those of the seed
        self._acc_rng = np.random.default_rng([seed, 0xC0])
        self.gain_error = [float(self._acc_rng.uniform(-1.0, 1.0)) * self.accuracy.gain_error_max
                           for _ in world.coils]
        self.current_noise_a = current_noise_a
        self.commit_horizon_us = commit_horizon_us
        n = len(world.coils)
        self.queue: list[dict] = []         # accepted, not yet committed (sorted by true start)
        self.active: list[dict] = []        # committed, waiting for the end edge
        self.history: list[list[tuple[int, int]]] = [[] for _ in range(n)]  # per coil (master start, end)
        self.recent: list[list[int]] = [[] for _ in range(n)]               # recent pulse ids per coil
        self.open_circuit = [False] * n     # static switches (tests); timed ones come from faults
        self.sag = 1.0
        self.executed: list[dict] = []      # ground truth of every pulse that ran
        self.refusals: list[dict] = []
        self.refused = 0
        self.duplicates = 0
        self.cmd_leads_us: list[int] = []   # master lead of every accepted command at arrival
        # winding temperatures (first-order thermal model, advanced pulse by pulse)
        self.temp_c = [self.limits.ambient_c] * n
        self._temp_t = [0] * n

    # --- fault state at a true time
    def _open(self, c: int, t: int) -> bool:
        return self.open_circuit[c] or (self.faults is not None and self.faults.at("open_circuit", t, c) is not None)

    def _short(self, c: int, t: int) -> bool:
        return self.faults is not None and self.faults.at("short", t, c) is not None

    def supply_v(self, t: int) -> float:
        f = self.sag
        if self.faults is not None:
            s = self.faults.at("sag", t)
            if s is not None:
                f *= s.value
        return self.world.supply_v * f

    def temperature(self, c: int, t_us: int) -> float:
        """Winding temperature of coil ``c`` at true time ``t_us`` (no pulse since the last one);
        an ``overheat`` fault holds it at the fault's temperature while it lasts (a hot spot:
        blocked cooling, a heat source nearby)."""
        lim = self.limits
        f = self.faults.at("overheat", t_us, c) if self.faults is not None else None
        if f is not None:
            return float(f.value)
        amb = lim.ambient_c
        dt = max(0, t_us - self._temp_t[c]) * 1e-6
        return amb + (self.temp_c[c] - amb) * math.exp(-dt / lim.thermal_tau_s)

    def _heat(self, c: int, t0: int, t1: int, amps: float) -> None:
        """Advance the thermal model over a pulse of ``amps`` through coil ``c`` (I^2 R heating)."""
        lim = self.limits
        T = self.temperature(c, t0)
        amb = lim.ambient_c
        # C T' = I^2 R(T) - (T - T_a)/R_th with R(T) = R_a (1 + k (T - T_a)) (copper, DriverAccuracy):
        # first order with tau' = tau / (1 - I^2 R_a k R_th) towards T_a + I^2 R_a R_th / (1 - I^2 R_a k R_th)
        r_a = self.world.coils[c].resistance
        acc = self.accuracy
        k = acc.alpha_per_k / (1.0 + acc.alpha_per_k * (amb - 20.0))
        g = amps * amps * r_a * k * lim.thermal_r_k_per_w
        if g >= 1.0:                         # thermal runaway: no steady state; heat as fast as at T
            g = 0.999
        T_inf = amb + amps * amps * r_a * lim.thermal_r_k_per_w / (1.0 - g)
        tau = lim.thermal_tau_s / (1.0 - g)
        self.temp_c[c] = T_inf + (T - T_inf) * math.exp(-(t1 - t0) * 1e-6 / tau)
        self._temp_t[c] = t1

    def resistance(self, c: int, t_us: int) -> float:
        """Winding resistance (ohm) of coil ``c`` at true time ``t_us`` (its temperature then)."""
        return self.accuracy.resistance(self.world.coils[c].resistance, self.temperature(c, t_us),
                                        self.limits.ambient_c)

    def accuracy_report(self) -> dict:
        """The regulation and thermal model of this run for the bench report: the parameters, the
        seeded static gain error of every coil, and what happened (hottest winding, largest
        resistance, pulses the supply limited, the achieved current's error against the target)."""
        acc = self.accuracy
        ran = [e for e in self.executed if "resistance_ohm" in e and e.get("target_a")]
        rel = [e["current_a"] / e["target_a"] - 1.0 for e in ran]
        return {
            "static_gain_error_max": acc.gain_error_max, "pulse_gain_sigma": acc.pulse_gain_sigma,
            "pulse_offset_sigma_a": acc.pulse_offset_sigma_a,
            "ripple": {"pwm_hz": acc.pwm_hz, "filter_hz": acc.filter_hz} if acc.ripple else None,
            "copper_alpha_per_k": acc.alpha_per_k,
            "static_gain_error": [round(g, 6) for g in self.gain_error],
            "current_error_rms": round(float(np.sqrt(np.mean(np.square(rel)))), 6) if rel else None,
            "winding_temp_max_c": round(max([self.limits.ambient_c] + [float(t) for t in self.temp_c]), 3),
            "resistance_rise_max": round(max([e["resistance_ohm"] / self.world.coils[e["coil"]].resistance - 1.0
                                              for e in ran] or [0.0]), 6),
            "pulses_voltage_limited": sum(1 for e in ran if e.get("voltage_limited")),
        }

    def _duty(self, coil: int, start: int, dur: int) -> float:
        w0 = start + dur - self.limits.duty_window_us
        on = dur + sum(min(e, start + dur) - max(s, w0) for s, e in self.history[coil] if e > w0)
        return on / self.limits.duty_window_us

    def on_message(self, msg, now_us: int, send) -> None:
        if msg.NAME != "COIL_PULSE_CMD":
            return
        c, amps = msg.coil, msg.current_ma * CURRENT_LSB_A
        if c < len(self.recent) and msg.pulse_id in self.recent[c]:
            self.duplicates += 1            # a duplicated frame: already handled
            return
        lead = msg.start_us - self.master(now_us)
        fault = 0
        if c >= len(self.world.coils):
            fault = COIL_FAULT_REFUSED
        elif not self.sync.synced:
            fault = COIL_FAULT_REFUSED
        elif abs(amps) > self.limits.max_current_a + 1e-9:
            fault = COIL_FAULT_REFUSED | COIL_FAULT_OVER_CURRENT
        elif msg.duration_us > self.limits.max_pulse_us or msg.duration_us <= 0:
            fault = COIL_FAULT_REFUSED
        elif lead < self.limits.min_lead_us:
            fault = COIL_FAULT_REFUSED | COIL_FAULT_LATE
        elif self._duty(c, msg.start_us, msg.duration_us) > self.limits.max_duty:
            fault = COIL_FAULT_REFUSED | COIL_FAULT_DUTY_LIMIT
        if c < len(self.recent):
            self.recent[c].append(msg.pulse_id)
            if len(self.recent[c]) > 32:
                del self.recent[c][:16]
        if fault:
            self.refused += 1
            self.refusals.append({"coil": c, "pulse_id": msg.pulse_id, "faults": fault, "rx_true_us": now_us,
                                  "lead_us": lead})
            send(self, CoilStatus(min(c, 255), msg.pulse_id, 0, msg.start_us, msg.start_us, fault))
            return
        self.cmd_leads_us.append(lead)
        t0 = self.true_of_master(msg.start_us, now_us)
        t1 = self.true_of_master(msg.start_us + msg.duration_us, t0)
        rec = {"coil": c, "pulse_id": msg.pulse_id, "master_start_us": msg.start_us,
               "master_end_us": msg.start_us + msg.duration_us, "target_a": amps,
               "start_us": t0, "end_us": t1, "rx_true_us": now_us, "lead_us": lead, "faults": 0}
        self.history[c].append((msg.start_us, msg.start_us + msg.duration_us))
        if len(self.history[c]) > 64:
            del self.history[c][:32]
        bisect.insort(self.queue, rec, key=lambda r: r["start_us"])

    def _commit(self, rec: dict) -> None:
        c, t0, t1 = rec["coil"], rec["start_us"], rec["end_us"]
        coil = self.world.coils[c]
        v = self.supply_v(t0)
        target = rec["target_a"]
        if self.temperature(c, t0) > self.limits.max_temp_c:
            # over-temperature protection: the pulse is not driven, the refusal reported
            rec["faults"] = COIL_FAULT_REFUSED | COIL_FAULT_OVER_TEMPERATURE
            rec["current_a"] = 0.0
            rec["tau_us"] = self.world.currents[c].tau_us
            rec["refused_hot"] = True
            self.active.append(rec)
            return
        tau_s = None                    # open or shorted: the world's own L/R
        if self._open(c, t0):
            achieved = 0.0
        elif self._short(c, t0):
            r_short = coil.resistance * self.limits.short_resistance_factor
            achieved = math.copysign(v / r_short, target)
            t1 = t0 + self.limits.trip_us
            rec["faults"] |= COIL_FAULT_OVER_CURRENT
            rec["end_us"] = t1
        else:
            # the regulation holds the sensed current (1 + gain error) I at the set point, which
            # carries this pulse's error; the supply limits the current to V / R(T)
            acc = self.accuracy
            r_t = self.resistance(c, t0)
            rec["resistance_ohm"] = r_t
            setpoint = target * (1.0 + float(self._acc_rng.normal(0.0, 1.0)) * acc.pulse_gain_sigma) \
                + (1.0 if target >= 0.0 else -1.0) * float(self._acc_rng.normal(0.0, 1.0)) * acc.pulse_offset_sigma_a
            regulated = setpoint / (1.0 + self.gain_error[c])
            achieved = math.copysign(min(abs(regulated), v / r_t), target)
            rec["voltage_limited"] = abs(regulated) > v / r_t
            tau_s = float(coil.inductance) / r_t
            rec["tau_us"] = tau_s * 1e6
            pp = acc.ripple_pp_a(achieved, r_t, float(coil.inductance), v)
            phase = float(self._acc_rng.uniform(0.0, 2.0 * math.pi))
            if pp > 0.0 and not rec["voltage_limited"]:
                # kept apart from the pulses (CoilCurrent.add_ripple): the order does not matter
                self.world.currents[c].add_ripple(t0, t1, 0.5 * pp, acc.pwm_hz, phase)
        if v < self.limits.supply_low_fraction * self.world.supply_v:
            rec["faults"] |= COIL_FAULT_SUPPLY_LOW      # the driver's under-voltage warning
        rec["current_a"] = achieved
        rec.setdefault("tau_us", self.world.currents[c].tau_us)
        self.world.currents[c].schedule(t0, t1 - t0, achieved, tau_s)
        self._heat(c, t0, t1, achieved)
        self.active.append(rec)

    def on_power_off(self, now_us: int) -> None:
        # outputs off: cut a running pulse, forget what was queued
        for rec in self.active:
            if rec["start_us"] <= now_us < rec["end_us"]:
                self.world.currents[rec["coil"]].schedule(now_us, 1, 0.0)
                rec["end_us"] = now_us
                rec["aborted"] = True
                self.executed.append(rec)
        self.active.clear()
        self.queue.clear()

    def on_power_on(self, now_us: int) -> None:
        for r in self.recent:
            r.clear()

    def step(self, now_us: int, send) -> None:
        while self.queue and self.queue[0]["start_us"] <= now_us + self.commit_horizon_us:
            self._commit(self.queue.pop(0))
        if not self.active:
            return
        done = [r for r in self.active if r["end_us"] <= now_us]
        if not done:
            return
        self.active = [r for r in self.active if r["end_us"] > now_us]
        for rec in done:
            c = rec["coil"]
            # through the same sense amplifier as the regulation: the report is (1 + g) I, the static
            # gain error g hidden in it (the set point's error per pulse and the ripple show)
            t_m = rec["end_us"] - 1
            cur = self.world.currents[c]
            measured = (1.0 + self.gain_error[c]) * (float(cur.current_at(t_m)) + cur.ripple_at(t_m)) \
                + float(self.rng.normal(0.0, self.current_noise_a))
            target = abs(rec["target_a"])
            faults = rec["faults"]
            if rec.get("refused_hot"):
                self.refused += 1
                self.refusals.append({"coil": c, "pulse_id": rec["pulse_id"], "faults": faults,
                                      "rx_true_us": rec["rx_true_us"], "lead_us": rec["lead_us"]})
                send(self, CoilStatus(c, rec["pulse_id"], 0, rec["master_start_us"], rec["master_start_us"], faults))
                continue
            if not faults & COIL_FAULT_OVER_CURRENT and target > 0.0:
                if abs(measured) < self.limits.open_fraction * target:
                    faults |= COIL_FAULT_OPEN_CIRCUIT
                elif abs(measured) < self.limits.sag_fraction * target:
                    faults |= COIL_FAULT_CURRENT_SAG
            rec["faults"] = faults
            rec["measured_a"] = measured
            ma = _i16(measured / CURRENT_LSB_A)
            # (a clock stepped back far enough puts an edge before the master's zero: reported as 0)
            rec["reported_start_us"] = max(0, self.master(rec["start_us"]))
            rec["reported_end_us"] = max(0, self.master(rec["end_us"]))
            send(self, CoilStatus(c, rec["pulse_id"], ma, rec["reported_start_us"], rec["reported_end_us"], faults))
            self.executed.append(rec)


# ---------------------------------------------------------------------------
# Sensor node: magnetometer + IMU
# ---------------------------------------------------------------------------


@dataclass
class MagSpec:
    """Magnetometer of a sensor node.

    ``noise_t`` is the rms white noise per sample and axis; the equivalent
    noise density is ``noise_t / sqrt(rate_hz / 2)`` (bandwidth = Nyquist).
    Output: 16-bit counts of ``MAG_LSB_T`` (5 nT), clipped at ``range_t``
    (the sample's saturation bit is set when any axis exceeds it).

    Set/reset flipping (thesis ``002`` sec 5.5, 7.2): a magnetoresistive
    sensor's output is ``s B + o`` with the flip state ``s = +-1``; the
    flipping electronics estimate the offset ``o`` from a set/reset pair taken
    ``flip_delta_us`` apart around each flip, which leaves (a) a residual
    offset ``s o_res`` (rms ``offset_t`` per axis) whose sign follows the flip
    state, and (b) an error ``-(B(t_f + d) - B(t_f - d)) / 2`` that persists
    until the next flip when the field changes during the flip: nothing in
    a still field, a large artefact on a pulse edge. The sensor flips by
    itself every ``flip_every`` samples (0: never) unless a ``MAG_FLIP_CMD``
    arrived within ``command_hold_us``; commanded flips happen at the
    commanded master time.
    """
    rate_hz: float = 120.0
    noise_t: float = 0.5e-7
    range_t: float = 32767 * MAG_LSB_T
    offset_t: float = 0.3e-6
    flip_every: int = 8
    flip_delta_us: int = 500
    command_hold_us: int = 3_000_000

    @property
    def noise_density(self) -> float:
        """T / sqrt(Hz)."""
        return self.noise_t / math.sqrt(self.rate_hz / 2.0)

    @classmethod
    def thesis(cls, **kw) -> "MagSpec":
        """120 Hz, 0.05 uT rms (thesis sec 5.2.1: flipped magnetoresistive sensor)."""
        return cls(**kw)

    @classmethod
    def fast(cls, rate_hz: float = 1000.0, **kw) -> "MagSpec":
        """A fast profile at the thesis sensor's noise density (``noise_t`` grows with sqrt(rate))."""
        nd = cls().noise_density
        kw.setdefault("flip_every", 64)
        return cls(rate_hz=rate_hz, noise_t=nd * math.sqrt(rate_hz / 2.0), **kw)


@dataclass
class ImuSpec:
    """Accelerometer and gyroscope beside the magnetometer (MEMS, MTx-class defaults).

    Accelerometer: specific force in the sensor frame ``R^T (a - g)``,
    ``g = (0, 0, -gravity)`` in the world (source) frame, plus bias and white
    noise. Gyroscope: angular velocity in the sensor frame plus bias and white
    noise. Biases start at a seeded value (``*_bias_sigma`` per axis) and
    random-walk (``*_bias_rw`` per sqrt(s)). Noise densities per sqrt(Hz);
    per-sample rms = density * sqrt(rate/2). Output quantised to the
    protocol's ``ACC_LSB`` / ``GYR_LSB``.

    Saturation: each axis clips at the part's full scale, ``acc_range``
    (m/s^2) and ``gyro_range`` (rad/s), or at the IMU_SAMPLE field's range
    where that is smaller (+-32767 counts: 32.767 m/s^2, 16.38 rad/s), see
    :meth:`acc_full_scale`. The defaults are the Xsens MTx data sheet's full
    scales (the module of thesis ``002`` sec 5.3, its ref [118]: acceleration
    +-50 m/s^2, rate of turn +-1200 deg/s), so with them the field clips
    first. A clipped axis goes out as +-``IMU_CLIP_COUNTS`` (the code a
    saturated MEMS output sticks at), and a delta interval with a clipped
    sample carries the saturated stamp bit (:func:`send_delta`).
    """
    rate_hz: float = 100.0
    #: IMU_DELTA pairs per second (0: IMU_SAMPLE at ``rate_hz``); ``rate_hz`` a multiple of it
    delta_rate_hz: float = 0.0
    acc_noise_density: float = 2.0e-3       # m/s^2/sqrt(Hz)
    acc_bias_sigma: float = 0.02            # m/s^2
    acc_bias_rw: float = 2.0e-4             # m/s^2/sqrt(s)
    gyro_noise_density: float = 8.7e-4      # rad/s/sqrt(Hz) (0.05 deg/s/sqrt(Hz))
    gyro_bias_sigma: float = 8.7e-3         # rad/s (0.5 deg/s)
    gyro_bias_rw: float = 1.7e-4            # rad/s/sqrt(s)
    gravity: float = 9.81
    acc_range: float = 50.0                 # m/s^2, full scale (MTx data sheet: +-50 m/s^2)
    gyro_range: float = math.radians(1200.0)  # rad/s, full scale (MTx data sheet: +-1200 deg/s)

    @property
    def acc_full_scale(self) -> float:
        """m/s^2 at which an accelerometer axis clips: the part's range or the field's, the smaller."""
        return min(float(self.acc_range), IMU_CLIP_COUNTS * ACC_LSB)

    @property
    def gyro_full_scale(self) -> float:
        """rad/s at which a gyroscope axis clips: the part's range or the field's, the smaller."""
        return min(float(self.gyro_range), IMU_CLIP_COUNTS * GYR_LSB)

    def clip(self, f, w):
        """What the parts output for specific force ``f`` (3,) m/s^2 and rate ``w`` (3,) rad/s:
        ``(f, w, acc_saturated, gyro_saturated)``, each axis clipped at its full scale (an axis
        at or beyond it is saturated)."""
        fa, ga = self.acc_full_scale, self.gyro_full_scale
        f = np.asarray(f, dtype=float)
        w = np.asarray(w, dtype=float)
        sat_f = bool(np.any(~(np.abs(f) < fa)))        # NaN counts as saturated too
        sat_w = bool(np.any(~(np.abs(w) < ga)))
        if sat_f:
            f = np.clip(np.nan_to_num(f, nan=0.0), -fa, fa)
        if sat_w:
            w = np.clip(np.nan_to_num(w, nan=0.0), -ga, ga)
        return f, w, sat_f, sat_w

    def sample_counts(self, f, w) -> tuple[list[int], bool, bool]:
        """The six IMU_SAMPLE counts (ax, ay, az, gx, gy, gz) of ``f``, ``w`` and the two
        saturation flags: a clipped axis is +-``IMU_CLIP_COUNTS``, the others rounded and kept
        inside it."""
        f, w, sat_f, sat_w = self.clip(f, w)
        fa, ga = self.acc_full_scale, self.gyro_full_scale
        out = []
        for v, lsb, fs in ((f, ACC_LSB, fa), (w, GYR_LSB, ga)):
            for x in v:
                if abs(x) >= fs:
                    out.append(IMU_CLIP_COUNTS if x > 0 else -IMU_CLIP_COUNTS)
                else:
                    out.append(max(1 - IMU_CLIP_COUNTS, min(IMU_CLIP_COUNTS - 1, int(round(x / lsb)))))
        return out, sat_f, sat_w

    @property
    def acc_sigma(self) -> float:
        return self.acc_noise_density * math.sqrt(self.rate_hz / 2.0)

    @property
    def gyro_sigma(self) -> float:
        return self.gyro_noise_density * math.sqrt(self.rate_hz / 2.0)


class _PreparedMag:
    """A magnetometer sample computed ahead (:meth:`SensorNode.prepare_sample`): sample ``k`` at
    true time ``t``, its noise and the generator's state before that draw, the world's edit mark
    and the node's flip-command count it was computed at; then its flips (artefact, log entry),
    how many pending commanded flips it consumed, the latest instant it read, the field ``B``,
    and its message, saturation and stamp."""
    __slots__ = ("k", "t", "noise", "rng_state", "mark", "flip_cmds", "flips", "n_pending", "t_max", "B",
                 "msg", "sat", "stamp")

    def __init__(self, k: int, t: int, noise, rng_state, mark: tuple, flip_cmds: int):
        self.k, self.t, self.noise, self.rng_state, self.mark, self.flip_cmds = k, t, noise, rng_state, mark, flip_cmds
        self.flips: list = []
        self.n_pending = 0
        self.t_max = t
        self.B = self.msg = None
        self.sat, self.stamp = False, 0

    def compute(self, node: "SensorNode") -> None:
        """``node``'s :meth:`SensorNode._mag_sample` for this sample, its flips applied to copies
        of the node's flip state (the node books them at the instant)."""
        m, t, d = node.mag, self.t, node.mag.flip_delta_us
        state, err, t_max = node.flip_state, node.flip_err, t
        for tf, st in node.pending_flips:
            if tf > t:
                break
            self.n_pending += 1
            if st != state:
                err, state = -0.5 * (node._sensed(tf + d) - node._sensed(tf - d)), st
                self.flips.append((err, {"true_us": tf, "state": st, "commanded": True,
                                         "artefact_t": float(np.linalg.norm(err))}))
                t_max = max(t_max, tf + d)
        if m.flip_every and self.k % m.flip_every == 0 and t >= node.cmd_until_us:
            tf = t - 2 * d
            err, state = -0.5 * (node._sensed(tf + d) - node._sensed(tf - d)), -state
            self.flips.append((err, {"true_us": tf, "state": state, "commanded": False,
                                     "artefact_t": float(np.linalg.norm(err))}))
        self.t_max = t_max
        self.B = (node._sensed(t) + state * node.offset + err + self.noise)
        self.msg, self.sat, self.stamp = node._mag_msg(t, self.B, state)


class SensorNode(Node):
    """A 3-axis magnetometer (and optionally an IMU beside it) with its own clock.

    Sample instants follow the node's oscillator (period ``1/rate`` of local
    time); each sample is stamped with the node's estimate of master time.
    See :class:`MagSpec` and :class:`ImuSpec` for the sensor models. The
    magnetometer sees the world's total field at the sample instant, in the
    sensor frame at that instant (so a rotating sensor sees the earth field
    turn during a pulse).
    """
    role = ROLE_SENSOR
    _CHUNK = 32

    def __init__(self, node_id: int, world, mag: MagSpec | None = None, imu: ImuSpec | None = None,
                 seed: int = 0, clock: NodeClock | None = None, faults=None, *, rate_hz: float | None = None,
                 noise_t: float | None = None, range_t: float | None = None):
        super().__init__(clock, faults, seed)
        mag = mag or MagSpec()
        if rate_hz is not None:
            mag.rate_hz = rate_hz
        if noise_t is not None:
            mag.noise_t = noise_t
        if range_t is not None:
            mag.range_t = range_t
        mag.range_t = min(mag.range_t, 32767 * MAG_LSB_T)
        self.mag, self.imu = mag, imu
        self.node_id = node_id
        self.world = world
        self.rng = np.random.default_rng(seed)
        self.imu_rng = np.random.default_rng(seed + 104729)
        self.offset = self.rng.normal(0.0, mag.offset_t, 3)
        self.flip_state = 1
        self.flip_err = np.zeros(3)
        self.cmd_until_us = -1
        self.pending_flips: list[tuple[int, int]] = []
        # ground truth
        self.stamps: list[int] = []
        self.true_times: list[int] = []
        self._by_stamp: dict[int, int] = {}
        self.flip_log: list[dict] = []
        self.flip_cmds = 0
        self.samples = 0
        self.saturations = 0
        self.imu_samples = 0
        self.imu_saturated = 0            # IMU samples with an axis clipped at its full scale
        #: the node's imperfections (``hil.imperfections.SensorImperfection``; None: a perfect sensor)
        self.imperfect = None
        self._prep: _PreparedMag | None = None        # the next sample, computed ahead (prepare_sample)
        self.prepared_used = self.prepared_redone = 0
        self._schedule_mag(0)
        self.delta = None
        self.imu_deltas = 0
        if imu is not None:
            self.acc_bias = self.imu_rng.normal(0.0, imu.acc_bias_sigma, 3)
            self.gyro_bias = self.imu_rng.normal(0.0, imu.gyro_bias_sigma, 3)
            self._schedule_imu(0)
            if imu.delta_rate_hz:
                self.delta = DeltaIntegrator(max(1, int(round(imu.rate_hz / imu.delta_rate_hz))),
                                             self._imu_period * 1e-6)

    # backwards-compatible attribute names
    @property
    def period_us(self) -> int:
        return int(round(1e6 / self.mag.rate_hz))

    @property
    def noise_t(self) -> float:
        return self.mag.noise_t

    @property
    def range_t(self) -> float:
        return self.mag.range_t

    @property
    def flip(self) -> int:
        return self.flip_state

    # --- schedules (true time, from the node oscillator)
    def _schedule_mag(self, t0: int) -> None:
        self._mag_period = 1e6 / self.mag.rate_hz / self.clock.rate
        self._mag_base = t0 + float(self.rng.uniform(0.0, self._mag_period))
        self._mag_k = 0
        self._mag_cached_to = -1
        self._flip_pref_to = -(1 << 62)      # the last commanded flip whose reads prefetch() computed

    def _mag_t(self, k: int) -> int:
        return int(round(self._mag_base + k * self._mag_period))

    def _schedule_imu(self, t0: int) -> None:
        self._imu_period = 1e6 / self.imu.rate_hz / self.clock.rate
        self._imu_base = t0 + float(self.imu_rng.uniform(0.0, self._imu_period))
        self._imu_k = 0
        self._imu_cache: dict[int, tuple] = {}
        self._imu_pref_k = 0                # the next IMU instant prefetch() computes

    def _imu_t(self, k: int) -> int:
        return int(round(self._imu_base + k * self._imu_period))

    def on_power_on(self, now_us: int) -> None:
        self._drop_prep()               # (its noise draw undone before the schedule's draw)
        self._schedule_mag(now_us)
        self.flip_err[:] = 0.0
        self.pending_flips.clear()
        self.cmd_until_us = -1
        if self.imu is not None:
            self._schedule_imu(now_us)

    # --- flips
    def on_message(self, msg, now_us: int, send) -> None:
        if msg.NAME != "MAG_FLIP_CMD" or msg.node != self.node_id:
            return
        self.flip_cmds += 1
        t = max(self.true_of_master(msg.at_us, now_us), now_us)
        bisect.insort(self.pending_flips, (t, 1 if msg.state else -1))
        self.cmd_until_us = now_us + self.mag.command_hold_us

    def _flip(self, tf: int, state: int, commanded: bool) -> None:
        if state == self.flip_state:
            return
        d = self.mag.flip_delta_us
        dB = self._sensed(tf + d) - self._sensed(tf - d)
        self.flip_err = -0.5 * dB
        self.flip_state = state
        self.flip_log.append({"true_us": tf, "state": state, "commanded": commanded,
                              "artefact_t": float(np.linalg.norm(self.flip_err))})

    # --- sampling
    def step(self, now_us: int, send) -> None:
        if not self.sync.synced:
            # not streaming until synchronised: let the schedules run past
            while self._mag_t(self._mag_k) <= now_us:
                self._mag_k += 1
            if self.imu is not None:
                while self._imu_t(self._imu_k) <= now_us:
                    self._imu_k += 1
            return
        while self._mag_t(self._mag_k) < self.synced_since_us:   # taken before the node had time
            self._mag_k += 1
        if self.imu is not None:
            while self._imu_t(self._imu_k) < self.synced_since_us:
                self._imu_k += 1
        while self._mag_t(self._mag_k) <= now_us:
            k = self._mag_k
            if k > self._mag_cached_to:
                self.world.precompute([self._mag_t(j) for j in range(k, k + self._CHUNK)])
                self._mag_cached_to = k + self._CHUNK - 1
            self._mag_sample(self._mag_t(k), k, send)
            self._mag_k += 1
        if self.imu is not None:
            while self._imu_t(self._imu_k) <= now_us:
                self._imu_sample(self._imu_t(self._imu_k), self._imu_k, send)
                self._imu_k += 1

    # --- physics ahead of the sampling path (wall-clock loops)
    def next_due_us(self) -> int:
        """True time (us) of this node's next magnetometer or IMU sample."""
        t = self._mag_t(self._mag_k)
        if self.imu is not None:
            t = min(t, self._imu_t(self._imu_k))
        return t

    def prefetch(self, until_us: int, max_n: int, min_n: int = 1) -> int:
        """Compute ahead, off the sampling path, what this node's coming samples up to true time
        ``until_us`` will read from the world: the pose and every coil's unit field at each
        magnetometer instant (:meth:`hil.world.World.precompute`), at the field reads of the
        set/reset flips due by then (``t -+ flip_delta_us``), and the kinematics at each IMU
        instant. At most ``max_n`` sample instants in one call, and none while fewer than
        ``min_n`` are missing (a loop that tops up in pieces of ``min_n = max_n`` pays the
        call's fixed cost once a piece); a commanded flip's reads are computed at the first call
        after the command. Returns how many sample instants were computed (0: ahead up to
        ``until_us``). A due sample then finds its physics in the caches instead of computing a
        chunk of it while it is late: same functions, evaluated earlier. The wall-clock emulator
        loop calls it between steps (``tools.bench.realtime.emulator_loop``)."""
        n = self._prefetch_mag(until_us, max_n, min_n)
        if self.imu is not None and n < max_n:
            n += self._prefetch_imu(until_us, max_n - n, min_n)
        return n

    def _prefetch_mag(self, until_us: int, max_n: int, min_n: int) -> int:
        m, d = self.mag, self.mag.flip_delta_us
        times = []
        for tf, _ in self.pending_flips:          # commanded flips: known well ahead of time
            if tf > self._flip_pref_to:
                times += [tf - d, tf + d]
                self._flip_pref_to = tf
        k = max(self._mag_cached_to + 1, self._mag_k)
        n = 0
        if self._mag_t(k + min_n - 1) <= until_us:
            while n < max_n and self._mag_t(k) <= until_us:
                t = self._mag_t(k)
                times.append(t)
                if m.flip_every and k % m.flip_every == 0:      # an autonomous flip reads t - 3d, t - d
                    times += [t - 3 * d, t - d]
                k += 1
                n += 1
        if times:
            self.world.precompute(times)
        if n:
            self._mag_cached_to = k - 1
        return n

    def _prefetch_imu(self, until_us: int, max_n: int, min_n: int) -> int:
        k = max(self._imu_pref_k, self._imu_k)
        ts = []
        if self._imu_t(k + min_n - 1) > until_us:
            return 0
        while len(ts) < max_n and self._imu_t(k) <= until_us:
            if self._imu_t(k) not in self._imu_cache:
                ts.append(self._imu_t(k))
            k += 1
        self._imu_pref_k = k
        if ts:
            K = self.world.sensor_kinematics(np.asarray(ts, dtype=np.int64))
            self._imu_cache.update({tj: (K.acceleration[i], K.R[i], K.angular_velocity[i]) for i, tj in enumerate(ts)})
        return len(ts)

    def _mag_sample(self, t: int, k: int, send) -> None:
        p = self._take_prep(k, t)
        if p is not None and self._prep_valid(p):
            self._commit_prep(p, send)
            return
        m = self.mag
        while self.pending_flips and self.pending_flips[0][0] <= t:
            tf, st = self.pending_flips.pop(0)
            self._flip(tf, st, True)
        if m.flip_every and k % m.flip_every == 0 and t >= self.cmd_until_us:
            self._flip(t - 2 * m.flip_delta_us, -self.flip_state, False)
        noise = self.rng.normal(0.0, m.noise_t, 3) if p is None else p.noise    # (drawn in sample order)
        B = (self._sensed(t) + self.flip_state * self.offset + self.flip_err + noise)
        self.prepared_redone += p is not None
        self._send_mag(t, B, send)

    # --- the next sample computed ahead, off the sampling path (wall-clock loops)
    #: False in a subclass whose sample is not :meth:`_mag_sample`'s (``hil.ac_nodes.FastSensorNode``)
    prepares_samples = True

    @property
    def prepared_msg(self):
        """The ``MAG_PACKED`` of the next sample as :meth:`prepare_sample` computed it (None: none)."""
        return None if self._prep is None else self._prep.msg

    def prepare_sample(self, until_us: int) -> int:
        """Compute the next magnetometer sample ahead if it is due by true time ``until_us``: its
        set/reset flips (commanded and autonomous, with their artefacts), the field through the
        sensor's model, its noise (drawn now, in sample order), quantisation and ``MAG_PACKED``
        message, so that at its instant :meth:`_mag_sample` only books and sends it. The result
        holds while the world is not edited at or before the latest instant it read (a pulse
        committed by the driver, :meth:`hil.world.World.edited_since`) and no ``MAG_FLIP_CMD``
        arrives; otherwise it is computed again (here, or on the sampling path with the same
        noise). The stamp is taken at the instant (a ``TIME_SYNC`` between moves it). The byte
        stream is the one the sampling path alone gives. Returns 1 when it computed, else 0."""
        if not (self.prepares_samples and self.online and self.sync.synced):
            return 0
        k = self._mag_k
        while self._mag_t(k) < self.synced_since_us:
            k += 1
        t = self._mag_t(k)
        if t > until_us:
            return 0
        p = self._prep
        if p is not None and (p.k != k or p.t != t):
            self._drop_prep()
            p = None
        if p is not None and self._prep_valid(p):
            return 0
        if k > self._mag_cached_to:                 # (as step() would before this sample)
            self.world.precompute([self._mag_t(j) for j in range(k, k + self._CHUNK)])
            self._mag_cached_to = k + self._CHUNK - 1
        if p is None:
            state = self.rng.bit_generator.state
            noise = self.rng.normal(0.0, self.mag.noise_t, 3)
        else:
            state, noise = p.rng_state, p.noise
        self._prep = _PreparedMag(k, t, noise, state, self.world.edit_mark(), self.flip_cmds)
        self._prep.compute(self)
        return 1

    def _take_prep(self, k: int, t: int):
        """The prepared sample if it is sample ``k`` at ``t`` (taken off the node); a prepared
        sample of another instant (skipped: sync lost, power cycled) is dropped with its draw."""
        p = self._prep
        if p is not None and (p.k != k or p.t != t):
            self._drop_prep()
            return None
        self._prep = None
        return p

    def _drop_prep(self) -> None:
        """Forget the prepared sample and undo its noise draw (the node's generator back where it
        was before it, so the draws stay in the order of the samples sent)."""
        if self._prep is not None:
            bits = np.random.PCG64()            # (the generator of np.random.default_rng, as made here)
            bits.state = self._prep.rng_state
            self.rng = np.random.Generator(bits)
            self._prep = None

    def _prep_valid(self, p: "_PreparedMag") -> bool:
        return p.flip_cmds == self.flip_cmds and not self.world.edited_since(p.mark, p.t_max)

    def _commit_prep(self, p: "_PreparedMag", send) -> None:
        """Book and send the prepared sample ``p`` at its instant: its flips, then the sample (its
        stamp taken now)."""
        del self.pending_flips[:p.n_pending]
        for err, log in p.flips:
            self.flip_err, self.flip_state = err, log["state"]
            self.flip_log.append(log)
        msg, sat, stamp = p.msg, p.sat, self._stamp(p.t)
        if stamp != p.stamp:
            msg, sat, stamp = self._mag_msg(p.t, p.B, self.flip_state)
        self.prepared_used += 1
        self._book_mag(p.t, sat, stamp)
        send(self, msg)

    def fit_imperfection(self, si) -> None:
        """Give this sensor its imperfections (``hil.imperfections.SensorImperfection``) before the
        run starts (see :meth:`_sensed`); they record its own turn-on IMU biases."""
        self.imperfect = si
        if getattr(self, "imu", None) is not None:
            si.record_turn_on(self.acc_bias, self.gyro_bias)

    def _sensed(self, t: int):
        """The field (3,) T the magnetometer reads at true time ``t`` before its flip offset and
        noise: the world's field in the sensor frame, through the imperfect magnetometer model
        (``hil.imperfections.MagImperfection.measure``) when the node has one."""
        return self._through_model(self.world.field_sensor_frame(t), t)

    def _through_model(self, B, t: int):
        """``B`` (3,) T, sensor frame, through the node's magnetometer imperfections (if any)."""
        imp = self.imperfect
        if imp is not None and imp.mag is not None:
            B = imp.mag.measure(B, t)
        return B

    def _send_mag(self, t: int, B, send) -> None:
        """Quantise the field ``B`` (3,) T measured at true time ``t``, stamp it on the master clock and
        send it as a MAG_PACKED (saturated beyond the range, flip state in the stamp bits)."""
        msg, sat, stamp = self._mag_msg(t, B, self.flip_state)
        self._book_mag(t, sat, stamp)
        send(self, msg)

    def _stamp(self, t: int) -> int:
        # MAG_PACKED: the master time rounded to the stamp's 8 us; the receiver restores it
        return max(0, self.master(t) + STAMP_LSB_US // 2) // STAMP_LSB_US * STAMP_LSB_US

    def _mag_msg(self, t: int, B, flip_state: int):
        """(the ``MAG_PACKED`` of ``B`` (3,) T at true time ``t`` in ``flip_state``, saturated?, its
        stamp); books nothing."""
        m = self.mag
        sat = bool(np.any(np.abs(B) > m.range_t))
        lim = m.range_t / MAG_LSB_T
        counts = np.clip(np.round(B / MAG_LSB_T), -lim, lim)
        stamp = self._stamp(t)
        return MagPacked(self.node_id, int(counts[0]), int(counts[1]), int(counts[2]),
                         pack_stamp(stamp) | (STAMP_FLIP if flip_state > 0 else 0)
                         | (STAMP_SATURATED if sat else 0)), sat, stamp

    def _book_mag(self, t: int, sat: bool, stamp: int) -> None:
        self.saturations += sat
        self.samples += 1
        self.stamps.append(stamp)
        self.true_times.append(t)
        self._by_stamp.setdefault(stamp, t)

    def _imu_sample(self, t: int, k: int, send) -> None:
        imu = self.imu
        kin = self._imu_cache.pop(t, None)
        if kin is None:
            ts = [self._imu_t(j) for j in range(k, k + self._CHUNK)]
            K = self.world.sensor_kinematics(np.asarray(ts, dtype=np.int64))   # world frame
            self._imu_cache.update({tj: (K.acceleration[i], K.R[i], K.angular_velocity[i]) for i, tj in enumerate(ts)})
            kin = self._imu_cache.pop(t)
        a, R, w = kin
        dt = self._imu_period * 1e-6
        self.acc_bias += self.imu_rng.normal(0.0, imu.acc_bias_rw * math.sqrt(dt), 3)
        self.gyro_bias += self.imu_rng.normal(0.0, imu.gyro_bias_rw * math.sqrt(dt), 3)
        f = R.T @ (a - np.array([0.0, 0.0, -imu.gravity]))
        if self.imperfect is not None and self.imperfect.imu is not None:
            # scale, misalignment, g-sensitivity, bias instability, IMU-to-magnetometer alignment
            f, w = self.imperfect.imu.measure(f, w, dt)
        f = f + self.acc_bias + self.imu_rng.normal(0.0, imu.acc_sigma, 3)
        g = w + self.gyro_bias + self.imu_rng.normal(0.0, imu.gyro_sigma, 3)
        self.imu_samples += 1
        send_imu(self, imu, k, t, f, g, send)

    # --- ground truth look-ups
    def true_time_of(self, stamp_us: int) -> int | None:
        """True time of the sample stamped ``stamp_us`` (the first one sent with that stamp: the
        firmware's sample ring refuses a later sample whose stamp is not newer)."""
        return self._by_stamp.get(int(stamp_us))


# ---------------------------------------------------------------------------
# Recorder (the host)
# ---------------------------------------------------------------------------


class Recorder:
    """Plays the host: keeps every POSE (with the true pose at its time stamp and the
    PULSE_WINDOWs of its cycle), PULSE_WINDOW, FAULT_EVENT, HEARTBEAT and TIME_SYNC.

    ``master_to_true`` maps a master-clock time to true time: None for the
    identity (the firmware's clock is the bench's time base, as in both
    runners here), ``"sync"`` to learn it from the ``TIME_SYNC`` broadcasts the
    emulator sees (a firmware or a board with a clock of its own: the
    recorder fits them like a node with a perfect clock, ``hil.clock.NodeSync``),
    or a callable.
    """

    def __init__(self, world, master_to_true=None):
        self.world = world
        self.sync = None
        if master_to_true == "sync":
            self.sync = NodeSync()
            self.master_to_true = lambda t: self.sync.to_local(int(t))
        else:
            self.master_to_true = master_to_true or (lambda t: int(t))
        self.poses: list[dict] = []
        self.trajectories: dict = {}          # per sensor node, when sensors move apart (World.view)
        self.windows: list = []
        self.events: list = []
        self.heartbeats: list = []
        self.time_syncs: list = []
        self.flip_cmds: list = []
        self.pulse_cmds: list = []
        self._open_windows: dict[int, list] = {}

    def on_message(self, msg, now_us: int) -> None:
        name = msg.NAME
        if name == "POSE":
            traj = self.trajectories.get(msg.node, self.world.trajectory)
            p, R = traj.pose(self.master_to_true(msg.t_us))
            # the windows a magnetic pose was made of (fused poses at the IMU rate use none)
            wins = [] if msg.status & POSE_FUSED else self._open_windows.pop(msg.node, [])
            self.poses.append({"msg": msg, "rx_us": now_us, "true_p": np.array(p), "true_R": np.array(R),
                               "windows": wins})
        elif name == "PULSE_WINDOW":
            self.windows.append((now_us, msg))
            self._open_windows.setdefault(msg.node, []).append(msg)
        elif name == "FAULT_EVENT":
            self.events.append((now_us, msg))
        elif name == "HEARTBEAT":
            self.heartbeats.append((now_us, msg))
        elif name == "TIME_SYNC":
            self.time_syncs.append((now_us, msg))
            if self.sync is not None:
                self.sync.update(now_us, msg.master_time_us)
        elif name == "MAG_FLIP_CMD":
            self.flip_cmds.append((now_us, msg))
        elif name == "COIL_PULSE_CMD":
            self.pulse_cmds.append((now_us, msg))
