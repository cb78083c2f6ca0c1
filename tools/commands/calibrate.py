"""Estimate the source's and the sensor's imperfections from a calibration
run and write the calibration file (TOML) that ``bench --calibration`` and
``firmware --calibration`` apply.

Methods: ``grid`` (a positioning jig: the sensor still at known poses, each
coil driven in turn; fits the coil moments and offsets and the
magnetometer's soft and hard iron), ``free`` (free motion with still
periods, no ground truth: the magnetometer's ellipsoid, the accelerometer,
the gyroscope's bias, g-sensitivity and matrix, the magnetometer-to-IMU
rotation). The run is read from ``--input`` (a ``.npz`` recording in the
layout of ``coiltrack.hil.calibrun``) or recorded on the emulated bench
(``--record``, the imperfect bench's hardware unit ``--unit``). Every
parameter is written with its 1-sigma; ``[meta]`` holds the method, the
date, the residual RMS and the number of poses. ``--merge FILE`` keeps the
tables of an earlier file that this method does not fit (e.g. ``free``
then ``grid``)."""
from __future__ import annotations

import datetime
import sys

from .. import args as A
from ..inputs.infile import InputFileError
from ..inputs.userconfig import load_over
from ..stopping import held_signals, Stopped

HELP = "estimate a calibration file from a calibration run (grid of known poses, free motion)"
EXIT = {130: "stopped by SIGINT: no calibration written; a recording made by --record is kept (in --recording, "
             "else OUT.recording.npz) for --input",
        143: "stopped by SIGTERM: likewise"}


def add_arguments(p) -> None:
    # imported where used here and below: the fits (scipy underneath) load only when needed, not for --help
    from ..calibration.fits import METHODS

    p.add_argument("--method", choices=sorted(METHODS), required=True, help="the calibration procedure")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--input", type=A.input_file, metavar="FILE", help="a recorded calibration run (.npz)")
    src.add_argument("--record", action="store_true",
                     help="record the run on the emulated imperfect bench (coiltrack.hil.calibrun)")
    p.add_argument("--unit", type=A.integer(0, 2**32 - 1), default=1,
                   help="--record: the bench hardware unit (imperfection seed; default 1, the imperfect scenarios')")
    p.add_argument("--seed", type=A.seed, default=1, help="--record: noise seed (default 1)")
    p.add_argument("--grid", type=A.integer(2, 15), default=7, metavar="N",
                   help="--record --method grid: N x N positions per plane (Anser's 7 or 9; default 7)")
    p.add_argument("--config", type=A.input_file, metavar="FILE",
                   help="TOML firmware configuration (the nominal source the moments refer to)")
    p.add_argument("--merge", type=A.input_file, metavar="FILE",
                   help="an earlier calibration file whose other tables are kept")
    p.add_argument("--write-biases", action="store_true",
                   help="--method free: write the accelerometer and gyroscope biases into the sensor table "
                        "(default: reported in [meta] only; a MEMS turn-on bias changes at every power-up and the "
                        "fusion filter estimates it, so another session's bias is no correction)")
    p.add_argument("--out", type=A.output_path, metavar="FILE", required=True, help="the calibration file to write")
    p.add_argument("--recording", type=A.output_path, metavar="FILE",
                   help="--record: also write the recording (.npz, read back by --input) as soon as it is recorded. "
                        "A calibration stopped (SIGINT, SIGTERM) while fitting writes it anyway, here or, without "
                        "this option, to the --out file with the suffix .recording.npz")


def _load_input(path, method):
    import zipfile

    import numpy as np

    try:
        from coiltrack.hil.calibrun import load_recording

        rec = load_recording(path)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        return f"--input {path}: not a calibration recording ({exc})"
    kind = str(np.asarray(rec.get("kind", "")))
    if kind != method:
        return f"--input {path}: a '{kind}' recording, not one for --method {method}"
    return rec


_MAG = ("mag_soft", "mag_soft_sigma", "mag_hard_t", "mag_hard_t_sigma")


def _merge_sensor(new: dict, old: dict, new_grid: bool, old_grid: bool) -> dict:
    """One node's keys, ``new`` over ``old``; except that a grid's magnetometer
    (``mag_soft`` with its rotation, fixed by the known orientations) wins over
    a free fit's (symmetric: the rotation ``U`` is not observable from the
    magnitude), and the free fit's ``mag_to_imu_rotvec``, which refers to the
    frame ``U`` rotates, is carried into the grid's: ``R_mi = U^T R_mi_free``
    with ``U`` the rotation of the polar factorisation of
    ``mag_soft_free^-1 mag_soft_grid``."""
    import numpy as np
    from scipy.linalg import polar
    from scipy.spatial.transform import Rotation

    out = dict(old)
    out.update(new)
    grid, free = (new, old) if new_grid and not old_grid else (old, new) if old_grid and not new_grid else (None, None)
    if grid is None or "mag_soft" not in grid or "mag_soft" not in free:
        return out
    for k in _MAG:
        if k in grid:
            out[k] = grid[k]
    if "mag_to_imu_rotvec" in free:
        U = polar(np.linalg.solve(np.array(free["mag_soft"]), np.array(grid["mag_soft"])), side="right")[0]
        R = U.T @ Rotation.from_rotvec(free["mag_to_imu_rotvec"]).as_matrix()
        out["mag_to_imu_rotvec"] = Rotation.from_matrix(R).as_rotvec().tolist()
    return out


def merge_tables(new: dict, old: dict) -> dict:
    """``new`` over ``old``, sensor node by node and key by key (a grid's
    magnetometer over a free fit's: :func:`_merge_sensor`); the ``[meta]``
    of both kept (the old one as ``meta.merged``)."""
    out = {k: v for k, v in old.items() if k not in ("meta", "sensor")}
    for k, v in new.items():
        if k not in ("meta", "sensor"):
            out[k] = v
    new_grid = new.get("meta", {}).get("method") == "grid"
    old_grid = old.get("meta", {}).get("method") == "grid" or \
        old.get("meta", {}).get("merged", {}).get("method") == "grid"
    sensors = {n: dict(t) for n, t in old.get("sensor", {}).items()}
    for n, t in new.get("sensor", {}).items():
        sensors[n] = _merge_sensor(t, sensors.get(n, {}), new_grid, old_grid)
    if sensors:
        out["sensor"] = sensors
    meta = dict(new.get("meta", {}))
    if "meta" in old:
        meta["merged"] = {k: v for k, v in old["meta"].items() if not isinstance(v, dict)}
    out["meta"] = meta
    return out


def recording_path(args) -> str:
    """Where a recording is kept: ``--recording``, else beside ``--out`` (suffix ``.recording.npz``)."""
    from pathlib import Path

    return args.recording or str(Path(args.out).with_suffix(".recording.npz"))


def _save_recording(rec: dict, path) -> None:
    from coiltrack.hil.calibrun import save_recording

    save_recording(rec, path)
    print(f"coiltrack calibrate: recording written to {path}")


def _stopped_fitting(args, rec: dict, exc) -> int:
    """SIGINT or SIGTERM during the fit: no calibration file, but a recording made here is
    kept (written now if ``--recording`` has not already), to fit later with ``--input``."""
    if args.record:
        path = recording_path(args)
        with held_signals():       # a second signal waits for the recording to be written
            if not args.recording:
                try:
                    _save_recording(rec, path)
                except (OSError, TypeError, ValueError) as err:
                    print(f"coiltrack calibrate: stopped by {exc.reason}; the recording could not be kept in "
                          f"{path}: {err}", file=sys.stderr)
                    return exc.exit_code
        print(f"coiltrack calibrate: stopped by {exc.reason} while fitting: no calibration written; the recording "
              f"is kept in {path} (fit it with --input {path})", file=sys.stderr)
    else:
        print(f"coiltrack calibrate: stopped by {exc.reason} while fitting {args.input}: no calibration written",
              file=sys.stderr)
    return exc.exit_code


def run(args) -> int:
    from coiltrack.firmware.calibration import Calibration, CalibrationError, dumps_toml
    from coiltrack.firmware.config import ConfigError, FirmwareConfig

    from ..calibration.fits import METHODS

    try:
        cfg = load_over(args.config, FirmwareConfig()) if args.config else FirmwareConfig()
    except InputFileError as exc:
        print(f"coiltrack calibrate: --config {exc}", file=sys.stderr)
        return 2
    except ConfigError as exc:
        print(f"coiltrack calibrate: --config {args.config}: {exc}", file=sys.stderr)
        return 2
    old = None
    if args.merge:
        from ..inputs.calibfile import read_table

        try:
            old = read_table(args.merge)
            Calibration.from_table(old, len(cfg.source.coils))
        except InputFileError as exc:
            print(f"coiltrack calibrate: --merge {exc}", file=sys.stderr)
            return 2
        except CalibrationError as exc:
            print(f"coiltrack calibrate: --merge {args.merge}: {exc}", file=sys.stderr)
            return 2
    if args.input:
        rec = _load_input(args.input, args.method)
        if isinstance(rec, str):
            print(f"coiltrack calibrate: {rec}", file=sys.stderr)
            return 2
    else:
        from ..calibration.fits import RECORDERS

        rec = RECORDERS[args.method](args.unit, args.seed, args.grid)
        if args.recording:
            _save_recording(rec, args.recording)
    try:
        tables = METHODS[args.method](rec, cfg)
    except ValueError as exc:
        print(f"coiltrack calibrate: {exc}", file=sys.stderr)
        return 2
    except Stopped as exc:
        return _stopped_fitting(args, rec, exc)
    if args.method == "free" and not args.write_biases:
        for sec in tables.get("sensor", {}).values():
            for k in ("accel_bias_m_s2", "gyro_bias_rad_s"):
                for kk in (k, k + "_sigma"):
                    if kk in sec:
                        tables["meta"]["recording_" + kk] = sec.pop(kk)
    tables["meta"]["date"] = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    if old is not None:
        tables = merge_tables(tables, old)
    Calibration.from_table(tables, len(cfg.source.coils))      # what is written must load
    with open(args.out, "w") as fh:
        fh.write(dumps_toml(tables))
    m = tables["meta"]
    print(f"coiltrack calibrate: {args.method}: {m['poses']} poses, residual RMS {m['residual_rms']:.3g} "
          f"{m.get('residual_unit', '')}; written to {args.out}")
    return 0
