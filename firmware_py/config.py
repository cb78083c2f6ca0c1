"""Firmware configuration: source, sensor, timing and limits.

Everything the firmware allocates is sized from one :class:`FirmwareConfig`
at start-up. A configuration can be read from TOML (:func:`load_config`);
a bad value is refused with a :class:`ConfigError` that names the key.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields, replace

from protocol.schema import NODE_COIL_DRIVER, NODE_FIRMWARE, NODE_SENSOR_BASE


class ConfigError(ValueError):
    """A configuration value is missing, of the wrong type or out of range."""

    def __init__(self, key: str, message: str):
        super().__init__(f"config key '{key}': {message}")
        self.key = key


@dataclass(frozen=True)
class CoilConfig:
    """One source coil: pose in the source frame, geometry, nominal current."""
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    radius: float = 0.055      # m
    turns: int = 50
    current: float = 1.5       # A, nominal pulse current
    resistance: float = 2.0    # ohm, for energy accounting


def thesis_coils() -> tuple[CoilConfig, ...]:
    """Three orthogonal coils of the thesis source (ch. 5.2.1: 50 turns,
    radius 5.5 cm, 1.5 A)."""
    return tuple(CoilConfig(axis=a) for a in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))


@dataclass(frozen=True)
class FirmwareConfig:
    # --- identity and links
    node_id: int = NODE_FIRMWARE
    coil_driver_id: int = NODE_COIL_DRIVER
    sensor_ids: tuple[int, ...] = (NODE_SENSOR_BASE,)
    # --- source
    coils: tuple[CoilConfig, ...] = field(default_factory=thesis_coils)
    field_model: str = "exact"             # "exact" | "dipole"
    hemisphere: tuple[float, float, float] = (1.0, 0.0, 0.0)
    # --- timing (thesis sec 5.3: 60 ms pulses, 600 ms cycle)
    tick_us: int = 1000
    pulse_us: int = 60_000
    cycle_us: int = 600_000
    spacing_us: int = 100_000              # pulse j starts at cycle start + j * spacing
    lead_us: int = 50_000                  # commands leave this long before the cycle
    first_cycle_us: int = 200_000          # start of the first cycle after boot
    heartbeat_us: int = 1_000_000
    # --- pulse-window extraction (Schepers sec 3.1, thesis sec 5.2)
    settle_us: int = 3_000                 # current rise + eddy settle
    fall_us: int = 3_000                   # current fall + eddy settle after the pulse
    guard_us: int = 2_000
    baseline_us: int = 35_000              # quiet samples used each side
    min_pulse_samples: int = 3
    min_baseline_samples: int = 2
    drift_limit_t: float = 5e-6
    mag_sigma_t: float = 0.5e-7            # per-sample noise std, T
    mag_rate_hz: float = 120.0
    ring_capacity: int = 4096
    # --- limits
    max_current_a: float = 2.0
    stale_us: int = 2_000_000

    def validate(self) -> "FirmwareConfig":
        """Return self, or raise ConfigError naming the first bad key."""
        def need(key, ok, msg):
            if not ok:
                raise ConfigError(key, msg)

        for name in ("tick_us", "pulse_us", "cycle_us", "spacing_us", "lead_us", "heartbeat_us",
                     "baseline_us", "ring_capacity", "stale_us"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and v > 0,
                 f"must be a positive integer, got {v!r}")
        for name in ("settle_us", "fall_us", "guard_us", "first_cycle_us"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and v >= 0, f"must be a non-negative integer, got {v!r}")
        need("coils", 1 <= len(self.coils) <= 16, f"need 1..16 coils, got {len(self.coils)}")
        for i, c in enumerate(self.coils):
            k = f"coils[{i}]"
            need(k + ".radius", c.radius > 0 and math.isfinite(c.radius), f"must be > 0, got {c.radius!r}")
            need(k + ".turns", isinstance(c.turns, int) and c.turns > 0, f"must be a positive integer, got {c.turns!r}")
            need(k + ".axis", len(c.axis) == 3 and math.hypot(*c.axis) > 1e-9, "must be a non-zero 3-vector")
            need(k + ".center", len(c.center) == 3 and all(math.isfinite(v) for v in c.center), "must be a finite 3-vector")
            need(k + ".current", 0 < abs(c.current) <= self.max_current_a,
                 f"must be non-zero and within max_current_a={self.max_current_a}, got {c.current!r}")
            need(k + ".resistance", c.resistance > 0, f"must be > 0, got {c.resistance!r}")
        need("field_model", self.field_model in ("exact", "dipole"), f"must be 'exact' or 'dipole', got {self.field_model!r}")
        need("hemisphere", len(self.hemisphere) == 3 and math.hypot(*self.hemisphere) > 0, "must be a non-zero 3-vector")
        need("sensor_ids", len(self.sensor_ids) >= 1 and all(0 < s < 256 for s in self.sensor_ids),
             "must list 1..255 node ids")
        need("mag_sigma_t", self.mag_sigma_t > 0, f"must be > 0, got {self.mag_sigma_t!r}")
        need("mag_rate_hz", self.mag_rate_hz > 0, f"must be > 0, got {self.mag_rate_hz!r}")
        need("pulse_us", self.pulse_us > self.settle_us + self.guard_us,
             "must be longer than settle_us + guard_us")
        n = len(self.coils)
        need("spacing_us", n == 1 or self.spacing_us >= self.pulse_us + self.fall_us + self.baseline_us + self.guard_us,
             "the quiet gap between pulses must hold fall_us + baseline_us + guard_us")
        need("cycle_us", self.cycle_us >= (n - 1) * self.spacing_us + self.pulse_us + self.fall_us + self.baseline_us,
             "cycle too short for all pulses and the trailing baseline")
        need("lead_us", self.lead_us < self.cycle_us, "must be shorter than cycle_us")
        samples_per_cycle = self.cycle_us * 1e-6 * self.mag_rate_hz
        need("ring_capacity", self.ring_capacity >= 2 * samples_per_cycle,
             f"must hold two cycles of samples (>= {int(2 * samples_per_cycle)})")
        return self


_SIMPLE = {f.name for f in fields(FirmwareConfig)} - {"coils"}
_COIL_KEYS = {f.name for f in fields(CoilConfig)}


def config_from_dict(d: dict, base: FirmwareConfig | None = None) -> FirmwareConfig:
    """Build and validate a config from a (TOML-shaped) dict; unknown keys are refused."""
    base = base or FirmwareConfig()
    kw = {}
    for key, value in d.items():
        if key == "coils":
            if not isinstance(value, list):
                raise ConfigError("coils", "must be an array of tables")
            coils = []
            for i, c in enumerate(value):
                if not isinstance(c, dict):
                    raise ConfigError(f"coils[{i}]", "must be a table")
                for k in c:
                    if k not in _COIL_KEYS:
                        raise ConfigError(f"coils[{i}].{k}", "unknown key")
                cc = {k: (tuple(float(x) for x in v) if isinstance(v, list) else v) for k, v in c.items()}
                coils.append(CoilConfig(**cc))
            kw["coils"] = tuple(coils)
        elif key in _SIMPLE:
            default = getattr(base, key)
            if isinstance(default, tuple):
                if not isinstance(value, list):
                    raise ConfigError(key, f"must be an array, got {value!r}")
                value = tuple(value)
            elif isinstance(default, bool) or isinstance(default, int):
                if not isinstance(value, int) or isinstance(value, bool):
                    raise ConfigError(key, f"must be an integer, got {value!r}")
            elif isinstance(default, float):
                if not isinstance(value, (int, float)) or isinstance(value, bool):
                    raise ConfigError(key, f"must be a number, got {value!r}")
                value = float(value)
            elif isinstance(default, str) and not isinstance(value, str):
                raise ConfigError(key, f"must be a string, got {value!r}")
            kw[key] = value
        else:
            raise ConfigError(key, "unknown key")
    return replace(base, **kw).validate()


def load_config(path) -> FirmwareConfig:
    """Read a TOML configuration file (top-level keys as in FirmwareConfig,
    ``[[coils]]`` tables as in CoilConfig)."""
    with open(path, "rb") as fh:
        try:
            d = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("<file>", f"not valid TOML: {exc}") from None
    return config_from_dict(d)
