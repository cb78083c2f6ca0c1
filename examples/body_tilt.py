"""Tilt errors of the orientations the fusion uses on a body-worn scenario
(a diagnostic of docs/bodyworn.md, not a scenario or a test).

Runs the bench and the firmware in one process on the simulated clock and,
every 50 ms after the first 3 s, compares against the bench's truth: the
sensor's ch. 2 filter ``Xi``, the source's ``Phi`` and the fusion filter's
``Theta`` (angle between estimated and true vertical, deg). With
``--true-phi`` / ``--true-xi`` the firmware's filters are set to the true
orientation after every tick (the ceiling of better orientation filters).

    .venv/bin/python examples/body_tilt.py roetenberg-flexion-back --duration 20 \\
        --set '{"acc_adapt_gain": 1.0}' [--true-phi --true-xi]
"""
import argparse
import dataclasses
import json
import math

import numpy as np

from coiltrack.firmware.loop import Firmware
from coiltrack.tools import report as report_mod
from coiltrack.tools import scenarios
from coiltrack.tools.runner import BenchSetup, sim_link_pair


def _tilt_deg(up_est, R_true) -> float:
    """Angle between the estimated vertical in the body frame (row 2 of R) and the true one."""
    z = up_est / np.linalg.norm(up_est)
    return math.degrees(math.acos(min(1.0, abs(float(z @ R_true[2])))))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenario")
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--set", default="{}", help="configuration overrides, JSON")
    ap.add_argument("--true-phi", action="store_true")
    ap.add_argument("--true-xi", action="store_true")
    a = ap.parse_args()
    sc = scenarios.get(a.scenario)
    cfg = sc.firmware_config().with_keys(**json.loads(a.set)).validate()
    fw_end, emu_end = sim_link_pair("inproc")
    bench = BenchSetup(sc, a.seed, a.duration, emu_end, cfg=cfg)
    fw = Firmware(cfg, fw_end)
    world, tr = bench.world, fw.tracker
    ex, ep, eth = [], [], []
    t, end = 0, int(a.duration * 1e6)
    while t < end:
        bench.emulator.step(t)
        fw.tick(t)
        src = getattr(tr, "source", None)
        if a.true_phi and src is not None and src.ori.f.initialized:
            src.ori.f.R[:] = world.source_kinematics(np.array([t]))[3][0]
        if a.true_xi:
            for ins in tr.inertial.values():
                if ins.ori.f.initialized:
                    ins.ori.f.R[:] = world.sensor_kinematics(t).R
        if t % 50_000 == 0 and t > 3_000_000:
            ins = next(iter(tr.inertial.values()))
            Rw = world.sensor_kinematics(t).R
            if ins.ori.f.initialized:
                ex.append(_tilt_deg(ins.ori.f.R[2], Rw))
            if src is not None and src.ori.f.initialized:
                ep.append(_tilt_deg(src.ori.f.R[2], world.source_kinematics(np.array([t]))[3][0]))
            if ins.fusion.initialized:
                eth.append(_tilt_deg(ins.fusion.st.Th[2], Rw))
        t += cfg.timing.tick_us
    rep = report_mod.build(bench, fw.status(), a.duration, transport="inproc", cfg=cfg)

    def rms(v):
        return round(float(np.sqrt(np.mean(np.square(v)))), 2) if v else None
    print(json.dumps({"scenario": a.scenario, "set": json.loads(a.set), "true_phi": a.true_phi,
                      "true_xi": a.true_xi, "fused_mm": rep.get("position_rms_mm"),
                      "fused_deg": rep.get("orientation_rms_deg"), "magnetic_mm": rep.get("magnetic_position_rms_mm"),
                      "xi_tilt_deg": rms(ex), "phi_tilt_deg": rms(ep), "theta_tilt_deg": rms(eth)}))


if __name__ == "__main__":
    main()
