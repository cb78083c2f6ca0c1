"""The calibration file: the source's and the sensors' imperfection
parameters, read once at start-up into preallocated arrays and applied on
the fly without allocating.

File (TOML)
    ``[source]`` (Raab ``seeds/004_86267342cd7488ce.txt``, "Source and Sensor
    Imperfections": the source matrix, here one row per coil)

    - ``coil_moment`` (n, 3): coil ``j``'s effective dipole moment per ampere
      in the source frame, relative to the nominal magnitude ``N_j pi a_j^2``;
      the nominal is the configured unit axis. Its direction is the true
      axis (misalignment, non-orthogonality), its norm the gain.
    - ``coil_offset_m`` (n, 3), m: true winding centre minus the configured one.
    - ``coil_moment_sigma``, ``coil_offset_m_sigma``: 1-sigma, same shapes.

    ``[sensor.N]`` (``N`` the node id), every key optional (a missing one is
    the nominal value), each with its ``*_sigma`` of the same shape:

    - ``mag_soft`` (3, 3) and ``mag_hard_t`` (3,) T: the magnetometer's
      ellipsoid, ``B_meas = mag_soft @ B_true + mag_hard_t`` (sensor frame,
      which is the magnetometer's frame);
    - ``accel_matrix`` (3, 3), ``accel_bias_m_s2`` (3,): ``f_meas = A f + b_a``;
    - ``gyro_matrix`` (3, 3), ``gyro_bias_rad_s`` (3,), ``gyro_g_sensitivity``
      (3, 3) rad/s per m/s^2: ``w_meas = G w + b_g + Gg f``;
    - ``mag_to_imu_rotvec`` (3,) rad: the IMU frame in the magnetometer
      frame, ``v_mag = exp([r]x) v_imu`` (``f``, ``w`` above are IMU-frame).

    ``[distortion]``: the residual-field map of the room, parsed by
    ``coiltrack.firmware.model.distortion.DistortionMap.from_table``.
    ``[meta]``: ``method``, ``date``, ``residual_rms``, ``poses`` (free form).

Application
    The source rows become calibrated :class:`~coiltrack.firmware.model.field.Coil`
    objects (:func:`calibrated_coils`: axis ``u_j = m_j / |m_j|``, gain
    ``|m_j|``, centre ``c_j + o_j``), so the one signal model
    (``model/signal.py``) evaluates them with the product it already makes.
    The sensor's inverses (``mag_soft^-1``, ``A^-1``, ``G^-1``, the rotation)
    are computed here once; :meth:`SensorCalibration.correct_mag` and
    :meth:`SensorCalibration.correct_imu` invert the models on each sample
    with Python floats (nine products per vector), nothing allocated.

Every bad value is refused with :class:`CalibrationError` naming the key
(``sensor.32.mag_soft``), before anything runs.
"""
from __future__ import annotations

import math
import tomllib

import numpy as np

from coiltrack.firmware.config import ConfigError
from coiltrack.firmware.model.field import Coil

__all__ = ["CalibrationError", "SourceCalibration", "SensorCalibration", "Calibration", "load_calibration",
           "calibrated_coils", "dumps_toml", "rotvec_matrix", "SENSOR_KEYS"]


class CalibrationError(ConfigError):
    """A bad calibration value: ``key`` names it (``source.coil_moment``,
    ``sensor.32.mag_soft``). A :class:`ConfigError`, so every caller that
    refuses a bad configuration refuses a bad calibration the same way."""

    def __init__(self, key: str, message: str):
        ValueError.__init__(self, f"calibration key '{key}': {message}")
        self.key = key
        self.message = message

    def __reduce__(self):
        return (CalibrationError, (self.key, self.message))


#: sensor keys, their shapes and nominal values
SENSOR_KEYS: dict[str, tuple[tuple[int, ...], object]] = {
    "mag_soft": ((3, 3), "eye"),
    "mag_hard_t": ((3,), "zero"),
    "accel_matrix": ((3, 3), "eye"),
    "accel_bias_m_s2": ((3,), "zero"),
    "gyro_matrix": ((3, 3), "eye"),
    "gyro_bias_rad_s": ((3,), "zero"),
    "gyro_g_sensitivity": ((3, 3), "zero"),
    "mag_to_imu_rotvec": ((3,), "zero"),
}
_MAG_KEYS = ("mag_soft", "mag_hard_t")
_IMU_KEYS = ("accel_matrix", "accel_bias_m_s2", "gyro_matrix", "gyro_bias_rad_s", "gyro_g_sensitivity",
             "mag_to_imu_rotvec")
#: bounds that refuse a file made for another device (or with its units wrong)
_LIMITS = {"mag_hard_t": 1e-3, "accel_bias_m_s2": 5.0, "gyro_bias_rad_s": 1.0, "gyro_g_sensitivity": 0.1,
           "mag_to_imu_rotvec": 0.5}
_MATRIX_COND_MAX = 10.0          # a scale/misalignment matrix this ill-conditioned is not a calibration


def rotvec_matrix(r) -> np.ndarray:
    """``exp([r]x)`` (3, 3) of a rotation vector ``r`` (3,), rad (Rodrigues)."""
    r = np.asarray(r, dtype=float).reshape(3)
    th = float(np.linalg.norm(r))
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(th) / th * K + (1.0 - math.cos(th)) / (th * th) * (K @ K)


def _array(key: str, value, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(key, f"must be an array of numbers of shape {list(shape)}") from None
    if a.shape != shape:
        raise CalibrationError(key, f"must have shape {list(shape)}, got {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(key, "must be finite")
    return a


def _sigma(key: str, table: dict, shape, section: str = "source") -> np.ndarray:
    k = f"{section}.{key}_sigma"
    if key + "_sigma" not in table:
        return np.zeros(shape)
    s = _array(k, table[key + "_sigma"], shape)
    if np.any(s < 0):
        raise CalibrationError(k, "must be non-negative")
    return s


def _matrix(key: str, a: np.ndarray) -> np.ndarray:
    """Inverse of a scale/misalignment matrix, refusing a singular one."""
    sv = np.linalg.svd(a, compute_uv=False)
    if not (sv[-1] > 0 and sv[0] / sv[-1] <= _MATRIX_COND_MAX):
        raise CalibrationError(key, f"must be a well-conditioned matrix (condition number <= {_MATRIX_COND_MAX:g})")
    if np.linalg.det(a) <= 0:
        raise CalibrationError(key, "must not mirror the axes (positive determinant)")
    return np.linalg.inv(a)


class SourceCalibration:
    """Per coil moment (direction x gain) and centre offset.

    Attributes
    ----------
    moment : ndarray (n, 3)        relative moments (unit axis = nominal)
    offset : ndarray (n, 3)        m
    moment_sigma, offset_sigma : ndarray (n, 3)
    """

    def __init__(self, moment, offset, moment_sigma=None, offset_sigma=None):
        self.moment = np.array(moment, dtype=float)
        self.offset = np.array(offset, dtype=float)
        n = self.moment.shape[0]
        self.moment_sigma = np.zeros((n, 3)) if moment_sigma is None else np.array(moment_sigma, dtype=float)
        self.offset_sigma = np.zeros((n, 3)) if offset_sigma is None else np.array(offset_sigma, dtype=float)

    @property
    def n(self) -> int:
        return self.moment.shape[0]

    @classmethod
    def from_table(cls, t: dict, n_coils: int | None = None, max_gain_error: float = 0.5,
                   max_tilt_deg: float = 20.0, nominal_axes=None) -> "SourceCalibration":
        if not isinstance(t, dict):
            raise CalibrationError("source", "must be a table")
        for k in t:
            if k not in ("coil_moment", "coil_offset_m", "coil_moment_sigma", "coil_offset_m_sigma"):
                raise CalibrationError(f"source.{k}", "unknown key")
        if "coil_moment" not in t:
            raise CalibrationError("source.coil_moment", "missing")
        rows = t["coil_moment"]
        n = len(rows) if isinstance(rows, list) else -1
        if n_coils is not None and n != n_coils:
            raise CalibrationError("source.coil_moment", f"must have one row per coil ({n_coils}), got {n}")
        if n < 1:
            raise CalibrationError("source.coil_moment", "must list one [mx, my, mz] per coil")
        m = _array("source.coil_moment", rows, (n, 3))
        o = _array("source.coil_offset_m", t.get("coil_offset_m", [[0.0] * 3] * n), (n, 3))
        ms = _sigma("coil_moment", t, (n, 3))
        os_ = _sigma("coil_offset_m", t, (n, 3))
        g = np.linalg.norm(m, axis=1)
        for j in range(n):
            if not abs(g[j] - 1.0) <= max_gain_error:
                raise CalibrationError("source.coil_moment",
                                       f"coil {j}: gain {g[j]:.4g} is beyond 1 +- {max_gain_error:g}")
            if nominal_axes is not None:
                ax = np.asarray(nominal_axes[j], dtype=float)
                c = float(np.dot(ax, m[j]) / (np.linalg.norm(ax) * g[j]))
                tilt = math.degrees(math.acos(max(-1.0, min(1.0, c))))
                if tilt > max_tilt_deg:
                    raise CalibrationError("source.coil_moment",
                                           f"coil {j}: {tilt:.1f} deg from its configured axis "
                                           f"(beyond {max_tilt_deg:g} deg: a file for another source?)")
        if np.any(np.abs(o) > 0.05):
            raise CalibrationError("source.coil_offset_m", "offsets beyond 5 cm: not a winding-centre offset")
        return cls(m, o, ms, os_)

    def to_table(self) -> dict:
        return {"coil_moment": self.moment.tolist(), "coil_moment_sigma": self.moment_sigma.tolist(),
                "coil_offset_m": self.offset.tolist(), "coil_offset_m_sigma": self.offset_sigma.tolist()}


class SensorCalibration:
    """One sensor node's magnetometer ellipsoid and IMU model, with the
    inverses computed once.

    Attributes (nominal when a key is absent)
    ----------
    values : dict key -> ndarray (shape of :data:`SENSOR_KEYS`)
    sigmas : dict key -> ndarray (same shapes; zero when not given)
    has_mag, has_imu : bool   any magnetometer / IMU key given
    """

    def __init__(self, node: int, values: dict | None = None, sigmas: dict | None = None):
        self.node = int(node)
        self.values = {}
        self.sigmas = {}
        given = set(values or {})
        for k, (shape, nom) in SENSOR_KEYS.items():
            v = (values or {}).get(k)
            self.values[k] = (np.eye(3) if nom == "eye" else np.zeros(shape)) if v is None else np.array(v, float)
            s = (sigmas or {}).get(k)
            self.sigmas[k] = np.zeros(shape) if s is None else np.array(s, float)
        self.has_mag = bool(given & set(_MAG_KEYS))
        self.has_imu = bool(given & set(_IMU_KEYS))
        self._given = given
        pre = f"sensor.{self.node}."
        v = self.values
        mi = _matrix(pre + "mag_soft", v["mag_soft"])
        ai = _matrix(pre + "accel_matrix", v["accel_matrix"])
        gi = _matrix(pre + "gyro_matrix", v["gyro_matrix"])
        R = rotvec_matrix(v["mag_to_imu_rotvec"])
        # flat tuples of Python floats: the per-sample code reads them without indexing numpy
        self._mi = tuple(float(x) for x in mi.reshape(9))
        self._mh = tuple(float(x) for x in v["mag_hard_t"])
        self._ai = tuple(float(x) for x in ai.reshape(9))
        self._ab = tuple(float(x) for x in v["accel_bias_m_s2"])
        self._gi = tuple(float(x) for x in gi.reshape(9))
        self._gb = tuple(float(x) for x in v["gyro_bias_rad_s"])
        self._gg = tuple(float(x) for x in v["gyro_g_sensitivity"].reshape(9))
        self._R = tuple(float(x) for x in R.reshape(9))

    @classmethod
    def from_table(cls, node: int, t: dict) -> "SensorCalibration":
        pre = f"sensor.{node}."
        if not isinstance(t, dict):
            raise CalibrationError(pre[:-1], "must be a table")
        values, sigmas = {}, {}
        for k, val in t.items():
            base = k[:-6] if k.endswith("_sigma") else k
            if base not in SENSOR_KEYS:
                raise CalibrationError(pre + k, "unknown key")
            shape = SENSOR_KEYS[base][0]
            a = _array(pre + k, val, shape)
            if k.endswith("_sigma"):
                if np.any(a < 0):
                    raise CalibrationError(pre + k, "must be non-negative")
                sigmas[base] = a
            else:
                lim = _LIMITS.get(k)
                if lim is not None and np.any(np.abs(a) > lim):
                    raise CalibrationError(pre + k, f"beyond {lim:g} in magnitude: wrong units or another device")
                values[k] = a
        return cls(node, values, sigmas)

    def to_table(self) -> dict:
        d = {}
        for k in SENSOR_KEYS:
            if k in self._given:
                d[k] = self.values[k].tolist()
                d[k + "_sigma"] = self.sigmas[k].tolist()
        return d

    # ------------------------------------------------------------ per sample
    def correct_mag(self, x: float, y: float, z: float) -> tuple:
        """``B_true = mag_soft^-1 (B_meas - mag_hard_t)``, T, sensor frame."""
        h = self._mh
        x -= h[0]
        y -= h[1]
        z -= h[2]
        m = self._mi
        return (m[0] * x + m[1] * y + m[2] * z, m[3] * x + m[4] * y + m[5] * z, m[6] * x + m[7] * y + m[8] * z)

    def correct_imu(self, ax: float, ay: float, az: float, gx: float, gy: float, gz: float) -> tuple:
        """Specific force (m/s^2) and rate (rad/s) in the magnetometer's
        frame from the IMU's readings: ``f_i = A^-1 (f_meas - b_a)``,
        ``w_i = G^-1 (w_meas - b_g - Gg f_i)``, then ``f = R f_i``,
        ``w = R w_i``. Returns ``(fx, fy, fz, wx, wy, wz)``."""
        b = self._ab
        ax -= b[0]
        ay -= b[1]
        az -= b[2]
        m = self._ai
        fx = m[0] * ax + m[1] * ay + m[2] * az
        fy = m[3] * ax + m[4] * ay + m[5] * az
        fz = m[6] * ax + m[7] * ay + m[8] * az
        g = self._gg
        b = self._gb
        gx -= b[0] + g[0] * fx + g[1] * fy + g[2] * fz
        gy -= b[1] + g[3] * fx + g[4] * fy + g[5] * fz
        gz -= b[2] + g[6] * fx + g[7] * fy + g[8] * fz
        m = self._gi
        wx = m[0] * gx + m[1] * gy + m[2] * gz
        wy = m[3] * gx + m[4] * gy + m[5] * gz
        wz = m[6] * gx + m[7] * gy + m[8] * gz
        r = self._R
        return (r[0] * fx + r[1] * fy + r[2] * fz, r[3] * fx + r[4] * fy + r[5] * fz,
                r[6] * fx + r[7] * fy + r[8] * fz,
                r[0] * wx + r[1] * wy + r[2] * wz, r[3] * wx + r[4] * wy + r[5] * wz,
                r[6] * wx + r[7] * wy + r[8] * wz)


class Calibration:
    """The whole file: ``source`` (or None), ``sensors`` {node: SensorCalibration},
    ``distortion`` (the parsed map or None), ``meta`` (dict)."""

    def __init__(self, source: SourceCalibration | None = None, sensors: dict | None = None,
                 distortion=None, meta: dict | None = None, distortion_table: dict | None = None):
        self.source = source
        self.sensors = dict(sensors or {})
        self.distortion = distortion
        self.distortion_table = distortion_table
        self.meta = dict(meta or {})

    @classmethod
    def from_table(cls, d: dict, n_coils: int | None = None, nominal_axes=None,
                   max_gain_error: float = 0.5, max_tilt_deg: float = 20.0) -> "Calibration":
        if not isinstance(d, dict):
            raise CalibrationError("<file>", "must be a TOML document")
        for k in d:
            if k not in ("source", "sensor", "distortion", "meta"):
                raise CalibrationError(k, "unknown section (source, sensor.N, distortion, meta)")
        src = None
        if "source" in d:
            src = SourceCalibration.from_table(d["source"], n_coils, max_gain_error, max_tilt_deg, nominal_axes)
        sensors = {}
        st = d.get("sensor", {})
        if not isinstance(st, dict):
            raise CalibrationError("sensor", "must hold tables [sensor.N]")
        for key, t in st.items():
            try:
                node = int(key)
            except ValueError:
                node = -1
            if not 1 <= node <= 255:
                raise CalibrationError(f"sensor.{key}", "must be a node id in 1..255")
            sensors[node] = SensorCalibration.from_table(node, t)
        dist = None
        dt = d.get("distortion")
        if dt is not None:
            if not isinstance(dt, dict):
                raise CalibrationError("distortion", "must be a table")
            try:
                from coiltrack.firmware.model.distortion import DistortionMap
            except ImportError:
                raise CalibrationError("distortion", "this firmware has no distortion map model") from None
            try:
                dist = DistortionMap.from_table(dt, n_coils)
            except ConfigError:
                raise
            except (ValueError, TypeError, KeyError) as exc:
                raise CalibrationError("distortion", str(exc)) from None
        meta = d.get("meta", {})
        if not isinstance(meta, dict):
            raise CalibrationError("meta", "must be a table")
        return cls(src, sensors, dist, meta, dt)

    def to_table(self) -> dict:
        d: dict = {}
        if self.meta:
            d["meta"] = dict(self.meta)
        if self.source is not None:
            d["source"] = self.source.to_table()
        if self.sensors:
            d["sensor"] = {str(k): s.to_table() for k, s in sorted(self.sensors.items())}
        if self.distortion_table is not None:
            d["distortion"] = self.distortion_table
        return d


def load_calibration(path, cfg=None) -> Calibration:
    """Read and validate a calibration file; with the firmware configuration
    ``cfg`` the source rows are checked against its coils (count, and each
    moment within ``calibration_max_tilt_deg`` of the configured axis and
    ``calibration_max_gain_error`` of unit gain)."""
    try:
        with open(path, "rb") as fh:
            d = tomllib.load(fh)
    except OSError as exc:
        raise CalibrationError("<file>", f"cannot read {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError("<file>", f"not valid TOML: {exc}") from None
    if cfg is None:
        return Calibration.from_table(d)
    return Calibration.from_table(d, len(cfg.source.coils), [c.axis for c in cfg.source.coils],
                                  getattr(getattr(cfg, "calibration", None), "calibration_max_gain_error", 0.5),
                                  getattr(getattr(cfg, "calibration", None), "calibration_max_tilt_deg", 20.0))


def calibrated_coils(coils, source: SourceCalibration | None) -> list:
    """The configured coils with the source calibration applied (start-up
    only): axis ``m_j / |m_j|``, gain ``|m_j|``, centre ``c_j + o_j``."""
    if source is None:
        return list(coils)
    if source.n != len(coils):
        raise CalibrationError("source.coil_moment", f"must have one row per coil ({len(coils)}), got {source.n}")
    out = []
    for j, c in enumerate(coils):
        m = source.moment[j]
        g = float(np.linalg.norm(m))
        out.append(Coil(np.asarray(c.center, float) + source.offset[j], m / g, c.radius, c.turns,
                        gain=g * float(getattr(c, "gain", 1.0))))
    return out


# ------------------------------------------------------------------ writing
def _fmt(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not math.isfinite(f):
            raise ValueError("calibration values must be finite")
        return repr(f)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dumps_toml(d: dict, _prefix: str = "") -> str:
    """A small TOML writer for the calibration tables (nested dicts become
    ``[a.b]`` tables; values: numbers, strings, booleans, nested arrays)."""
    lines, subs = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            subs.append((k, v))
        else:
            lines.append(f"{k} = {_fmt(v)}")
    out = ""
    if lines:
        out += (f"[{_prefix}]\n" if _prefix else "") + "\n".join(lines) + "\n\n"
    for k, v in subs:
        out += dumps_toml(v, f"{_prefix}.{k}" if _prefix else str(k))
    return out
