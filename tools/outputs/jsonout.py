"""Every JSON file and line the commands write goes through here: strict JSON,
with ``null`` where a figure is not a finite number (a run with no valid pose
has no RMS), so any parser reads it."""
from __future__ import annotations

import json
import math

import numpy as np


def sanitize(obj):
    """``obj`` with NaN and infinities as ``None`` and numpy values as Python ones."""
    if isinstance(obj, dict):
        return {str(k): sanitize(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [sanitize(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def dumps(obj, **kw) -> str:
    return json.dumps(sanitize(obj), allow_nan=False, **kw)


def write(path, obj) -> None:
    """``obj`` as indented JSON in ``path``."""
    with open(path, "w") as fh:
        fh.write(dumps(obj, indent=2) + "\n")
