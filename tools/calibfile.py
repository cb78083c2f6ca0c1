"""``--calibration FILE`` of ``bench`` and ``firmware``: the file read and
checked against the configuration before any work, then named in it
(``calibration.calibration_file``) for the firmware to apply at start-up."""
from __future__ import annotations

import dataclasses


def with_calibration(path, cfg):
    """``cfg`` with ``calibration_file = path``, or the one-line error (a str)
    that refuses the file (missing, not TOML, a bad value: the key named)."""
    from coiltrack.firmware.calibration import load_calibration
    from coiltrack.firmware.config import ConfigError

    try:
        load_calibration(path, cfg)
    except ConfigError as exc:
        return f"--calibration {path}: {exc}"
    return dataclasses.replace(cfg, calibration_file=str(path))
