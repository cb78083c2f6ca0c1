"""AC coil driver of the emulated bench: sinusoidal drive through each coil's series L/R.

Phasor convention: ``x(t) = Re[X exp(i omega t)]`` (as in :mod:`hil.conductors`).
The driver applies a voltage ``V cos(omega t + phi)`` (phasor ``V e^{i phi}``)
to a coil of resistance ``R`` and inductance ``L``; the steady-state current is

    I = V / (R + i omega L),   |I| = |V| / sqrt(R^2 + (omega L)^2),
    arg I = phi - atan(omega L / R)        (the current lags the voltage).

Switching the voltage on at ``t_on`` from rest adds the L/R transient that
keeps the current continuous: ``i(t) = Re[I e^{i omega t}] - Re[I e^{i omega t_on}] e^{-(t - t_on)/tau}``,
``tau = L/R``; switching it off at ``t_off`` leaves the free decay
``i(t_off) e^{-(t - t_off)/tau}``.

Two schemes (:class:`ACCoilDriver`):

* frequency division: every coil on all the time, each at its own frequency;
* time multiplexing: one frequency, coil ``k`` on during slot ``k`` of every
  cycle of ``n_coils`` slots (each slot starts from rest: the previous slot's
  tail ``e^{-(n-1) S / tau}`` must be below 1e-9, checked at construction).

Limits (:class:`ACLimits`) are enforced on every request: the frequency is
clipped into the allowed band, the voltage amplitude to the supply, then the
amplitude is scaled down until the current amplitude and the mean dissipated
power (``|I|^2 R / 2`` times the duty cycle) are within their limits; each
clip sets a flag bit in the executed :class:`ACDrive`. Times are seconds
(float) here: the field at any sample time is :func:`field_at`, the coils'
per-ampere fields from :meth:`hil.physics.Source.unit_fields` (magpylib)
scaled by :meth:`ACCoilDriver.current_at`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from coiltrack.hil.physics import Source, SourceCoil

__all__ = ["ACLimits", "ACRequest", "ACDrive", "ACCoilDriver", "coil_impedance", "execute_request", "field_at",
           "FLAG_FREQUENCY", "FLAG_VOLTAGE", "FLAG_CURRENT", "FLAG_POWER"]

FLAG_FREQUENCY = 1   # frequency clipped into [min_freq_hz, max_freq_hz]
FLAG_VOLTAGE = 2     # voltage amplitude clipped to max_voltage_v
FLAG_CURRENT = 4     # amplitude scaled so that |I| <= max_current_a
FLAG_POWER = 8       # amplitude scaled so that the mean power <= max_power_w

_TAIL_LIMIT = 1e-9


@dataclass(frozen=True)
class ACLimits:
    """What an AC coil driver enforces whatever it is asked (amplitudes, not rms)."""
    max_voltage_v: float = 12.0
    max_current_a: float = 2.0
    max_power_w: float = 3.0          # mean I^2 R per coil
    min_freq_hz: float = 5.0
    max_freq_hz: float = 2000.0


@dataclass(frozen=True)
class ACRequest:
    """Drive coil ``coil`` with ``amplitude_v cos(2 pi freq_hz t + phase_rad)``."""
    coil: int
    freq_hz: float
    amplitude_v: float
    phase_rad: float = 0.0


@dataclass(frozen=True)
class ACDrive:
    """An executed request: the applied voltage and the steady-state current phasors, and the clip flags."""
    coil: int
    freq_hz: float
    voltage: complex
    current: complex
    flags: int

    @property
    def omega(self) -> float:
        return 2.0 * math.pi * self.freq_hz


def coil_impedance(coil: SourceCoil, omega) -> complex:
    """Series impedance ``R + i omega L`` (ohm) of ``coil``."""
    return float(coil.resistance) + 1j * np.asarray(omega, dtype=float) * float(coil.inductance)


def execute_request(req: ACRequest, coil: SourceCoil, limits: ACLimits, duty: float = 1.0) -> ACDrive:
    """Apply the limits to ``req`` (in the order frequency, voltage, current, power) and return the drive."""
    if req.amplitude_v < 0.0 or not 0.0 < duty <= 1.0:
        raise ValueError("need amplitude_v >= 0 and 0 < duty <= 1")
    flags = 0
    f = min(max(req.freq_hz, limits.min_freq_hz), limits.max_freq_hz)
    flags |= FLAG_FREQUENCY if f != req.freq_hz else 0
    z = abs(coil_impedance(coil, 2.0 * math.pi * f))
    v = req.amplitude_v
    caps = ((limits.max_voltage_v, FLAG_VOLTAGE),
            (limits.max_current_a * z, FLAG_CURRENT),
            (z * math.sqrt(2.0 * limits.max_power_w / (coil.resistance * duty)), FLAG_POWER))
    for cap, flag in caps:
        if v > cap:
            v, flags = cap, flags | flag
    V = v * complex(math.cos(req.phase_rad), math.sin(req.phase_rad))
    return ACDrive(req.coil, f, V, V / coil_impedance(coil, 2.0 * math.pi * f), flags)


class ACCoilDriver:
    """Sinusoidal drive of the coils of ``source``: frequency division or time multiplexing.

    ``requests``: one :class:`ACRequest` per driven coil (coils without one stay
    at zero). ``slot_s`` ``None``: frequency division, all coils on from
    ``start_s``; a slot length: time multiplexing, coil ``k`` on during
    ``[start + (j n + k) S, start + (j n + k + 1) S)`` for ``j = 0, 1, ...``
    (``n`` = number of coils), and every request must then use one frequency.
    ``current_noise_a``: rms noise of the driver's current measurement
    (:meth:`measured_current`).
    """

    def __init__(self, source: Source, requests: Sequence[ACRequest], limits: ACLimits | None = None,
                 start_s: float = 0.0, slot_s: float | None = None, current_noise_a: float = 1e-3):
        self.source, self.limits = source, limits or ACLimits()
        self.start_s, self.slot_s, self.current_noise_a = float(start_s), slot_s, float(current_noise_a)
        n = len(source)
        if slot_s is not None:
            self._check_multiplex(requests, float(slot_s))
        duty = 1.0 if slot_s is None else 1.0 / n
        self.drives: list[ACDrive | None] = [None] * n
        for req in requests:
            if not 0 <= req.coil < n or self.drives[req.coil] is not None:
                raise ValueError(f"request coil {req.coil}: need one request per coil, 0 <= coil < {n}")
            self.drives[req.coil] = execute_request(req, source[req.coil], self.limits, duty)

    def _check_multiplex(self, requests: Sequence[ACRequest], slot: float) -> None:
        if slot <= 0.0 or len({r.freq_hz for r in requests}) > 1:
            raise ValueError("time multiplexing needs slot_s > 0 and one frequency for all coils")
        worst_tau = max(c.tau_s for c in self.source)
        if math.exp(-(len(self.source) - 1) * slot / worst_tau) > _TAIL_LIMIT:
            raise ValueError(f"slot_s = {slot} s: the previous slot's L/R tail exceeds {_TAIL_LIMIT:g}; "
                             f"need slot_s >= {-math.log(_TAIL_LIMIT) * worst_tau / (len(self.source) - 1):.3g} s")

    def _window(self, k: int, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Start and end of coil ``k``'s latest on-window at or before each ``t`` (s)."""
        if self.slot_s is None:
            return np.full(t.shape, self.start_s), np.full(t.shape, np.inf)
        period = self.slot_s * len(self.source)
        first = self.start_s + k * self.slot_s
        j = np.maximum(np.floor((t - first) / period), 0.0)
        on = first + j * period
        return on, on + self.slot_s

    def coil_current(self, k: int, t_s) -> np.ndarray:
        """Current (A) of coil ``k`` at times ``t_s`` (s, scalar or array): steady state, switch-on and decay."""
        t = np.asarray(t_s, dtype=float)
        d = self.drives[k]
        if d is None:
            return np.zeros(t.shape)
        tau = self.source[k].tau_s
        on, off = self._window(k, t)

        def steady(s):
            return np.real(d.current * np.exp(1j * d.omega * s))

        def driven(s):
            return steady(s) - steady(on) * np.exp(-np.maximum(s - on, 0.0) / tau)

        t_end = np.minimum(t, np.where(np.isfinite(off), off, t))     # frequency division: never off
        i = driven(t_end) * np.exp(-(t - t_end) / tau)
        return np.where(t >= on, i, 0.0)

    def current_at(self, t_s) -> np.ndarray:
        """Currents of all coils, shape ``(n_coils,) + shape(t_s)`` (A)."""
        return np.stack([self.coil_current(k, t_s) for k in range(len(self.source))])

    def measured_current(self, t_s, rng: np.random.Generator) -> np.ndarray:
        """The driver's current measurement: :meth:`current_at` plus white noise (rms ``current_noise_a``)."""
        i = self.current_at(t_s)
        return i + rng.normal(0.0, self.current_noise_a, i.shape)


def field_at(source: Source, driver: ACCoilDriver, points, t_s) -> np.ndarray:
    """Field of the driven coils (T, world frame) at sample times ``t_s`` (s, (n,)).

    ``points``: one fixed point (3,) or one point per time (n, 3). The per-ampere
    fields come from :meth:`Source.unit_fields` (magpylib's circular-filament kernel).
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    pts = np.asarray(points, dtype=float)
    current = driver.current_at(t)                                  # (K, n)
    if pts.ndim == 1:
        return np.einsum("kn,ki->ni", current, source.unit_fields(pts[None, :])[:, 0, :])
    if pts.shape != (t.size, 3):
        raise ValueError(f"points: need shape (3,) or ({t.size}, 3), got {pts.shape}")
    return np.einsum("kn,kni->ni", current, source.unit_fields(pts))
