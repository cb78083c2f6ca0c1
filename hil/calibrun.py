"""Calibration runs on the imperfect bench: a positioning jig and free motion, recorded to a file.

Two recordings, both through the same imperfect sensor models as the bench's nodes
(``hil.imperfections``; the physics of ``hil.physics``, never the firmware's):

* :func:`record_grid`: a positioning jig (Anser EMT's 7 x 7 / 9 x 9 grid procedure): the sensor
  is held still at each station of an ``n_xy`` x ``n_xy`` grid of positions on several planes, at
  ``n_ori`` orientations each, whose true poses the jig knows; at every station each coil is driven
  in turn at its current and the magnetometer's samples are averaged over the coil's flat top
  (``b_on``) and over a coil-off baseline (``b_off``).
* :func:`record_free`: free motion with no ground truth for the calibration (the sensor's own
  magnetometer and IMU): the board is turned through all orientations in the earth field (the 24
  orientations of a cube, each axis up and down at four headings, then ``n_random`` more), held still
  ``still_s`` at each (gravity and the earth field constant), turned smoothly in ``move_s`` between
  them; no coil is driven. The true rotation and rates are stored for tests only.

The set/reset residual offset of the magnetometer (``hil.nodes.MagSpec.offset_t``, its sign
following the flip state) is left out: a calibration run averages both flip states, as the
firmware's flip handling does on the bench, so it cancels and is not part of the hard iron. Sample
means carry white noise ``noise_t / sqrt(n)``; quantisation (5 nT, dithered by 50 nT noise) is left
out of the means.

File: :func:`save_recording` writes one ``.npz`` (``numpy.savez``, no pickles), keys as in the
functions' docstrings plus ``kind`` ("grid" | "free") and ``meta_json`` (a JSON object: unit, seed,
node, earth field, gravity, rates, noise); :func:`load_recording` reads it back.
"""
from __future__ import annotations

import itertools
import json
import math

import numpy as np

from .imperfections import Imperfections
from .motion import matrix_to_rotvec, random_rotation, rotvec_to_matrix
from .nodes import ImuSpec, MagSpec
from .physics import EARTH_FIELD_T, Source, thesis_source

__all__ = ["record_grid", "record_free", "save_recording", "load_recording", "cube_rotations"]

NODE = 16


def _unit(unit: int, spec=None, node: int = NODE) -> tuple[Imperfections, Source]:
    nominal = thesis_source().coils
    imp = Imperfections.draw(unit, nominal, sensor_ids=(node,), spec=spec)
    return imp, Source(imp.apply_source(nominal))


def record_grid(unit: int = 1, seed: int = 0, n_xy: int = 7, x_range=(0.15, 0.35), y_range=(-0.15, 0.15),
                z_levels=(-0.05, 0.0, 0.05), n_ori: int = 3, currents_a=(1.5, 1.5, 1.5), n_on: int = 24,
                n_off: int = 24, station_s: float = 2.0, mag: MagSpec | None = None, spec=None,
                node: int = NODE) -> dict:
    """Jig recording of hardware ``unit`` (noise from ``seed``). S = n_xy^2 * len(z_levels) * n_ori
    stations (position-major; the first orientation of each position is the identity, the others
    uniformly random), K coils. Returns:

    ``p_true`` (S, 3) m and ``R_true`` (S, 3, 3) (sensor -> source) the jig's poses; ``currents_a``
    (K,) A; ``b_on`` (S, K, 3) T mean magnetometer reading (magnetometer frame) during coil k's flat
    top; ``b_off`` (S, 3) T the coil-off mean; ``n_on``, ``n_off`` samples per mean; ``noise_t``
    per-sample rms (T); ``temperature_c`` (S,) at the station (stations ``station_s`` apart);
    ``kind`` and ``meta``. ``b_on[s, k] - b_off[s]`` is ``N(soft @ (B_k + B_e) + h) - N(soft @ B_e + h)``
    (``N`` the non-linearity, ``B_k`` coil k's field at ``I_k``, ``B_e`` the earth field, both
    magnetometer frame) plus noise of rms ``noise_t * sqrt(1/n_on + 1/n_off)``."""
    mag = mag or MagSpec()
    imp, source = _unit(unit, spec, node)
    mi = imp.sensors[node].mag
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1401]))
    xs, ys = np.linspace(*x_range, n_xy), np.linspace(*y_range, n_xy)
    P, Rs = [], []
    for z, x, y in itertools.product(z_levels, xs, ys):
        for j in range(n_ori):
            P.append((x, y, z))
            Rs.append(np.eye(3) if j == 0 else random_rotation(rng))
    P, Rs = np.asarray(P, dtype=float), np.asarray(Rs)
    S, K = P.shape[0], len(source)
    I = np.asarray(currents_a, dtype=float).reshape(K)
    U = source.unit_fields(P)                                  # (K, S, 3) T/A, source frame
    b_on = np.empty((S, K, 3))
    b_off = np.empty((S, 3))
    temp = np.empty(S)
    s_on, s_off = mag.noise_t / math.sqrt(n_on), mag.noise_t / math.sqrt(n_off)
    for s in range(S):
        t_us = int(round(s * station_s * 1e6))
        Re = Rs[s].T @ EARTH_FIELD_T
        meas = (lambda B: mi.measure(B, t_us)) if mi is not None else (lambda B: B)
        b_off[s] = meas(Re) + rng.normal(0.0, s_off, 3)
        for k in range(K):
            b_on[s, k] = meas(Re + I[k] * (Rs[s].T @ U[k, s])) + rng.normal(0.0, s_on, 3)
        temp[s] = float(mi.temperature.at(t_us * 1e-6)) if mi is not None else 25.0
    meta = {"unit": int(unit), "seed": int(seed), "node": int(node), "earth_field_t": EARTH_FIELD_T.tolist(),
            "rate_hz": mag.rate_hz, "noise_t": mag.noise_t, "n_xy": n_xy, "z_levels": list(z_levels),
            "n_ori": n_ori, "station_s": station_s, "imperfection_seed": int(unit)}
    return {"kind": "grid", "meta": meta, "p_true": P, "R_true": Rs, "currents_a": I, "b_on": b_on,
            "b_off": b_off, "n_on": int(n_on), "n_off": int(n_off), "noise_t": float(mag.noise_t),
            "temperature_c": temp, "node": int(node)}


def cube_rotations() -> np.ndarray:
    """The 24 rotations of a cube (each sensor axis up and down, four headings each), (24, 3, 3)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            for i, (j, sg) in enumerate(zip(perm, signs)):
                M[i, j] = sg
            if np.linalg.det(M) > 0.0:
                out.append(M)
    return np.asarray(out)


def record_free(unit: int = 1, seed: int = 0, n_random: int = 12, still_s: float = 2.0, move_s: float = 1.5,
                rate_hz: float = 120.0, mag: MagSpec | None = None, imu: ImuSpec | None = None, spec=None,
                node: int = NODE) -> dict:
    """Free-motion recording of hardware ``unit`` (noise, random orientations, turn-on biases from
    ``seed``), all sensors at ``rate_hz`` on the same instants, sensor at a fixed point (no linear
    acceleration). Returns ``t_s`` (N,); ``mag_t`` (N, 3) T raw magnetometer; ``acc_m_s2``,
    ``gyro_rad_s`` (N, 3) raw IMU (IMU frame); ``still`` (N,) bool; ``temperature_c`` (N,); for
    tests only: ``truth_R`` (N, 3, 3) sensor -> world, ``truth_w_mag`` (N, 3) body rate and
    ``truth_f_mag`` (N, 3) specific force in the magnetometer frame, ``truth_accel_bias0``,
    ``truth_gyro_bias0`` (3,) the turn-on biases. The IMU has the node's model: turn-on bias
    ``N(0, *_bias_sigma)``, random walk, white noise at ``ImuSpec``'s densities, after the
    imperfections (``ImuImperfection.measure``)."""
    mag = mag or MagSpec()
    imu = imu or ImuSpec(rate_hz=rate_hz)
    imp, _ = _unit(unit, spec, node)
    si = imp.sensors[node]
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1402]))
    rots = list(cube_rotations()) + [random_rotation(rng) for _ in range(n_random)]
    dt = 1.0 / rate_hz
    n_still, n_move = int(round(still_s * rate_hz)), int(round(move_s * rate_hz))
    Rl, wl, still = [], [], []
    for i, Ra in enumerate(rots):
        Rl += [Ra] * n_still
        wl += [np.zeros(3)] * n_still
        still += [True] * n_still
        if i + 1 < len(rots):
            v = matrix_to_rotvec(Ra.T @ rots[i + 1])
            # the turn lasts (n_move + 1) sample intervals, from the last still sample to the next one
            T_move = (n_move + 1) * dt
            for j in range(n_move):
                tau = (j + 1) / (n_move + 1)
                sm = 3 * tau**2 - 2 * tau**3
                ds = 6 * tau * (1 - tau) / T_move
                Rl.append(Ra @ rotvec_to_matrix(sm * v))
                wl.append(ds * v)
                still.append(False)
    R = np.asarray(Rl)
    w = np.asarray(wl)
    N = R.shape[0]
    t_s = np.arange(N) * dt
    g = np.array([0.0, 0.0, -imu.gravity])
    f_mag = np.einsum("nji,j->ni", R, -g)                     # R^T (a - g), a = 0
    B = np.einsum("nji,j->ni", R, EARTH_FIELD_T)
    acc_b = rng.normal(0.0, imu.acc_bias_sigma, 3)
    gyr_b = rng.normal(0.0, imu.gyro_bias_sigma, 3)
    acc_b0, gyr_b0 = acc_b.copy(), gyr_b.copy()
    mag_out = np.empty((N, 3))
    acc = np.empty((N, 3))
    gyr = np.empty((N, 3))
    temp = np.empty(N)
    for n in range(N):
        t_us = int(round(t_s[n] * 1e6))
        mag_out[n] = (si.mag.measure(B[n], t_us) if si.mag is not None else B[n]) + rng.normal(0.0, mag.noise_t, 3)
        f, ww = (si.imu.measure(f_mag[n], w[n], dt) if si.imu is not None else (f_mag[n], w[n]))
        acc_b += rng.normal(0.0, imu.acc_bias_rw * math.sqrt(dt), 3)
        gyr_b += rng.normal(0.0, imu.gyro_bias_rw * math.sqrt(dt), 3)
        acc[n] = f + acc_b + rng.normal(0.0, imu.acc_noise_density * math.sqrt(rate_hz / 2.0), 3)
        gyr[n] = ww + gyr_b + rng.normal(0.0, imu.gyro_noise_density * math.sqrt(rate_hz / 2.0), 3)
        temp[n] = float(si.mag.temperature.at(t_s[n])) if si.mag is not None else 25.0
    meta = {"unit": int(unit), "seed": int(seed), "node": int(node), "earth_field_t": EARTH_FIELD_T.tolist(),
            "gravity": imu.gravity, "rate_hz": rate_hz, "noise_t": mag.noise_t,
            "acc_sigma": imu.acc_noise_density * math.sqrt(rate_hz / 2.0),
            "gyro_sigma": imu.gyro_noise_density * math.sqrt(rate_hz / 2.0),
            "still_s": still_s, "move_s": move_s, "imperfection_seed": int(unit)}
    return {"kind": "free", "meta": meta, "t_s": t_s, "mag_t": mag_out, "acc_m_s2": acc, "gyro_rad_s": gyr,
            "still": np.asarray(still, dtype=bool), "temperature_c": temp, "rate_hz": float(rate_hz),
            "truth_R": R, "truth_w_mag": w, "truth_f_mag": f_mag, "truth_accel_bias0": acc_b0,
            "truth_gyro_bias0": gyr_b0, "node": int(node)}


def save_recording(rec: dict, path) -> None:
    """Write a recording as one ``.npz`` (``meta`` as the JSON string ``meta_json``)."""
    arrays = {k: np.asarray(v) for k, v in rec.items() if k != "meta"}
    arrays["meta_json"] = np.asarray(json.dumps(rec["meta"]))
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def load_recording(path) -> dict:
    """Read a recording written by :func:`save_recording` (``kind`` a str, ``meta`` a dict, 0-d
    numbers as Python scalars)."""
    with np.load(path, allow_pickle=False) as z:
        out = {}
        for k in z.files:
            a = z[k]
            out[k] = a.item() if a.ndim == 0 else a
    out["meta"] = json.loads(out.pop("meta_json"))
    out["kind"] = str(out["kind"])
    return out
