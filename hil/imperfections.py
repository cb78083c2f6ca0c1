"""The imperfections of a real bench, drawn seeded, applied in the physics, listed and written
in the calibration file's parameterisation.

Raab ``004_86267342cd7488ce.txt`` ("Source and Sensor Imperfections"): "the imperfections in
the three-axis source and sensor can be described by 3x3 fixed-valued matrices that include
both rotation (due to physical mounting of the source or sensor), gain, and skewing (due to
cross coupling between axes)". This module draws them, and those of the magnetometer and the
IMU beside it, from stated distributions (one seed, a stream of its own: the trajectory and
the sensor noise of a run do not change when the imperfections are switched on):

* :class:`SourceImperfection`: per coil an axis tilt (rotation vector perpendicular to the
  nominal axis, angle uniform in [0, ``tilt_max_deg``], default 2 deg: independent tilts make
  the coils non-orthogonal), a gain (effective turns x area) ``1 + N(0, 2 %)`` clipped to
  +-5 %, and a winding-centre offset ``N(0, 1 mm)`` per axis. They are applied to the exact-loop
  coils of :mod:`hil.physics` (rotated, moved, scaled filaments evaluated by magpylib), never
  downstream.
* :class:`MagImperfection`: the magnetometer frame's field ``B`` becomes
  ``N(soft @ B + hard) + tc * (T(t) - T_ref)`` with soft iron ``I + D + C`` (scale ``D`` diagonal
  ``N(0, 2 %)``; cross-axis ``C`` off-diagonal ``N(0, 1 %)``), hard iron ``N(0, 3 uT)`` per axis
  (the magnetised parts of a board: battery, connector, screws), a temperature coefficient of the
  offset ``N(0, 10 nT/K)`` per axis under a warm-up temperature profile
  (:class:`TemperatureProfile`) and a cubic compression near the range
  ``N(x) = x (1 - k3 (x / range)^2)``, ``k3`` ``U(0, 0.5 %)`` per axis (the error at full scale,
  a "linearity" figure in % FS). Magnitudes: uncalibrated AMR / MEMS three-axis magnetometers,
  e.g. the MEMSIC MMC5983MA and Honeywell HMC5883L data sheets (sensitivity and cross-axis
  tolerances of one to a few %, linearity 0.1-0.5 % FS, offset drift of some nT/K), and the
  Xsens MTi/MTx documentation (magnetometer linearity 0.2 % FS after its factory calibration).
* :class:`ImuImperfection`: accelerometer and gyroscope matrices ``I + D + C`` (scale
  ``N(0, 1 %)``, misalignment / cross-axis ``N(0, 0.5 %)`` per off-diagonal element), gyroscope
  g-sensitivity ``N(0, 0.1 deg/s/g)`` per element, bias instability as a first-order
  Gauss-Markov process per axis (a flicker approximation: ``sigma`` 0.01 deg/s and 2e-3 m/s^2,
  correlation time 100 s), and the magnetometer-to-IMU misalignment ``N(0, 0.5 deg)`` per axis
  (two chips soldered on one board). Magnitudes: Bosch BMI088 data sheet (gyroscope sensitivity
  tolerance and cross-axis sensitivity about 1 %, g-sensitivity about 0.1 deg/s/g; accelerometer
  cross-axis about 0.5 %) and the Xsens MTx documentation (bias stability, noise). The turn-on
  bias and its random walk stay those of :class:`hil.nodes.ImuSpec`.

Conventions (the calibration file's, ``firmware_py/calibration.py``): the sensor frame of the
trajectory is the magnetometer frame. ``B_meas = mag_soft @ B_true + mag_hard_t``;
``R_mi = exp(mag_to_imu_rotvec)`` is the IMU frame in the magnetometer frame, so
``v_imu = R_mi^T v_mag``; ``f_meas = accel_matrix @ f_imu + accel_bias``,
``w_meas = gyro_matrix @ w_imu + gyro_bias + gyro_g_sensitivity @ f_imu``; source coil ``k``
has the dipole ``coil_moment[k] * |m_nominal|`` (``coil_moment[k] = gain_k * true unit axis``) at
``nominal centre + coil_offset_m[k]``. Units SI (T, m, rad, s, m/s^2, K as degC differences).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .motion import matrix_to_rotvec, rotvec_to_matrix
from .physics import SourceCoil

__all__ = [
    "ImperfectionSpec",
    "TemperatureProfile",
    "SourceImperfection",
    "MagImperfection",
    "ImuImperfection",
    "SensorImperfection",
    "Imperfections",
    "GaussMarkov",
]

DEG = math.pi / 180.0
G0 = 9.80665


@dataclass(frozen=True)
class ImperfectionSpec:
    """The distributions the imperfections are drawn from (1-sigma unless a bound is named) and
    which groups are on. All magnitudes are stated in the module docstring with their sources."""
    source: bool = True
    mag: bool = True
    imu: bool = True
    mag_to_imu: bool = True
    coil_tilt_max_deg: float = 2.0          # tilt angle ~ U(0, max), axis perpendicular to the coil's
    coil_gain_sigma: float = 0.02           # gain ~ 1 + N(0, sigma), clipped to +-coil_gain_max
    coil_gain_max: float = 0.05
    coil_offset_sigma_m: float = 1e-3       # winding-centre offset per axis
    mag_scale_sigma: float = 0.02
    mag_cross_sigma: float = 0.01
    mag_hard_sigma_t: float = 3e-6
    mag_tempco_sigma_t_per_k: float = 10e-9
    mag_nonlin_max: float = 0.005           # k3 ~ U(0, max): the relative error at full scale
    imu_scale_sigma: float = 0.01
    imu_cross_sigma: float = 0.005
    gyro_g_sens_sigma: float = 0.1 * DEG / G0      # rad/s per m/s^2 (0.1 deg/s/g)
    gyro_instability_rad_s: float = 0.01 * DEG
    accel_instability_m_s2: float = 2e-3
    instability_tau_s: float = 100.0
    mag_to_imu_sigma_deg: float = 0.5


@dataclass(frozen=True)
class TemperatureProfile:
    """The sensor's temperature (degC) over the run: a warm-up ``T0 + rise (1 - exp(-t/tau))``
    plus a slow ripple ``ripple sin(2 pi t / period)`` (air conditioning cycling). A board warms by
    some kelvin in its first minutes after switch-on."""
    t0_c: float = 25.0
    rise_c: float = 8.0
    tau_s: float = 300.0
    ripple_c: float = 0.5
    period_s: float = 120.0

    def at(self, t_s):
        t = np.asarray(t_s, dtype=float)
        return (self.t0_c + self.rise_c * (1.0 - np.exp(-t / self.tau_s))
                + self.ripple_c * np.sin(2.0 * np.pi * t / self.period_s))


class GaussMarkov:
    """First-order Gauss-Markov process per axis, stationary, standard deviation ``sigma`` and
    correlation time ``tau`` (s): ``x_{k+1} = e^{-dt/tau} x_k + sigma sqrt(1 - e^{-2 dt/tau}) n_k``.
    A sum of such processes approximates flicker ("bias instability"); one is used here."""

    def __init__(self, sigma: float, tau_s: float, rng: np.random.Generator):
        self.sigma, self.tau_s, self.rng = float(sigma), float(tau_s), rng
        self.x = rng.normal(0.0, self.sigma, 3) if self.sigma > 0.0 else np.zeros(3)

    def step(self, dt_s: float) -> np.ndarray:
        if self.sigma > 0.0:
            a = math.exp(-dt_s / self.tau_s)
            self.x = a * self.x + self.sigma * math.sqrt(1.0 - a * a) * self.rng.normal(0.0, 1.0, 3)
        return self.x


def _perpendicular_tilt(rng: np.random.Generator, axis: np.ndarray, max_rad: float) -> np.ndarray:
    """A rotation vector perpendicular to ``axis`` (a spin about a circular coil's own axis changes
    nothing), direction uniform, angle ``U(0, max_rad)``."""
    a = axis / np.linalg.norm(axis)
    helper = np.eye(3)[int(np.argmin(np.abs(a)))]
    u = np.cross(a, helper)
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    phi = rng.uniform(0.0, 2.0 * np.pi)
    return rng.uniform(0.0, max_rad) * (math.cos(phi) * u + math.sin(phi) * v)


def _matrix(rng: np.random.Generator, scale_sigma: float, cross_sigma: float) -> np.ndarray:
    """``I + diag(N(0, scale_sigma)) + offdiag(N(0, cross_sigma))`` (3, 3)."""
    M = np.eye(3) + np.diag(rng.normal(0.0, scale_sigma, 3))
    off = rng.normal(0.0, cross_sigma, (3, 3))
    np.fill_diagonal(off, 0.0)
    return M + off


@dataclass
class SourceImperfection:
    """Per coil (rows in the source's coil order): ``tilt_rotvec`` (K, 3) rad, ``gain`` (K,),
    ``offset_m`` (K, 3) m."""
    tilt_rotvec: np.ndarray
    gain: np.ndarray
    offset_m: np.ndarray

    @classmethod
    def draw(cls, rng: np.random.Generator, axes: np.ndarray, spec: ImperfectionSpec) -> "SourceImperfection":
        K = axes.shape[0]
        tilt = np.stack([_perpendicular_tilt(rng, axes[k], spec.coil_tilt_max_deg * DEG) for k in range(K)])
        gain = 1.0 + np.clip(rng.normal(0.0, spec.coil_gain_sigma, K), -spec.coil_gain_max, spec.coil_gain_max)
        off = rng.normal(0.0, spec.coil_offset_sigma_m, (K, 3))
        return cls(tilt, gain, off)

    def apply(self, coils) -> list[SourceCoil]:
        """New :class:`hil.physics.SourceCoil` objects: each coil's winding tilted (its existing
        misalignment composed with ``tilt``), moved by ``offset`` and its filaments scaled by
        ``gain``; the geometry and electrical values otherwise copied."""
        out = []
        for k, c in enumerate(coils):
            mis = matrix_to_rotvec(rotvec_to_matrix(self.tilt_rotvec[k]) @ rotvec_to_matrix(c.misalignment))
            out.append(replace(c, center=c.center + self.offset_m[k], misalignment=mis,
                               gain=float(c.gain * self.gain[k])))
        return out


@dataclass
class MagImperfection:
    """Magnetometer: ``soft`` (3, 3), ``hard_t`` (3,) T, ``tempco_t_per_k`` (3,) T/K about
    ``temp_ref_c``, ``nonlin_k3`` (3,) relative compression at ``range_t`` (T)."""
    soft: np.ndarray
    hard_t: np.ndarray
    tempco_t_per_k: np.ndarray
    nonlin_k3: np.ndarray
    range_t: float
    temperature: TemperatureProfile = field(default_factory=TemperatureProfile)
    temp_ref_c: float = 25.0

    def offset_t(self, t_us) -> np.ndarray:
        """Temperature-dependent offset (3,) T at true time ``t_us``."""
        return self.tempco_t_per_k * (float(self.temperature.at(t_us * 1e-6)) - self.temp_ref_c)

    def linear(self, B: np.ndarray) -> np.ndarray:
        """``soft @ B + hard`` for B (3,) or (n, 3) T, magnetometer frame."""
        return np.asarray(B) @ self.soft.T + self.hard_t

    def nonlinear(self, x: np.ndarray) -> np.ndarray:
        """``x (1 - k3 (x / range)^2)`` per axis."""
        return x * (1.0 - self.nonlin_k3 * (x / self.range_t) ** 2)

    def measure(self, B_true: np.ndarray, t_us: int) -> np.ndarray:
        """What the magnetometer reads (before its flip offset, flip artefact, noise and
        quantisation, which :class:`hil.nodes.SensorNode` adds) for the field ``B_true`` (3,) T in
        its frame at true time ``t_us``."""
        return self.nonlinear(self.linear(B_true)) + self.offset_t(t_us)


@dataclass
class ImuImperfection:
    """IMU: ``accel_matrix``, ``gyro_matrix`` (3, 3), ``gyro_g_sens`` (3, 3) rad/s per m/s^2,
    ``mag_to_imu_rotvec`` (3,) rad, bias instability processes (Gauss-Markov, seeded)."""
    accel_matrix: np.ndarray
    gyro_matrix: np.ndarray
    gyro_g_sens: np.ndarray
    mag_to_imu_rotvec: np.ndarray
    gyro_instability_rad_s: float
    accel_instability_m_s2: float
    instability_tau_s: float
    seed: int = 0

    def __post_init__(self) -> None:
        self.R_mi = rotvec_to_matrix(self.mag_to_imu_rotvec)
        rng = np.random.default_rng(self.seed)
        self._gyro_bi = GaussMarkov(self.gyro_instability_rad_s, self.instability_tau_s, rng)
        self._acc_bi = GaussMarkov(self.accel_instability_m_s2, self.instability_tau_s, rng)

    def measure(self, f_mag: np.ndarray, w_mag: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Specific force (3,) m/s^2 and rate (3,) rad/s in the magnetometer frame -> what the
        accelerometer and the gyroscope read before the node's turn-on bias, random walk and noise
        (bias instability advanced by ``dt_s``)."""
        f = self.R_mi.T @ f_mag
        w = self.R_mi.T @ w_mag
        fa = self.accel_matrix @ f + self._acc_bi.step(dt_s)
        wg = self.gyro_matrix @ w + self.gyro_g_sens @ f + self._gyro_bi.step(dt_s)
        return fa, wg


@dataclass
class SensorImperfection:
    """One sensor node's magnetometer and IMU imperfections (either may be None: perfect)."""
    mag: MagImperfection | None
    imu: ImuImperfection | None
    #: the node's own turn-on biases (``hil.nodes.SensorNode.acc_bias``/``gyro_bias``), recorded
    #: when installed, for the calibration table
    accel_bias0: np.ndarray | None = None
    gyro_bias0: np.ndarray | None = None

    def record_turn_on(self, acc_bias, gyro_bias) -> None:
        """The node's own turn-on IMU biases (m/s^2, rad/s), kept for the calibration table."""
        self.accel_bias0 = np.array(acc_bias, dtype=float)
        self.gyro_bias0 = np.array(gyro_bias, dtype=float)


def _r(x, nd: int = 9):
    """Nested lists of floats rounded to ``nd`` significant-ish decimals, for the report."""
    a = np.asarray(x, dtype=float)
    return np.round(a, nd).tolist()


class Imperfections:
    """All the imperfections of one bench: the source's and each sensor node's.

    Build with :meth:`draw`; apply with :meth:`apply_source` (world coils) and :meth:`install`
    (sensor nodes); list with :meth:`listing`; write with :meth:`as_calibration_table`.
    """

    def __init__(self, seed: int, spec: ImperfectionSpec, source: SourceImperfection | None,
                 sensors: dict[int, SensorImperfection], nominal_moments: np.ndarray | None = None):
        self.seed, self.spec, self.source, self.sensors = int(seed), spec, source, sensors
        self.nominal_moments = nominal_moments

    @classmethod
    def draw(cls, seed: int, coils, sensor_ids=(16,), spec: ImperfectionSpec | None = None,
             range_t: float = 32767 * 5e-9) -> "Imperfections":
        """Seeded draw for the nominal ``coils`` (:class:`hil.physics.SourceCoil` list) and the
        sensor nodes ``sensor_ids``. Each group draws from a stream of its own (``SeedSequence``
        children), so switching one group off leaves the others' values unchanged."""
        spec = spec or ImperfectionSpec()
        ss = np.random.SeedSequence([int(seed), 14])
        s_src, s_sens = ss.spawn(2)
        axes = np.stack([c.axis for c in coils])
        source = SourceImperfection.draw(np.random.default_rng(s_src), axes, spec) if spec.source else None
        sensors = {}
        for sid, s in zip(sensor_ids, s_sens.spawn(len(sensor_ids))):
            s_mag, s_imu, s_mi, s_bi = s.spawn(4)
            mag = imu = None
            if spec.mag:
                r = np.random.default_rng(s_mag)
                mag = MagImperfection(soft=_matrix(r, spec.mag_scale_sigma, spec.mag_cross_sigma),
                                      hard_t=r.normal(0.0, spec.mag_hard_sigma_t, 3),
                                      tempco_t_per_k=r.normal(0.0, spec.mag_tempco_sigma_t_per_k, 3),
                                      nonlin_k3=r.uniform(0.0, spec.mag_nonlin_max, 3), range_t=float(range_t))
            if spec.imu or spec.mag_to_imu:
                r = np.random.default_rng(s_imu)
                A = _matrix(r, spec.imu_scale_sigma, spec.imu_cross_sigma)
                Gm = _matrix(r, spec.imu_scale_sigma, spec.imu_cross_sigma)
                Gs = r.normal(0.0, spec.gyro_g_sens_sigma, (3, 3))
                mi = np.random.default_rng(s_mi).normal(0.0, spec.mag_to_imu_sigma_deg * DEG, 3)
                if not spec.imu:
                    A, Gm, Gs = np.eye(3), np.eye(3), np.zeros((3, 3))
                imu = ImuImperfection(A, Gm, Gs, mi if spec.mag_to_imu else np.zeros(3),
                                      spec.gyro_instability_rad_s if spec.imu else 0.0,
                                      spec.accel_instability_m_s2 if spec.imu else 0.0,
                                      spec.instability_tau_s, seed=int(s_bi.generate_state(1)[0]))
            sensors[int(sid)] = SensorImperfection(mag, imu)
        nominal = np.stack([c.moment_per_amp for c in coils])
        return cls(seed, spec, source, sensors, nominal)

    # -- applying ---------------------------------------------------------------------------

    def apply_source(self, coils) -> list[SourceCoil]:
        """The coils as built (tilted, moved, scaled), or the nominal ones when the source is perfect."""
        return list(coils) if self.source is None else self.source.apply(coils)

    def install(self, sensor_nodes) -> None:
        """Attach each sensor node's imperfections (``node.imperfect``; see
        :meth:`hil.nodes.SensorNode._sensed`) and record the node's own turn-on IMU biases."""
        for node in sensor_nodes:
            si = self.sensors.get(int(node.node_id))
            if si is None:
                continue
            node.fit_imperfection(si)

    # -- reporting ---------------------------------------------------------------------------

    def listing(self) -> list[dict]:
        """Every imperfection with its value (SI units; angles also in degrees), for the report."""
        out: list[dict] = [{"what": "seed", "value": self.seed}]
        if self.source is not None:
            for k in range(self.source.gain.size):
                tilt = self.source.tilt_rotvec[k]
                out.append({"what": f"source.coil{k}.tilt_deg", "value": round(float(np.linalg.norm(tilt)) / DEG, 4),
                            "rotvec_rad": _r(tilt)})
                out.append({"what": f"source.coil{k}.gain", "value": round(float(self.source.gain[k]), 6)})
                out.append({"what": f"source.coil{k}.offset_m", "value": _r(self.source.offset_m[k])})
        for sid, si in self.sensors.items():
            p = f"sensor{sid}."
            if si.mag is not None:
                m = si.mag
                out += [{"what": p + "mag.soft", "value": _r(m.soft, 6)},
                        {"what": p + "mag.hard_t", "value": _r(m.hard_t, 10)},
                        {"what": p + "mag.tempco_t_per_k", "value": _r(m.tempco_t_per_k, 12)},
                        {"what": p + "mag.nonlin_k3_at_range", "value": _r(m.nonlin_k3, 6), "range_t": m.range_t},
                        {"what": p + "mag.temperature_profile", "value": vars(m.temperature).copy(),
                         "ref_c": m.temp_ref_c}]
            if si.imu is not None:
                u = si.imu
                out += [{"what": p + "imu.accel_matrix", "value": _r(u.accel_matrix, 6)},
                        {"what": p + "imu.gyro_matrix", "value": _r(u.gyro_matrix, 6)},
                        {"what": p + "imu.gyro_g_sensitivity_rad_s_per_m_s2", "value": _r(u.gyro_g_sens, 9)},
                        {"what": p + "imu.bias_instability", "gyro_rad_s": u.gyro_instability_rad_s,
                         "accel_m_s2": u.accel_instability_m_s2, "tau_s": u.instability_tau_s,
                         "value": "Gauss-Markov"},
                        {"what": p + "mag_to_imu_deg",
                         "value": round(float(np.linalg.norm(u.mag_to_imu_rotvec)) / DEG, 4),
                         "rotvec_rad": _r(u.mag_to_imu_rotvec)}]
        return out

    def as_calibration_table(self) -> dict:
        """The truth in the calibration file's layout (``[source]``, ``[sensor.N]``, ``[meta]``),
        every ``*_sigma`` zero (exact), ``meta.method = "truth"``. A group that is perfect is
        written as the identity (nominal)."""
        K = self.nominal_moments.shape[0] if self.nominal_moments is not None else 3
        axes = self.nominal_moments / np.linalg.norm(self.nominal_moments, axis=1, keepdims=True)
        if self.source is not None:
            mom = np.stack([self.source.gain[k] * (rotvec_to_matrix(self.source.tilt_rotvec[k]) @ axes[k])
                            for k in range(K)])
            off = self.source.offset_m
        else:
            mom, off = axes, np.zeros((K, 3))
        z = lambda a: np.zeros_like(np.asarray(a, dtype=float)).tolist()  # noqa: E731
        table: dict = {"source": {"coil_moment": mom.tolist(), "coil_moment_sigma": z(mom),
                                  "coil_offset_m": np.asarray(off).tolist(), "coil_offset_m_sigma": z(off)},
                       "sensor": {}, "meta": {"method": "truth", "imperfection_seed": self.seed}}
        for sid, si in self.sensors.items():
            m, u = si.mag, si.imu
            soft = m.soft if m is not None else np.eye(3)
            hard = m.hard_t if m is not None else np.zeros(3)
            A = u.accel_matrix if u is not None else np.eye(3)
            Gm = u.gyro_matrix if u is not None else np.eye(3)
            Gs = u.gyro_g_sens if u is not None else np.zeros((3, 3))
            mi = u.mag_to_imu_rotvec if u is not None else np.zeros(3)
            ab = si.accel_bias0 if si.accel_bias0 is not None else np.zeros(3)
            gb = si.gyro_bias0 if si.gyro_bias0 is not None else np.zeros(3)
            t = {"mag_soft": soft, "mag_hard_t": hard, "gyro_matrix": Gm, "gyro_bias_rad_s": gb,
                 "gyro_g_sensitivity": Gs, "accel_matrix": A, "accel_bias_m_s2": ab, "mag_to_imu_rotvec": mi}
            sec = {}
            for k, v in t.items():
                sec[k] = np.asarray(v, dtype=float).tolist()
                sec[k + "_sigma"] = z(v)
            table["sensor"][str(sid)] = sec
            if m is not None:      # beyond the file's keys: what the calibration model leaves uncorrected
                table["meta"].setdefault("unmodelled", {})[str(sid)] = {
                    "mag_tempco_t_per_k": m.tempco_t_per_k.tolist(), "mag_nonlin_k3": m.nonlin_k3.tolist(),
                    "gyro_instability_rad_s": u.gyro_instability_rad_s if u is not None else 0.0,
                    "accel_instability_m_s2": u.accel_instability_m_s2 if u is not None else 0.0}
        return table
