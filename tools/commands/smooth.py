"""Fixed-interval RTS smoothing of a recorded run (thesis sec 4.2.5, sec 6.2.3).

Reads a frame log (``coiltrack bench --log PATH``), replays it into a fresh
firmware on its virtual clock with a recorder on each sensor's fusion filter
(``coiltrack.firmware.estimate.smoother.FusionRecorder``), runs the Rauch-Tung-Striebel
backward sweep (``coiltrack.firmware.estimate.smoother``) and, when the log names a scenario,
compares the forward and the smoothed poses with the scenario's ground truth
(rebuilt from the log's seed). ``--out`` writes the smoothed poses as JSON
lines (source frame: time, position, quaternion, position and orientation
standard deviations).
"""
from __future__ import annotations

import math
import sys

import numpy as np

from .. import args as A
from ..bench.framelog import replay, load
from ..outputs.jsonout import dumps

HELP = "RTS-smooth the fusion filter over a recorded run (frame log from `bench --log`)"
NAME = "smooth"
EXIT = {1: "the log has no fused run to smooth (no IMU samples)"}


def add_arguments(p) -> None:
    p.add_argument("log", type=A.input_file, help="frame log written by `coiltrack bench --log PATH`")
    p.add_argument("--out", type=A.output_path, metavar="PATH", help="write the smoothed poses (JSON lines)")
    p.add_argument("--json", type=A.output_path, metavar="PATH", help="write the summary as JSON")


def _truth_world(header):
    """The scenario's world for the log's seed (as ``tools.bench.runner.BenchSetup`` builds it)."""
    # imported where used here and below: the scenarios (scipy underneath) load only when needed, not for --help
    from .. import scenarios

    sc = scenarios.SCENARIOS.get(header.get("scenario"))
    if sc is None:
        return None
    ss = np.random.SeedSequence(int(header["seed"]))
    s_world = int(ss.spawn(5)[0].generate_state(1)[0])
    return sc.build_world(s_world, float(header["duration_s"]))


def _angle(Ra, Rb) -> float:
    c = (float(np.trace(Ra.T @ Rb)) - 1.0) * 0.5
    return math.acos(max(-1.0, min(1.0, c)))


def smooth_log(header: dict, reads) -> dict:
    """Replay, smooth, evaluate. Returns the summary and the smoothed segments per node."""
    from coiltrack.firmware.loop import Firmware
    from coiltrack.firmware.estimate.smoother import FusionRecorder, smooth

    recorders = {}

    def factory(cfg, port):
        fw = Firmware(cfg, port)
        for node, ins in getattr(fw.tracker, "inertial", {}).items():
            rec = FusionRecorder()
            ins.fusion.attach_recorder(rec)
            recorders[node] = rec
        return fw

    replay(factory, header, reads)
    world = _truth_world(header)
    out = {"scenario": header.get("scenario"), "seed": header.get("seed"), "duration_s": header["duration_s"],
           "nodes": {}}
    segments = {}
    for node, rec in recorders.items():
        segs = smooth(rec)
        segments[node] = segs
        info = {"segments": len(segs), "steps": int(sum(len(s["t"]) for s in segs))}
        if world is not None and segs:
            fe, se, fa, sa, dist = [], [], [], [], []
            for s in segs:
                K = world.trajectory.kinematics(s["t"])
                for i in range(len(s["t"])):
                    phi = s["phi"][i]
                    pf = phi.T @ s["p_forward"][i]
                    ps = phi.T @ s["p"][i]
                    fe.append(float(np.linalg.norm(pf - K.position[i])))
                    se.append(float(np.linalg.norm(ps - K.position[i])))
                    fa.append(_angle(phi.T @ s["Th_forward"][i], K.R[i]))
                    sa.append(_angle(phi.T @ s["Th"][i], K.R[i]))
                    dist.append(float(np.linalg.norm(K.position[i])))
            fe, se, fa, sa, dist = map(np.asarray, (fe, se, fa, sa, dist))
            rms = lambda a: float(np.sqrt(np.mean(a ** 2)))  # noqa: E731
            info.update({
                "forward_position_rms_mm": round(rms(fe) * 1e3, 3),
                "forward_orientation_rms_deg": round(math.degrees(rms(fa)), 3),
                "smoothed_position_rms_mm": round(rms(se) * 1e3, 3),
                "smoothed_orientation_rms_deg": round(math.degrees(rms(sa)), 3),
            })
            bands = {}
            for lo, hi in ((10, 30), (30, 45), (45, 60), (60, 90)):
                sel = (dist >= lo / 100) & (dist < hi / 100)
                if np.any(sel):
                    bands[f"{lo}-{hi}cm"] = {"forward_mm": round(rms(fe[sel]) * 1e3, 2),
                                             "smoothed_mm": round(rms(se[sel]) * 1e3, 2),
                                             "forward_deg": round(math.degrees(rms(fa[sel])), 2),
                                             "smoothed_deg": round(math.degrees(rms(sa[sel])), 2)}
            info["by_range"] = bands
        out["nodes"][str(node)] = info
    if out["nodes"]:
        first = next(iter(out["nodes"].values()))
        for k in ("forward_position_rms_mm", "forward_orientation_rms_deg", "smoothed_position_rms_mm",
                  "smoothed_orientation_rms_deg"):
            if k in first:
                out[k] = first[k]
    return out, segments


def write_poses(path, segments) -> None:
    from coiltrack.firmware.loop import _quat

    with open(path, "w") as fh:
        for node, segs in segments.items():
            for s in segs:
                for i in range(len(s["t"])):
                    phi = s["phi"][i]
                    p = phi.T @ s["p"][i]
                    R = phi.T @ s["Th"][i]
                    P = s["P"][i]
                    sp = np.sqrt(np.maximum(np.diag(phi.T @ P[0:3, 0:3] @ phi), 0.0))
                    so = np.sqrt(np.maximum(np.diag(s["Th"][i].T @ P[6:9, 6:9] @ s["Th"][i]), 0.0))
                    fh.write(dumps({"node": node, "t_us": int(s["t"][i]), "p": [round(float(x), 6) for x in p],
                                         "q": [round(float(x), 8) for x in _quat(R)],
                                         "sigma_p": [float(x) for x in sp], "sigma_rot": [float(x) for x in so]})
                             + "\n")


def run(args) -> int:
    import coiltrack.hil.world  # noqa: F401 - the truth needs the bench extra: checked before the replay

    log = load("smooth", args.log)
    if log is None:
        return 2
    header, reads = log
    out, segments = smooth_log(header, reads)
    if not segments or not any(segments.values()):
        print("coiltrack smooth: the log has no fused run to smooth (no IMU samples?)", file=sys.stderr)
        return 1
    print(f"coiltrack smooth: {out['scenario']} seed {out['seed']}, {out['duration_s']} s, RTS over the fusion filter")
    for node, info in out["nodes"].items():
        line = f"  node {node}: {info['steps']} steps in {info['segments']} segment(s)"
        if "smoothed_position_rms_mm" in info:
            line += (f"; forward {info['forward_position_rms_mm']} mm, {info['forward_orientation_rms_deg']} deg"
                     f" -> smoothed {info['smoothed_position_rms_mm']} mm, "
                     f"{info['smoothed_orientation_rms_deg']} deg")
        print(line)
        for band, b in info.get("by_range", {}).items():
            print(f"    at {band}: {b['forward_mm']} -> {b['smoothed_mm']} mm, "
                  f"{b['forward_deg']} -> {b['smoothed_deg']} deg")
    if args.out:
        write_poses(args.out, segments)
        print(f"smoothed poses written to {args.out}")
    if args.json:
        from ..outputs.jsonout import write

        write(args.json, out)
        print(f"summary written to {args.json}")
    return 0
