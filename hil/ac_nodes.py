"""Emulated nodes of AC excitation: the AC coil driver and the fast magnetometer node.

* :class:`ACDriverNode`: executes ``AC_DRIVE_CMD`` plans with
  :class:`hil.ac.ACCoilDriver` (frequency division: every coil on from its
  switch-on, at its own frequency; L/R response, limits clipped and
  flagged). The plan's phase reference ``ref_us`` and switch-on are master
  times, turned into true times through the driver's own synchronised clock
  (so its sync error shows as a phase error, as on a real bench). The
  driver regulates the current: it applies ``V = A |Z| e^{i (arg Z - w t_ref)}``
  so that ``i(t) = A cos(w (t - t_ref))`` in steady state, and reports the
  current it measures (amplitude and phase against the reference, averaged
  over ``status_average_samples`` samples of its current sensor, white noise
  ``current_noise_a`` each) in ``AC_DRIVE_STATUS`` after the switch-on and
  every ``status_every_us``.
* :class:`FastSensorNode`: a :class:`hil.nodes.SensorNode` whose magnetometer
  is a :class:`hil.magnetometers.FastMagProfile` (MMC5983MA: 1 kHz, 1.2 mG
  rms, averaging over 0.5 ms before the sample instant). Its samples carry
  the earth field and the objects' DC response (the world's field with the
  pulsed currents at rest), the coils' fields with the current averaged
  over the part's integration time (8-point Gauss-Legendre over the
  driver's closed-form current, transients included), and the conductors'
  and iron's AC response in steady state with their phase, through the
  part's filter ``H(f)``:

      B(t) = R^T [ B_dc(t) + sum_k ( ibar_k(t) u_k(p) + Re[ H(f_k) I_k F_k(p) e^{i w_k t} ] ) ],

  ``u_k`` the coil's field per ampere (magpylib), ``I_k`` the current
  phasor, ``F_k`` the objects' field per ampere: the lumped eddy loop
  through its transfer function (:func:`hil.conductors.eddy_moment_phasor`),
  a conducting (and permeable) sphere through Wait's exact response
  (:func:`hil.conductors.sphere_moment_phasor`), a magnetic sphere through
  its static moment, each a dipole at its centre (first-order scattering).
  Then white noise, the protocol's 5 nT counts and the range.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.protocol import MSG
from coiltrack.protocol.schema import (AC_CURRENT_LSB_A, AC_FAULT_REFUSED, AC_FREQ_LSB_HZ, AC_PHASE_LSB_RAD,
                                       MAG_LSB_T)

from . import conductors
from .ac import ACCoilDriver, ACLimits, ACRequest, coil_impedance
from .magnetometers import _NODES, _WEIGHTS, FastMagProfile
from .nodes import CoilDriverNode, MagSpec, SensorNode
from .world import ConductingSphereObject, EddyObject, FerroObject, MetalObject

AcStatus = MSG["AC_DRIVE_STATUS"]


class ACDriverNode(CoilDriverNode):
    """The coil driver with AC drive plans (pulse commands still handled as by the base class)."""

    def __init__(self, node_id: int, world, limits: ACLimits | None = None, seed: int = 0,
                 current_noise_a: float = 1e-3, clock=None, faults=None, status_every_us: int = 1_000_000,
                 status_average_samples: int = 1000):
        super().__init__(node_id, world, seed=seed, current_noise_a=current_noise_a, clock=clock, faults=faults)
        self.ac_limits = limits or ACLimits()
        self.status_every_us = int(status_every_us)
        self.status_average_samples = int(status_average_samples)
        self.plans: dict[int, dict] = {}     # coil -> accepted plan (master times)
        self.ac_rng = np.random.default_rng(seed + 31337)
        self.ac_driver: ACCoilDriver | None = None
        self.next_status_us: int | None = None
        self.ac_refused = 0

    def on_message(self, msg, now_us: int, send) -> None:
        if msg.NAME != "AC_DRIVE_CMD":
            super().on_message(msg, now_us, send)
            return
        c = msg.coil
        lead = msg.start_us - self.master(now_us)
        if c >= len(self.world.coils) or not self.sync.synced or lead < self.limits.min_lead_us:
            self.ac_refused += 1
            send(self, AcStatus(min(c, 255), msg.plan_id, msg.freq_mhz, 0, 0, msg.ref_us, AC_FAULT_REFUSED))
            return
        ref_true = self.true_of_master(msg.ref_us, now_us)
        on_true = self.true_of_master(msg.start_us, now_us)
        self.plans[c] = {"plan_id": msg.plan_id, "freq_hz": msg.freq_mhz * AC_FREQ_LSB_HZ,
                         "amplitude_a": msg.amplitude_ua * AC_CURRENT_LSB_A, "ref_us": msg.ref_us,
                         "ref_true_us": ref_true, "on_true_us": on_true, "rx_true_us": now_us}
        self._rebuild()

    def on_power_off(self, now_us: int) -> None:
        """Outputs off: the AC drive stops and its plans are forgotten."""
        super().on_power_off(now_us)
        self.plans.clear()
        self.ac_driver = None
        self.next_status_us = None

    def _rebuild(self) -> None:
        """One :class:`ACCoilDriver` over the accepted plans (frequency division from the earliest switch-on;
        a coil whose plan starts later joins at its own switch-on through its L/R transient)."""
        reqs = []
        src = self.world.source
        for c, p in sorted(self.plans.items()):
            coil = src[c]
            w = 2.0 * math.pi * p["freq_hz"]
            z = coil_impedance(coil, w)
            ph = math.atan2(z.imag, z.real) - w * p["ref_true_us"] * 1e-6
            reqs.append(ACRequest(c, p["freq_hz"], p["amplitude_a"] * abs(z), ph))
        on = min(p["on_true_us"] for p in self.plans.values())
        self.ac_driver = ACCoilDriver(src, reqs, self.ac_limits, start_s=on * 1e-6,
                                      current_noise_a=self.current_noise_a)
        self.next_status_us = max(p["on_true_us"] for p in self.plans.values()) + 50_000

    def step(self, now_us: int, send) -> None:
        super().step(now_us, send)
        if self.ac_driver is None or self.next_status_us is None or now_us < self.next_status_us:
            return
        self.next_status_us = now_us + self.status_every_us
        for c, p in sorted(self.plans.items()):
            d = self.ac_driver.drives[c]
            if d is None:
                continue
            # measured current phasor against cos(w (t - t_ref)), on the driver's clock
            w = d.omega
            ref_master_true = p["ref_true_us"]          # the reference as the driver's clock placed it
            I = d.current * complex(math.cos(w * ref_master_true * 1e-6), math.sin(w * ref_master_true * 1e-6))
            sd = self.current_noise_a * math.sqrt(2.0 / self.status_average_samples)
            I += complex(self.ac_rng.normal(0.0, sd), self.ac_rng.normal(0.0, sd))
            flags = d.flags & 0x0F
            amp = min(abs(I) / AC_CURRENT_LSB_A, 4294967295)
            phase = math.atan2(I.imag, I.real)
            send(self, AcStatus(c, p["plan_id"], int(round(d.freq_hz / AC_FREQ_LSB_HZ)), int(round(amp)),
                                int(round(phase / AC_PHASE_LSB_RAD)), p["ref_us"], flags))


def object_moment(world, obj, omega: float, k: int):
    """``(centre, complex moment)`` (m, A m^2 per ampere of coil ``k``'s current phasor) of ``obj`` in
    steady state at ``omega``, or None for an object without an AC response (a magnet on the board)
    or one that moves (a carried part: its DC response only)."""
    src = world.source
    coil = src[k]
    if isinstance(obj, EddyObject):
        return obj.conductor.position, conductors.eddy_moment_phasor(obj.conductor, coil, omega, 1.0)
    if isinstance(obj, ConductingSphereObject):
        sph = obj.sphere
        u = src.unit_fields(sph.position[None, :])[k, 0]
        return sph.position, conductors.sphere_moment_phasor(omega, sph.radius, sph.sigma, 1.0, u)
    if isinstance(obj, FerroObject):
        u = src.unit_fields(obj.sphere.position[None, :])[k, 0]
        return obj.sphere.position, obj.sphere.moment(u).astype(complex)
    if isinstance(obj, MetalObject) and obj.position is not None:
        u = src.unit_fields(obj.position[None, :])[k, 0]
        return obj.position, conductors.sphere_moment_phasor(omega, obj.radius, obj.sigma, obj.mu_r, u)
    return None


def object_response(world, obj, omega: float, k: int, point) -> np.ndarray:
    """Field phasor (T per ampere of coil ``k``'s current phasor, complex (3,)) of ``obj`` at ``point``."""
    pm = object_moment(world, obj, omega, k)
    if pm is None:
        return np.zeros(3, dtype=complex)
    return conductors.dipole_field_phasor(np.asarray(point, dtype=float).reshape(1, 3), pm[0], pm[1])[0]


class FastSensorNode(SensorNode):
    """A sensor node with a fast magnetometer under AC excitation (see module docstring).

    ``driver``: the coil driver whose AC drive (its ``ac_driver``, an :class:`hil.ac.ACCoilDriver`
    or None while no plan runs) the node's samples see; None: no AC drive at all."""

    def __init__(self, node_id: int, world, profile: FastMagProfile | None = None, imu=None, seed: int = 0,
                 clock=None, faults=None, driver=None):
        profile = profile or FastMagProfile.mmc5983ma()
        mag = MagSpec(rate_hz=profile.rate_hz, noise_t=profile.noise_rms_t, flip_every=0,
                      range_t=min(profile.range_t, 32767 * MAG_LSB_T))
        super().__init__(node_id, world, mag=mag, imu=imu, seed=seed, clock=clock, faults=faults)
        self.profile = profile
        self.driver = driver
        self._resp_cache: dict = {}

    def _coil_ac_field(self, t_us: int) -> np.ndarray:
        """Coil and object AC fields (T, source frame) at true time ``t_us`` as the part outputs them."""
        drv = self.driver.ac_driver if self.driver is not None else None
        if drv is None:
            return np.zeros(3)
        prof = self.profile
        t = t_us * 1e-6
        half = 0.5 * prof.integration_s
        nodes = t - half + half * _NODES
        ibar = 0.5 * (drv.current_at(nodes) @ _WEIGHTS)                  # (K,) averaged current
        p, R = self.world.pose(t_us)
        c = self.world._cache.get(int(t_us))
        U = c[2] if c is not None else self.world.unit_fields(p)
        B = ibar @ U
        for obj in self.world.objects:
            if not obj.active(t_us):
                continue
            for k, d in enumerate(drv.drives):
                if d is None:
                    continue
                F = self._response(obj, d.omega, k, p)
                if F is None:
                    continue
                h = prof.response(d.freq_hz)
                B = B + np.real(h * d.current * F * complex(math.cos(d.omega * t), math.sin(d.omega * t)))
        return B

    def _response(self, obj, omega: float, k: int, p):
        key = (id(obj), k, omega)
        if key not in self._resp_cache:
            self._resp_cache[key] = object_moment(self.world, obj, omega, k)
        pm = self._resp_cache[key]
        if pm is None:
            return None
        return conductors.dipole_field_phasor(np.asarray(p, dtype=float).reshape(1, 3), pm[0], pm[1])[0]

    prepares_samples = False        # its sample is its own (SensorNode.prepare_sample prepares the base's)

    def _mag_sample(self, t: int, k: int, send) -> None:
        m = self.mag
        p, R = self.world.pose(t)
        B = (self._through_model(self.world.field_sensor_frame(t) + R.T @ self._coil_ac_field(t), t)
             + self.flip_state * self.offset + self.rng.normal(0.0, m.noise_t, 3))
        self._send_mag(t, B, send)


class ACNodeKinds:
    """The nodes of a bench under AC excitation (``hil.bench.assemble(..., kinds=ACNodeKinds(profile))``):
    an :class:`ACDriverNode` and :class:`FastSensorNode` s with the magnetometer ``profile`` that
    see its drive. The AC driver keeps its own limits (:class:`hil.ac.ACLimits`), not the pulse
    limits of the bench."""

    def __init__(self, profile: FastMagProfile | None = None):
        self.profile = profile

    def driver(self, node_id: int, world, *, limits, seed: int, clock, faults) -> ACDriverNode:
        return ACDriverNode(node_id, world, seed=seed, clock=clock, faults=faults)

    def sensor(self, node_id: int, world, *, mag, imu, seed: int, clock, faults, driver) -> FastSensorNode:
        return FastSensorNode(node_id, world, self.profile, imu=imu, seed=seed, clock=clock, faults=faults,
                              driver=driver)


def ac_amplitude_sigma(freqs_hz, rate_hz: float, window_s: float, noise_t: float, integration_s: float,
                       offsets: int = 16) -> np.ndarray:
    """Standard deviation (T, (n,)) of the in-phase amplitude of each coil from one block of ``window_s``
    at ``rate_hz`` with white noise ``noise_t`` per sample and axis: the least-squares fit of DC, a ramp
    and a cosine and a sine per coil (numpy's inverse of the design's normal matrix), averaged over
    ``offsets`` positions of the sample grid against the carriers, divided by the magnetometer's gain
    ``|H(f)|`` (:meth:`FastMagProfile.response`). The reference of the AC Cramer-Rao bound."""
    f = np.asarray(freqs_hz, dtype=float)
    N = int(round(window_s * rate_hz))
    prof = FastMagProfile("ref", rate_hz, integration_s, 0.0, noise_t, 1.0, 1.0, 0)
    v = np.zeros(f.size)
    for o in range(offsets):
        t = (np.arange(N) + o / offsets) / rate_hz + 0.123
        tau = (t - t[0]) / window_s - 0.5
        cols = [np.ones(N), tau]
        for fk in f:
            cols += [np.cos(2 * np.pi * fk * t), np.sin(2 * np.pi * fk * t)]
        A = np.stack(cols, axis=1)
        C = np.linalg.inv(A.T @ A)
        v += 0.5 * (np.diag(C)[2::2] + np.diag(C)[3::2])
    v /= offsets
    return noise_t * np.sqrt(v) / np.abs(prof.response(f))
