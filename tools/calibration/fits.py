"""The fits of ``coiltrack calibrate``: a calibration recording (``hil.calibrun``
layout, or a real jig's in the same layout) in, the calibration file's tables
(``firmware_py/calibration.py``) out, each parameter with its 1-sigma.

Uncertainty: the weighted residuals ``r / sigma`` at the solution, their
Jacobian ``J`` and ``cov = (J^T J)^-1 * chi2 / dof`` (the residual variance
scales the covariance, so unmodelled effects -- the magnetometer's
non-linearity, its temperature offset -- widen the sigmas instead of being
hidden). ``residual_rms`` in ``[meta]`` is the RMS of the unweighted
residuals in the measurement's unit.

grid (a positioning jig, Anser's 7 x 7 / 9 x 9 procedures)
    Parameters: per coil the relative moment ``m_k`` (3) and the winding
    offset ``o_k`` (3, m); the magnetometer's ``mag_soft`` (9) and constant
    offset ``mag_hard_t`` (3, T). Data at station ``s`` (known ``p_s``,
    ``R_s``): coil-on minus coil-off means
    ``b_on[s,k] - b_off[s] = mag_soft R_s^T I_k B_k(p_s; m_k, o_k)`` (the
    firmware's own exact-loop model, ``model/field.py``, Schepers & Veltink
    ``000`` eqs 6-7, so the file fits the model it will correct) and the
    coil-off means ``b_off[s] = mag_soft R_s^T E + mag_hard_t`` (``E`` the
    earth field, which the known orientations make the magnetometer's
    reference: without it the soft-iron scale and the coil gains trade off
    exactly). Nonlinear least squares (scipy ``least_squares``, trust region).

free (no ground truth: the sensor's own magnetometer and IMU)
    magnetometer: ellipsoid fit ``|mag_soft^-1 (b - h)| = |E|`` over all
    samples (``mag_soft`` symmetric: the rotation part is not observable from
    the magnitude; the grid gives it); accelerometer: the still periods' means
    with ``|A^-1 (f - b_a)| = g`` (A symmetric likewise); gyroscope: in still
    periods ``w = b_g + Gg f_i`` (linear, with ``f_i`` the corrected force),
    then the gyro matrix ``G`` and ``mag_to_imu_rotvec`` from the rotation
    between consecutive still periods: integrated (corrected) gyro against
    the change of the accelerometer's and magnetometer's directions (TRIAD).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.model.field import Coil

from ..scenarios.distortion import STEEL_TABLE
from .survey import register as _register_survey

__all__ = ["fit_grid", "fit_free", "METHODS", "T_REF_C"]

#: the temperature the magnetometer's constant offset (``mag_hard_t``) refers to, degC
T_REF_C = 25.0


def _cov(res, dof_min=1):
    """(cov, chi2/dof) of a scipy least_squares result on weighted residuals."""
    J = res.jac
    dof = max(J.shape[0] - J.shape[1], dof_min)
    s2 = float(res.fun @ res.fun) / dof
    JtJ = J.T @ J
    cov = np.linalg.pinv(JtJ) * s2
    return cov, s2


# ---------------------------------------------------------------------- grid
def fit_grid(rec: dict, cfg: FirmwareConfig | None = None) -> dict:
    """Source moments and offsets (and the magnetometer's soft and hard iron)
    from a jig recording; returns the calibration tables ``{"source", "sensor", "meta"}``.

    ``rec``: ``p_true`` (S, 3), ``R_true`` (S, 3, 3) sensor->source, ``currents_a`` (K,),
    ``b_on`` (S, K, 3), ``b_off`` (S, 3) T, ``n_on``, ``n_off``, ``noise_t``, ``meta``
    (``earth_field_t`` (3,) source frame, ``node``).
    """
    cfg = cfg or FirmwareConfig()
    model = _GridModel(rec, cfg)
    res = least_squares(model.resid, model.x0(), method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                        max_nfev=200)
    cov, s2 = _cov(res)
    sd = np.sqrt(np.diag(cov))
    m, o, soft, hard, tc, k3 = model.unpack(res.x)
    ms, os_, softs, hards, tcs, k3s = model.unpack(sd)
    n_d = model.S * model.K * 3
    rms = math.sqrt(float(np.mean((res.fun[:n_d] * model.sig_on) ** 2)))
    tables = {"meta": {"method": "grid", "poses": int(model.S), "residual_rms": rms, "residual_unit": "T",
                       "chi2_per_dof": s2, "iterations": int(res.nfev)},
              "source": {"coil_moment": m.tolist(), "coil_moment_sigma": ms.tolist(),
                         "coil_offset_m": o.tolist(), "coil_offset_m_sigma": os_.tolist()}}
    sec = {"mag_soft": soft.tolist(), "mag_soft_sigma": np.abs(softs).tolist(),
           "mag_hard_t": hard.tolist(), "mag_hard_t_sigma": np.abs(hards).tolist()}
    tables["sensor"] = {str(model.node): sec}
    # fitted beside them, not applied by the firmware (its samples carry no temperature; the
    # non-linearity is below the noise away from the source): reported in [meta]
    tables["meta"].update({"mag_tempco_t_per_k": tc.tolist(), "mag_tempco_t_per_k_sigma": np.abs(tcs).tolist(),
                           "mag_nonlin_k3": k3.tolist(), "mag_nonlin_k3_sigma": np.abs(k3s).tolist(),
                           "temp_ref_c": T_REF_C})
    return tables


class _GridModel:
    """The grid fit's measurement model (module docstring) on one recording: the parameter
    vector ``x = [m (3K), o (3K) mm, soft (9), hard (3) uT, tempco (3) nT/K, k3 (3) %]``
    and the weighted residuals of the coil-on and coil-off means."""

    def __init__(self, rec: dict, cfg: FirmwareConfig):
        self.P = np.asarray(rec["p_true"], float)
        self.Rs = np.asarray(rec["R_true"], float)
        self.I = np.asarray(rec["currents_a"], float)
        self.b_on = np.asarray(rec["b_on"], float)
        self.b_off = np.asarray(rec["b_off"], float)
        self.S, self.K = self.b_on.shape[0], self.b_on.shape[1]
        if len(cfg.source.coils) != self.K:
            raise ValueError(f"the recording has {self.K} coils, the configuration {len(cfg.source.coils)}")
        meta = rec.get("meta", {})
        E = np.asarray(meta.get("earth_field_t", [0.0, 0.0, 0.0]), float).reshape(3)
        self.node = int(rec.get("node", meta.get("node", cfg.link.sensor_ids[0])))
        noise = float(rec["noise_t"])
        self.sig_on = noise / math.sqrt(int(rec["n_on"]))
        self.sig_o = noise / math.sqrt(int(rec["n_off"]))
        self.nom = cfg.source.coils
        if not np.linalg.norm(E) > 0:
            raise ValueError("the grid fit needs the earth field (meta.earth_field_t): it fixes the soft-iron scale")
        self.T = np.asarray(rec.get("temperature_c", np.full(self.S, T_REF_C)), float) - T_REF_C
        self.rng_t = float(cfg.pulse.mag_range_t)
        self.Be = np.einsum("sji,j->si", self.Rs, E)            # earth field, sensor frame (S, 3)

    def x0(self) -> np.ndarray:
        axes = np.array([np.asarray(c.axis, float) / np.linalg.norm(c.axis) for c in self.nom])
        return np.concatenate([axes.reshape(-1), np.zeros(3 * self.K), np.eye(3).reshape(-1),
                               np.mean(self.b_off - self.Be, axis=0) * 1e6, np.zeros(3), np.zeros(3)])

    def unpack(self, x):
        K = self.K
        n_src = 6 * K
        m = x[:3 * K].reshape(K, 3)
        o = x[3 * K:6 * K].reshape(K, 3) * 1e-3
        soft = x[n_src:n_src + 9].reshape(3, 3)
        hard = x[n_src + 9:n_src + 12] * 1e-6
        tc = x[n_src + 12:n_src + 15] * 1e-9
        k3 = x[n_src + 15:n_src + 18] * 1e-2
        return m, o, soft, hard, tc, k3

    def coil_fields(self, m, o):
        out = np.empty((self.K, self.S, 3))
        for k, c in enumerate(self.nom):
            g = float(np.linalg.norm(m[k]))
            coil = Coil(np.asarray(c.center, float) + o[k], m[k] / g, c.radius, c.turns, gain=g)
            out[k] = coil.field(self.P, self.I[k], model="exact")
        return out

    def reading(self, x_lin, k3):
        return x_lin * (1.0 - k3 * (x_lin / self.rng_t) ** 2)

    def resid(self, x):
        m, o, soft, hard, tc, k3 = self.unpack(x)
        T, Be = self.T, self.Be
        B = self.coil_fields(m, o)                                   # (K, S, 3) source frame
        Bs = np.einsum("sji,ksj->ski", self.Rs, B) + Be[:, None, :]  # sensor frame R^T B + earth
        on = self.reading(np.einsum("ij,skj->ski", soft, Bs) + hard, k3) + (T[:, None] * tc)[:, None, :]
        off = self.reading(Be @ soft.T + hard, k3) + T[:, None] * tc
        return np.concatenate([((self.b_on - on) / self.sig_on).reshape(-1),
                               ((self.b_off - off) / self.sig_o).reshape(-1)])


# ---------------------------------------------------------------------- free
def _segments(still: np.ndarray, min_len: int):
    """(start, end) index pairs of the still runs at least ``min_len`` long."""
    out, i, n = [], 0, len(still)
    while i < n:
        if still[i]:
            j = i
            while j < n and still[j]:
                j += 1
            if j - i >= min_len:
                out.append((i, j))
            i = j
        else:
            i += 1
    return out


def _sym(v):
    return np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])


def _ellipsoid(X: np.ndarray, radius: float, sigma: np.ndarray, temp=None, range_t: float = 0.0):
    """``|Minv (x_lin - c)| = radius`` with ``Minv`` symmetric: returns M (= inv Minv),
    c, their sigmas (M's by first-order propagation), residual rms. With ``temp``
    (N,) degC about :data:`T_REF_C` and ``range_t`` > 0 the reading is taken as the
    magnetometer's ``x = N(x_lin) + tc * temp``, ``N(v) = v (1 - k3 (v / range)^2)``,
    and ``tc``, ``k3`` (3 each) are fitted beside (the bench's temperature offset
    and non-linearity, which would otherwise bend the ellipsoid)."""
    c0 = X.mean(axis=0)
    extra = temp is not None and range_t > 0
    x0 = np.concatenate([[1, 1, 1, 0, 0, 0], c0 / radius, np.zeros(6) if extra else []])

    def lin(x):
        if not extra:
            return X
        tc = x[9:12] * 1e-9
        k3 = x[12:15] * 1e-2
        y = X - temp[:, None] * tc
        return y * (1.0 + k3 * (y / range_t) ** 2)          # N^-1 to first order in k3

    def resid(x):
        Mi = _sym(x[:6])
        return (np.linalg.norm((lin(x) / radius - x[6:9]) @ Mi.T, axis=1) - 1.0) * radius / sigma

    res = least_squares(resid, x0, method="lm", xtol=1e-14, ftol=1e-14)
    cov, s2 = _cov(res)
    Mi = _sym(res.x[:6])
    M = np.linalg.inv(Mi)
    c = res.x[6:9] * radius
    # sigmas of M's elements by finite differences of inv(Minv) along the parameter covariance
    Jm = np.zeros((9, 6))
    for i in range(6):
        dx = np.zeros(6)
        dx[i] = 1e-7
        Jm[:, i] = (np.linalg.inv(_sym(res.x[:6] + dx)) - M).reshape(9) / 1e-7
    Ms = np.sqrt(np.maximum(np.diag(Jm @ cov[:6, :6] @ Jm.T), 0.0)).reshape(3, 3)
    cs = np.sqrt(np.diag(cov[6:9, 6:9])) * radius
    rms = math.sqrt(float(np.mean((res.fun * sigma) ** 2)))
    return M, c, Ms, cs, rms


def _triad(a, b):
    """Rotation whose columns are the orthonormal frame of (a, b) (a first)."""
    e1 = a / np.linalg.norm(a)
    e2 = np.cross(a, b)
    e2 /= np.linalg.norm(e2)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=1)


def fit_free(rec: dict, cfg: FirmwareConfig | None = None) -> dict:
    """Magnetometer ellipsoid, accelerometer, gyroscope and magnetometer-to-IMU
    rotation from a free-motion recording (no ground truth used); returns the
    ``{"sensor", "meta"}`` tables.

    ``rec``: ``t_s`` (N,), ``mag_t`` (N, 3) T, ``acc_m_s2`` (N, 3), ``gyro_rad_s`` (N, 3) (IMU frame),
    ``still`` (N,) bool, ``meta`` (``earth_field_t``, ``gravity``, ``noise_t``, ``acc_sigma``,
    ``gyro_sigma``, ``node``).
    """
    meta = rec.get("meta", {})
    node = int(rec.get("node", meta.get("node", 1)))
    t = np.asarray(rec["t_s"], float)
    g0 = float(meta.get("gravity", 9.80665))
    Emag = float(np.linalg.norm(np.asarray(meta.get("earth_field_t", [49e-6]), float)))
    rate = 1.0 / float(np.median(np.diff(t)))
    st = _StillMeans(rec, rate)
    # magnetometer and accelerometer ellipsoids on the still means
    range_t = float(cfg.pulse.mag_range_t) if cfg is not None else 32767 * 5e-9
    Ms, hm, Mss, hms, rms_m = _ellipsoid(st.mm, Emag, st.s_mag, st.tm, range_t)
    A, ba, As, bas, rms_a = _ellipsoid(st.am, g0, st.s_acc)
    Ai, Mi = np.linalg.inv(A), np.linalg.inv(Ms)
    fi = (st.am - ba) @ Ai.T                                 # corrected specific force, IMU frame
    bm = (st.mm - hm) @ Mi.T                                 # corrected field, magnetometer frame
    bg, Gg, bgs, Ggs = _gyro_at_rest(t, st, fi)
    acc = np.asarray(rec["acc_m_s2"], float)
    gyr = np.asarray(rec["gyro_rad_s"], float)
    w_mv, dts = _motion_rates(t, rate, st.segs, acc, gyr, ba, Ai, bg, Gg)
    res = least_squares(lambda x: _rotation_resid(x, w_mv, dts, fi, bm), np.zeros(12), method="lm",
                        xtol=1e-12, ftol=1e-12)
    cov, s2r = _cov(res)
    sd = np.sqrt(np.diag(cov))
    G = np.eye(3) + res.x[:9].reshape(3, 3)
    rv = res.x[9:12]
    rms_rot = math.sqrt(float(np.mean((res.fun * 1e-3) ** 2)))
    sec = {"mag_soft": Ms.tolist(), "mag_soft_sigma": Mss.tolist(), "mag_hard_t": hm.tolist(),
           "mag_hard_t_sigma": hms.tolist(),
           "accel_matrix": A.tolist(), "accel_matrix_sigma": As.tolist(), "accel_bias_m_s2": ba.tolist(),
           "accel_bias_m_s2_sigma": bas.tolist(),
           "gyro_bias_rad_s": bg.tolist(), "gyro_bias_rad_s_sigma": bgs.tolist(),
           "gyro_g_sensitivity": Gg.tolist(), "gyro_g_sensitivity_sigma": Ggs.tolist(),
           "gyro_matrix": G.tolist(), "gyro_matrix_sigma": sd[:9].reshape(3, 3).tolist(),
           "mag_to_imu_rotvec": rv.tolist(), "mag_to_imu_rotvec_sigma": sd[9:12].tolist()}
    return {"meta": {"method": "free", "poses": len(st.segs), "residual_rms": rms_m, "residual_unit": "T",
                     "accel_residual_rms_m_s2": rms_a, "rotation_residual_rms_rad": rms_rot,
                     "chi2_per_dof": s2r},
            "sensor": {str(node): sec}}


class _StillMeans:
    """The still periods of a free recording (at least 9, each at least 0.5 s; their edges
    dropped: the board settles) and each one's mean field, force and rate with its sigma."""

    def __init__(self, rec: dict, rate: float):
        meta = rec.get("meta", {})
        t = np.asarray(rec["t_s"], float)
        mag = np.asarray(rec["mag_t"], float)
        acc = np.asarray(rec["acc_m_s2"], float)
        gyr = np.asarray(rec["gyro_rad_s"], float)
        segs = _segments(np.asarray(rec["still"], bool), max(4, int(0.5 * rate)))
        if len(segs) < 9:
            raise ValueError(f"the recording holds {len(segs)} still periods; the free fit needs at least 9")
        trim = lambda a, b: (a + (b - a) // 5, b - (b - a) // 5)  # noqa: E731
        self.segs = segs = [trim(a, b) for a, b in segs]
        self.mm = np.array([mag[a:b].mean(axis=0) for a, b in segs])
        self.am = np.array([acc[a:b].mean(axis=0) for a, b in segs])
        self.wm = np.array([gyr[a:b].mean(axis=0) for a, b in segs])
        nn = np.array([b - a for a, b in segs], float)
        self.s_mag = float(meta.get("noise_t", 5e-8)) / np.sqrt(nn)
        self.s_acc = float(meta.get("acc_sigma", 0.01)) / np.sqrt(nn)
        self.s_gyr = float(meta.get("gyro_sigma", 0.005)) / np.sqrt(nn)
        self.tm = None
        if "temperature_c" in rec:
            temp = np.asarray(rec["temperature_c"], float)
            self.tm = np.array([temp[a:b].mean() for a, b in segs]) - T_REF_C
        self.t_mid = np.array([t[a:b].mean() for a, b in segs])


def _gyro_at_rest(t, st: _StillMeans, fi):
    """Gyro bias and g-sensitivity: at rest ``w_meas = b_g(t) + Gg f_i``; the bias drifts
    (random walk, instability), taken as linear in time over the recording (the bias written
    is its mean). Returns ``(b_g, Gg, sigma b_g, sigma Gg)``."""
    s_gyr = st.s_gyr
    tc = st.t_mid - st.t_mid.mean()
    X = np.hstack([np.ones((len(st.segs), 1)), tc[:, None], fi])   # (n, 5)
    coef, *_ = np.linalg.lstsq(X / s_gyr[:, None], st.wm / s_gyr[:, None], rcond=None)
    r = st.wm - X @ coef
    dof = max(len(st.segs) - X.shape[1], 1)
    XtXi = np.linalg.inv((X / s_gyr[:, None]).T @ (X / s_gyr[:, None]))
    s2g = np.array([float(np.sum((r[:, i] / s_gyr) ** 2)) / dof for i in range(3)])
    cs = np.sqrt(np.outer(np.diag(XtXi), s2g))               # (5, 3)
    return coef[0], coef[2:].T, cs[0], cs[2:].T


def _motion_rates(t, rate, segs, acc, gyr, ba, Ai, bg, Gg):
    """The corrected rates between consecutive still periods, padded to one length (zero
    rate = no rotation): ``(w (npairs, L, 3), dt (npairs, L))``."""
    pairs = [(segs[i][1], segs[i + 1][0]) for i in range(len(segs) - 1)]
    L = max(b - a for a, b in pairs)
    idx = np.zeros((len(pairs), L), dtype=int)
    valid = np.zeros((len(pairs), L), dtype=bool)
    for n, (a, b) in enumerate(pairs):
        idx[n, :b - a] = np.arange(a, b)
        valid[n, :b - a] = True
    dts = np.where(valid, np.diff(np.append(t, t[-1] + 1.0 / rate))[idx], 0.0)
    f_mv = (acc[idx] - ba) @ Ai.T                            # (npairs, L, 3)
    return gyr[idx] - bg - f_mv @ Gg.T, dts


def _integrate_all(w_mv, dts, G):
    """Integrated rotation matrices (npairs, 3, 3), IMU frame, with gyro matrix G (quaternions)."""
    npairs, L = dts.shape
    w = (w_mv @ np.linalg.inv(G).T) * dts[:, :, None]
    q = np.zeros((npairs, 4))
    q[:, 0] = 1.0
    ang = np.linalg.norm(w, axis=2)
    half = 0.5 * ang
    sinc = np.where(ang > 1e-12, np.sin(half) / np.where(ang > 1e-12, ang, 1.0), 0.5)
    dq = np.concatenate([np.cos(half)[:, :, None], w * sinc[:, :, None]], axis=2)
    for k in range(L):
        a0, a1, a2, a3 = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
        b0, b1, b2, b3 = dq[:, k, 0], dq[:, k, 1], dq[:, k, 2], dq[:, k, 3]
        q = np.stack([a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3, a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
                      a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1, a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0], axis=1)
    return Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()


def _rotation_resid(x, w_mv, dts, fi, bm):
    """Integrated gyro (gyro matrix ``I + x[:9]``) against the rotation between consecutive still
    periods from (gravity, field) by TRIAD, through the IMU->mag rotation ``x[9:12]``: in each
    sensor's own frame (gravity in the IMU frame, field in the magnetometer frame); mrad."""
    G = np.eye(3) + x[:9].reshape(3, 3)
    Rmi = Rotation.from_rotvec(x[9:12]).as_matrix()
    Q = _integrate_all(w_mv, dts, G)
    out = []
    for i in range(len(Q)):
        # world-from-mag at still i from (gravity, field) in the mag frame (TRIAD):
        # R_w_i = T_w T_i^T, so the body rotation R_w_i^T R_w_{i+1} = T_i T_{i+1}^T
        T0 = _triad(Rmi @ fi[i], bm[i])
        T1 = _triad(Rmi @ fi[i + 1], bm[i + 1])
        dR_imu = Rmi.T @ (T0 @ T1.T) @ Rmi
        out.append(Rotation.from_matrix(Q[i].T @ dR_imu).as_rotvec())
    return np.concatenate(out) / 1e-3

def _record_grid(unit: int, seed: int, grid: int) -> dict:
    from coiltrack.hil import calibrun

    return calibrun.record_grid(unit=unit, seed=seed, n_xy=grid)


def _record_free(unit: int, seed: int, grid: int) -> dict:
    from coiltrack.hil import calibrun

    return calibrun.record_free(unit=unit, seed=seed)


#: ``coiltrack calibrate --method NAME``: ``fit(recording, cfg) -> tables``, and for ``--record``
#: ``record(unit, seed, grid) -> recording`` on the emulated bench (a further method, e.g. the
#: distortion survey, registers itself in both)
METHODS = {"grid": fit_grid, "free": fit_free}
RECORDERS = {"grid": _record_grid, "free": _record_free}
# the distortion survey (--method survey) of the steel-table room
_register_survey(METHODS, RECORDERS, STEEL_TABLE)
