"""The runner that puts a world, its nodes and a firmware on one link.

It is the only place where ``hil`` and ``firmware_py`` meet, and they meet
only through protocol frames on a link.
"""
from __future__ import annotations

import gc
import sys
import time
from typing import TYPE_CHECKING

import numpy as np

from coiltrack.firmware.loop import Firmware
from coiltrack.hil.bench import assemble
from coiltrack.hil.faults import BenchFaults, LinkFaults
from coiltrack.hil.nodes import ImuSpec, MagSpec
from coiltrack.protocol import SignatureVerifier

from ..outputs import report as report_mod
from ..stopping import Stopped, mark
from .framelog import RecordingPort, config_to_dict, write_log
from .links import inproc_pair
from .timing import inproc_cpu_timing, inproc_timing

if TYPE_CHECKING:       # the scenarios use this engine (scenarios.imperfect): only the type here
    from ..scenarios.base import Scenario


class BenchSetup:
    """World, nodes and recorder of a scenario for one seed (built by ``hil.bench.assemble``).

    ``faults``: a :class:`hil.faults.BenchFaults` (link, node and world fault
    switches) or a bare :class:`hil.faults.LinkFaults`. ``cfg``: the firmware
    configuration the nodes serve (its sensor ids; default the scenario's).
    ``noise_draw``: 0 (the seed's own draws), or k > 0: the same world (trajectory, objects)
    with every node's draws (driver, sensor, faults, clocks: white noise and static errors
    alike) taken from ``SeedSequence([seed, k])`` instead, a run-to-run repeat on one trajectory.
    """

    def __init__(self, scenario: Scenario, seed: int, duration_s: float, link,
                 faults: BenchFaults | LinkFaults | None = None, cfg=None, noise_draw: int = 0):
        ss = np.random.SeedSequence(seed)
        s_world, s_driver, s_sensor, s_faults, s_clocks = (int(s.generate_state(1)[0]) for s in ss.spawn(5))
        if noise_draw:
            nodes = np.random.SeedSequence([seed, int(noise_draw)]).spawn(4)
            s_driver, s_sensor, s_faults, s_clocks = (int(s.generate_state(1)[0]) for s in nodes)
        self.scenario = scenario
        self.seed = seed
        self.duration_s = duration_s
        self.world = scenario.build_world(s_world, duration_s)
        sids = tuple((cfg or scenario.firmware_config()).link.sensor_ids)
        views = scenario.sensor_worlds(self.world, s_world, duration_s, sids) if scenario.sensor_worlds else None
        spec = scenario.sensor
        key = (cfg or scenario.firmware_config()).signing_key_bytes()
        # with a key the nodes require signed commands (an unsigned or forged one is dropped, counted)
        self.verifier = SignatureVerifier(key, require=True) if key else None
        mag = MagSpec(rate_hz=spec.rate_hz, noise_t=spec.noise_t, flip_every=getattr(spec, "flip_every", 8))
        imu_rate = getattr(spec, "imu_rate_hz", 0.0)
        delta_rate = getattr(spec, "imu_delta_rate_hz", 0.0)
        imu = ImuSpec(rate_hz=imu_rate, delta_rate_hz=delta_rate) if imu_rate else None
        kinds = getattr(spec, "node_kinds", None)   # a sensor spec that brings its own nodes (AC excitation)
        self.bench = assemble(self.world, link, mag=mag, imu=imu, faults=faults, seed_driver=s_driver,
                              seed_sensor=s_sensor, seed_faults=s_faults, seed_clocks=s_clocks,
                              clock_drift_ppm=getattr(spec, "clock_drift_ppm", 50.0),
                              sensor_ids=sids, verifier=self.verifier, sensor_worlds=views,
                              kinds=kinds() if kinds is not None else None)
        install = getattr(spec, "install", None)
        if install is not None:             # a sensor spec that completes its nodes (imperfections)
            install(self.bench, s_driver, s_sensor)
        src_id = getattr(spec, "source_imu_id", 0)
        if src_id:
            # an IMU + magnetometer module on the source (thesis sec 6.2.3), a node of its own
            from coiltrack.hil.bench import random_clock
            from coiltrack.hil.imu import SourceImuNode
            from coiltrack.protocol import FrameEncoder

            rng = np.random.default_rng(s_clocks + 1)
            src_imu = ImuSpec(rate_hz=imu_rate or 120.0, delta_rate_hz=delta_rate)
            if not getattr(spec, "source_acc_offset", True):
                src_imu.acc_bias_sigma, src_imu.acc_bias_rw = 0.0, 0.0
            node = SourceImuNode(src_id, self.world, imu=src_imu,
                                 mag=MagSpec(rate_hz=spec.rate_hz, noise_t=spec.noise_t),
                                 seed=s_sensor + 4099, clock=random_clock(rng, getattr(spec, "clock_drift_ppm", 50.0)))
            emu = self.bench.emulator
            emu.nodes.append(node)
            emu.encoders[src_id] = FrameEncoder(src_id)
            self.source_imu = node
        self.faults = self.bench.faults
        self.link = self.bench.link
        self.driver = self.bench.driver
        self.sensors = self.bench.sensors
        self.sensor = self.sensors[0]
        self.recorder = self.bench.recorder
        self.emulator = self.bench.emulator


class Progress:
    def __init__(self, enabled: bool, total_s: float, label: str):
        self.enabled = enabled and sys.stderr.isatty()
        self.total_s = total_s
        self.label = label
        self.last = 0.0

    def update(self, sim_s: float, poses: int, extra: str = "") -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self.last < 0.2:
            return
        self.last = now
        sys.stderr.write(f"\r{self.label}: t={sim_s:7.1f}/{self.total_s:.0f} s  poses={poses:5d} {extra}\033[K")
        sys.stderr.flush()

    def done(self) -> None:
        if self.enabled:
            sys.stderr.write("\r\033[K")
            sys.stderr.flush()


def parse_faults(spec: str, scenario: Scenario) -> BenchFaults:
    """``--faults``, parsed and checked against the scenario's source (ValueError otherwise)."""
    faults = BenchFaults.parse(spec)
    return faults.check_coils(len(scenario.build_world(0, 1.0).coils))


def sim_link_pair(transport: str):
    """(firmware end, emulator end) of a link for the simulated clock."""
    if transport == "inproc":
        return inproc_pair()
    if transport == "can":
        from coiltrack.protocol.can import inproc_link_pair
        from coiltrack.protocol.schema import NODE_COIL_DRIVER, NODE_FIRMWARE

        return inproc_link_pair(NODE_FIRMWARE, NODE_COIL_DRIVER)
    raise ValueError(f"transport '{transport}' does not run on the simulated clock")


def run_inproc(scenario: Scenario, seed: int, duration_s: float, faults: LinkFaults | None = None,
               progress: bool = False, cfg=None, transport: str = "inproc", log_path=None, outputs=None,
               noise_draw: int = 0) -> dict:
    """Run firmware and emulator in one process on the simulated clock.
    ``noise_draw``: the nodes' draws of :class:`BenchSetup` (0: the seed's own).
    ``log_path``: also write what the firmware received (``tools.bench.framelog``).
    ``outputs``: a :class:`tools.outputs.sinks.Outputs` (OpenIGTLink, capture, pose table, plot).

    ``transport``: ``inproc`` joins them with an in-memory byte pipe; ``can``
    with an in-process python-can bus (``protocol.interfaces.inproc``), every
    message segmented into CAN frames and reassembled (``protocol.can.CanLink``).
    Both give the same frames at the same simulated instants, so the same report.

    Stopped early (SIGINT, SIGTERM: :class:`tools.stopping.Stopped`), the
    report of what was done, marked ``interrupted``, is raised with the
    exception as ``exc.partial``.
    """
    cfg = cfg or scenario.firmware_config()
    fw_end, emu_end = sim_link_pair(transport)
    bench = BenchSetup(scenario, seed, duration_s, emu_end, faults, cfg=cfg, noise_draw=noise_draw)
    rec_port = None
    if outputs is not None:
        fw_end = outputs.wrap(fw_end)
    if log_path is not None:
        fw_end = rec_port = RecordingPort(fw_end)
    fw = Firmware(cfg, fw_end)
    prog = Progress(progress, duration_s, scenario.name)
    wall0 = time.perf_counter()
    cpu_ns: list = []
    t, exec_ns, stopped = _tick_loop(bench, fw, rec_port, int(duration_s * 1e6), cfg.timing.tick_us, prog, outputs,
                                     cpu_ns)
    fw_end.close()
    emu_end.close()
    prog.done()
    wall = time.perf_counter() - wall0
    done_s = duration_s if stopped is None else max(t, cfg.timing.tick_us) * 1e-6
    rep = report_mod.build(bench, fw.status(), done_s, transport=transport, cfg=cfg)
    rep.update(inproc_timing(exec_ns, cfg.timing.tick_us))
    rep.update(inproc_cpu_timing(cpu_ns[0], cfg.timing.tick_us))
    rep["wall_s"] = round(wall, 2)
    rep["speedup"] = round(done_s / wall, 1) if wall > 0 else None
    if rec_port is not None:
        write_log(log_path, {"scenario": scenario.name, "seed": seed, "duration_s": done_s, "tick_us": cfg.timing.tick_us,
                             "config": config_to_dict(cfg)}, rec_port.reads)
        rep["log"] = str(log_path)
    if outputs is not None:
        outputs.finish(bench, rep)
    if stopped is not None:
        raise mark(rep, stopped)
    return rep


def _tick_loop(bench, fw, rec_port, end_us: int, tick: int, prog, outputs=None, cpu_out: list | None = None,
               trace=None):
    """Emulator step and firmware tick on the simulated clock until ``end_us``. Tick
    execution times are measured as the wall time of each ``fw.tick`` (replayed on a
    real-time schedule by ``tools.bench.realtime.inproc_timing``) and, when ``cpu_out`` is a
    list, as the thread's CPU time (``time.thread_time_ns``: the time the machine spent on other
    processes left out), appended to it as one array. ``trace``: a
    :class:`tools.bench.ticktrace.TickTrace` told each tick's start and end (off: None). Returns
    the last tick time, the execution times (ns) and the :class:`Stopped` that ended the run
    early, if any."""
    exec_ns = np.zeros(end_us // tick + 2, dtype=np.int64)
    cpu_ns = np.zeros(exec_ns.size, dtype=np.int64)
    clk, cpu = time.perf_counter_ns, time.thread_time_ns
    # the interpreter's cyclic collector is held off during each tick and runs (if due) at the next
    # allocation after it: a collection scans the whole process's objects (the world's, the nodes',
    # the recorder's, a 1.5 ms pause in multi16), which a board's firmware has none of, and which
    # the firmware process of the wall-clock bench never runs (``realtime._realtime_setup``)
    gc_on = gc.isenabled()
    k = 0
    t = 0
    try:
        while t <= end_us:
            if outputs is not None:
                outputs.tick(t)         # paces the run to the wall clock while serving OpenIGTLink
            bench.emulator.step(t)
            if rec_port is not None:
                rec_port.now_us = t
            if trace is not None:
                trace.begin(k)
            if gc_on:
                gc.disable()
            c = cpu()
            a = clk()
            fw.tick(t)
            b = clk()
            cpu_ns[k] = cpu() - c
            if gc_on:
                gc.enable()
            exec_ns[k] = b - a
            if trace is not None:
                trace.end(k, b - a, cpu_ns[k])
            k += 1
            if (t // tick) % 1000 == 0:
                prog.update(t * 1e-6, fw.poses)
            t += tick
        bench.emulator.step(t)  # deliver the last frames to the recorder
    except Stopped as exc:
        if cpu_out is not None:
            cpu_out.append(cpu_ns[:k])
        return t, exec_ns[:k], exc
    finally:
        if gc_on:
            gc.enable()
    if cpu_out is not None:
        cpu_out.append(cpu_ns[:k])
    return t, exec_ns[:k], None


#: report keys copied from the fixed-cycle reference run as ``fixed_<key>``
FIXED_KEYS = ("position_rms_mm", "position_p95_mm", "orientation_rms_deg", "poses", "pulses_per_s",
              "coil_charge_c", "coil_energy_j", "supply_energy_j", "projected_runtime_h", "crlb_position_rms_mm",
              "pulse_ms")


def add_fixed_comparison(rep: dict, scenario: Scenario, seed: int, duration_s: float, faults=None,
                         transport: str = "inproc", noise_draw: int = 0) -> dict:
    """For a scenario with a ``fixed_config`` (an actuation-policy scenario such as
    ``schepers-adaptive``): run that fixed X, Y, Z cycle on the same trajectory and
    seed (simulated clock) and add its figures to ``rep`` as ``fixed_*``, with the
    ratios ``position_rms_ratio``, ``orientation_rms_ratio`` and ``energy_ratio``
    (this run over the fixed one); ``noise_draw``: the run's, so both see the same bench."""
    if scenario.fixed_config is None:
        return rep
    ref = run_inproc(scenario, seed, duration_s, faults=faults, cfg=scenario.fixed_config(),
                     transport=transport if transport in ("inproc", "can") else "inproc", noise_draw=noise_draw)
    for k in FIXED_KEYS:
        rep["fixed_" + k] = ref.get(k)
    ratio = lambda a, b: round(a / b, 3) if a is not None and b else None  # noqa: E731
    rep["position_rms_ratio"] = ratio(rep.get("position_rms_mm"), ref.get("position_rms_mm"))
    rep["orientation_rms_ratio"] = ratio(rep.get("orientation_rms_deg"), ref.get("orientation_rms_deg"))
    rep["energy_ratio"] = ratio(rep.get("coil_energy_j"), ref.get("coil_energy_j"))
    return rep


def record_log(sc: "Scenario", seed: int, duration: float, cfg=None):
    """The frame log of an in-process bench run of scenario ``sc`` for ``duration`` s (its
    configuration, or the :class:`FirmwareConfig` ``cfg``): the header and the reads, tick by tick,
    as ``coiltrack bench --log`` writes them (for ``framelog.replay``)."""
    fw_end, emu_end = inproc_pair()
    bench = BenchSetup(sc, seed, duration, emu_end)
    cfg = cfg or sc.firmware_config()
    port = RecordingPort(fw_end)
    fw = Firmware(cfg, port)
    t = 0
    while t <= duration * 1e6:
        bench.emulator.step(t)
        port.now_us = t
        fw.tick(t)
        t += cfg.timing.tick_us
    header = {"scenario": sc.name, "seed": seed, "duration_s": duration, "tick_us": cfg.timing.tick_us,
              "config": config_to_dict(cfg)}
    return header, port.reads
