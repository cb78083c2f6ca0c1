"""``--calibration FILE`` of ``bench`` and ``firmware``: the file read and
checked against the configuration before any work, then named in it
(``calibration.calibration_file``) for the firmware to apply at start-up.

The file is read strictly first (``tools.inputs.infile``): not UTF-8, empty (a
calibration file with no table is no calibration), not TOML, a key given
twice, a ``nan`` or ``inf`` are refused naming the file and its line or key."""
from __future__ import annotations

import dataclasses
from .infile import InputFileError, load_toml


def read_table(path) -> dict:
    """The calibration file's tables, read strictly; an
    :class:`~coiltrack.tools.inputs.infile.InputFileError` when it cannot be a calibration."""
    d = load_toml(path, "calibration table")
    if not d:
        raise InputFileError(path, "holds no calibration table (only comments): not a calibration file")
    return d


def with_calibration(path, cfg):
    """``cfg`` with ``calibration_file = path``, or the one-line error (a str)
    that refuses the file (missing, not UTF-8, empty, not TOML, a bad value: the key named)."""
    from coiltrack.firmware.calibration import load_calibration
    from coiltrack.firmware.config import ConfigError

    try:
        read_table(path)
        load_calibration(path, cfg)
    except InputFileError as exc:
        return f"--calibration {exc}"
    except ConfigError as exc:
        return f"--calibration {path}: {exc}"
    return cfg.with_(calibration={"calibration_file": str(path)})
