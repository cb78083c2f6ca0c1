"""A user's firmware configuration file, merged over a scenario's.

``coiltrack bench --config FILE`` and ``coiltrack firmware --config FILE``
read the TOML file and put its keys over the scenario's configuration
(``coiltrack.firmware.config.config_from_dict``). Every bad value is refused
with a :class:`ConfigError` naming its key, also a value of the wrong shape
that the checks themselves trip over (a string where a number belongs).
"""
from __future__ import annotations

from coiltrack.firmware.config import ConfigError, FirmwareConfig, config_from_dict
from .infile import load_toml


def _crashes(d: dict, base: FirmwareConfig) -> bool:
    """Whether ``d`` over ``base`` raises something else than a ConfigError."""
    try:
        config_from_dict(d, base)
    except ConfigError:
        return False
    except Exception:            # noqa: BLE001 - any Python error of a value of the wrong shape
        return True
    return False


def _guilty_key(d: dict, base: FirmwareConfig) -> tuple[str, object]:
    """The first ``section.key`` (``source.coils[i].key`` within a coil) whose value
    alone makes the configuration raise something else than a ConfigError, and that value."""
    for sec, table in d.items():
        for key, value in (table.items() if isinstance(table, dict) else ()):
            if not _crashes({sec: {key: value}}, base):
                continue
            if key == "coils" and isinstance(value, list):
                for i, c in enumerate(value):
                    for k, v in (c.items() if isinstance(c, dict) else ()):
                        if _crashes({sec: {"coils": [{k: v}]}}, base):
                            return f"{sec}.coils[{i}].{k}", v
            return f"{sec}.{key}", value
    return "<file>", None


def merge(d: dict, base: FirmwareConfig) -> FirmwareConfig:
    """``d`` (TOML-shaped) over ``base``, validated; ConfigError naming the key otherwise."""
    try:
        return config_from_dict(d, base)
    except ConfigError:
        raise
    except Exception as exc:     # noqa: BLE001 - reported, naming the key
        key, value = _guilty_key(d, base)
        raise ConfigError(key, f"invalid value {value!r} ({type(exc).__name__}: {exc})") from None


def load_over(path, base: FirmwareConfig) -> FirmwareConfig:
    """The TOML file ``path`` over ``base``. A file that cannot be used as such (unreadable,
    not UTF-8, empty, not TOML, a key given twice, a ``nan`` or ``inf``) is an
    :class:`~coiltrack.tools.inputs.infile.InputFileError` naming the file and its line or key (a file
    of comments alone puts nothing over ``base``); a bad value a :class:`ConfigError`."""
    cfg = merge(load_toml(path, "configuration"), base)
    cal = getattr(getattr(cfg, "calibration", None), "calibration_file", "")
    if cal and cal != getattr(getattr(base, "calibration", None), "calibration_file", ""):
        from .calibfile import read_table
        from .infile import InputFileError

        try:
            read_table(cal)      # the calibration file it names, read as strictly, before any work
        except InputFileError as exc:
            raise InputFileError(path, str(exc), key="calibration.calibration_file") from None
    return cfg
