"""The firmware main loop: one fixed-step ``tick(now_us)`` through fixed stages.

The stages are composed once, in ``__init__``, from the configuration; each
tick runs them top-down, in this order, with no blocking call and no sleep:

1. receive (:class:`coiltrack.firmware.receive.Receiver`): drain the Port,
   decode, route samples into the sensor channels and the tracker, coil
   status into the pulse schedule;
2. measure: close the pulse windows whose trailing baseline is complete
   (:mod:`coiltrack.firmware.measure.windows`);
3. track: turn measurements into poses, within the tick's work budget: the
   magnetic-only tracker (:mod:`coiltrack.firmware.track.magnetic`), the
   burst-fusion tracker of thesis ch. 6
   (:mod:`coiltrack.firmware.track.burst_fusion`) or the single-coil EKF;
4. actuate: the excitation policy sends its coil commands through the one
   :class:`coiltrack.firmware.actuate.schedule.PulseSchedule`: bursts of the
   fixed X, Y, Z cycle (:mod:`coiltrack.firmware.actuate.burst`) or
   single-coil pulses on demand (Schepers & Veltink 2010,
   :mod:`coiltrack.firmware.track.single_coil_tracker`). It comes after
   measure and track so that a policy that closes the loop decides on the
   newest estimate (on ``schepers-adaptive`` seed 1, deciding before the
   tick's updates costs 10 % of position accuracy);
5. supervise (:mod:`coiltrack.firmware.supervise.supervisor`): time sync,
   node health, magnetometer flips;
6. transmit (:mod:`coiltrack.firmware.transmit`): the heartbeat (poses and
   window reports leave as they are made, through the same transmitter).

The pipeline is composed in one place, :mod:`coiltrack.firmware.compose` (its table
``TRACKERS``, from ``excitation``, ``actuation``, ``single_coil_fusion``, ``fusion`` and
``tight_fusion``); each stage is behind a ``typing.Protocol`` (``track.Tracker``,
``actuate.Actuation``, ``measure.Measurement``, ``pose.Solver``, ``port.Port``;
``docs/guide/extending.md``). The loop itself has no mode flag, and no stage writes
another's state. Every buffer is
created at start-up; the steady-state tick allocates no numpy array
(``tests/firmware/test_alloc.py``). Time is an integer count of microseconds
on the master clock.
"""
from __future__ import annotations

import time

from coiltrack.protocol import Signer
from coiltrack.protocol.signing import now_timestamp

from coiltrack.firmware.actuate.schedule import PulseSchedule
from coiltrack.firmware.compose import Parts, Pipeline, compose
from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.core import load as load_core
from coiltrack.firmware.measure.pulse import NO_TIME_US
from coiltrack.firmware.measure.windows import SensorChannel, WindowCloser
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.port import Port
from coiltrack.firmware.receive import Receiver
from coiltrack.firmware.rxdecode import frame_decoder
from coiltrack.firmware.rotation import quat_tuple as _quat  # noqa: F401  (re-exported for tools)
from coiltrack.firmware.supervise.supervisor import Supervisor
from coiltrack.firmware.transmit import Transmitter

#: the tick's stages, in order (``Firmware.tick_timed`` times each)
PHASES = ("receive", "measure", "track", "actuate", "supervise", "transmit")


class Firmware:
    """Fixed-size firmware state built once from a :class:`FirmwareConfig`."""

    def __init__(self, cfg: FirmwareConfig, port: Port, sign_ts0: int | None = None, calibration=None):
        """``sign_ts0``: the signing timestamp at boot (10 us units since 2015-01-01; default the
        wall clock's, read once here) when ``signing_key`` is set. ``calibration``: a
        :class:`coiltrack.firmware.calibration.Calibration` (default: the file ``calibration_file``
        of the configuration, read here, or none)."""
        self.cfg = cfg.validate()
        self.port = port
        if calibration is None and cfg.calibration.calibration_file:
            from coiltrack.firmware.calibration import load_calibration

            calibration = load_calibration(cfg.calibration.calibration_file, cfg)
        self.calibration = calibration
        self.coils = [Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.source.coils]
        if calibration is not None and calibration.source is not None and cfg.calibration.calibration_source:
            from coiltrack.firmware.calibration import calibrated_coils

            self.coils = calibrated_coils(self.coils, calibration.source)
        sensor_cal = calibration.sensors if calibration is not None and cfg.calibration.calibration_sensors else None
        key = cfg.signing_key_bytes()
        signer = Signer(key, cfg.signing.signing_link_id) if key else None
        if signer is not None and sign_ts0 is None:
            sign_ts0 = now_timestamp()
        # the numeric core ([core] impl), chosen once: the stages composed below bind its kernels
        kernels = load_core(cfg.core.impl)
        self.core = kernels.name
        decoder = frame_decoder(kernels)        # the receive stage's, on that core (its counters: the heartbeat's)
        self.tx = Transmitter(port, cfg.link.node_id, cfg.link.heartbeat_us, decoder, signer, sign_ts0 or 0, kernels)
        self.schedule = PulseSchedule(len(self.coils), self.tx, [c.resistance for c in cfg.source.coils])
        self.channels = tuple(SensorChannel(sid, cfg, kernels) for sid in cfg.link.sensor_ids)
        self.closer = WindowCloser(self.channels, cfg.pulse.fall_us, cfg.pulse.baseline_us, cfg.timing.cycle_us // 2, self.tx)
        self.supervisor = Supervisor(cfg, self.schedule, self.tx)
        # the room's map goes into the pose solvers' signal model as they are built
        distortion = getattr(calibration, "distortion", None) if cfg.distortion.distortion_apply else None
        parts = Parts(cfg, self.coils, self.channels, self.schedule, self.closer, self.supervisor, self.tx, distortion,
                      kernels)
        self.pipeline: Pipeline = compose(parts)
        self.tracker = self.pipeline.tracker
        self.receiver = Receiver(port, decoder, self.channels, self.schedule, self.tracker, self.supervisor,
                                 self.tx, other=self.pipeline.on_message, calibration=sensor_cal,
                                 imu_interval_us=1e6 / cfg.imu.imu_delta_rate_hz, imu_step_us=1e6 / cfg.imu.imu_rate_hz,
                                 frames_per_tick=cfg.receive.rx_frames_per_tick, queue_bytes=cfg.receive.rx_queue_bytes,
                                 core=kernels)
        # what binds across stages once every one is built (the tracker's hand-over reads the
        # supervisor's kernel, made with the receive stage)
        bind = getattr(self.tracker, "bind_composed", None)
        if bind is not None:
            bind()
        self.stages = (self.receiver.step, self.pipeline.measure, self.pipeline.track,
                       self.pipeline.actuate, self.supervisor.step, self.tx.step)
        self._completing = self.pipeline.completing_sample_us
        self.boot_us: int | None = None
        self.ticks = 0
        self.last_tick_us: int | None = None
        self._begin_tick = self.tx.begin_tick
        self._out = self._outv = None           # tick_timed's output and its view

    def completing_sample_us(self) -> int:
        """When the sample that completes the open burst is expected (us, master clock), once it
        is the next one; ``NO_TIME_US`` otherwise, and always where the pipeline gives no such
        hint (AC blocks, single-coil pulses). The wall-clock loop reads it after each tick and
        moves its grid so that a tick starts ``[timing] align_us`` after it
        (``tools.bench.realtime.firmware_loop``); it changes nothing here."""
        return NO_TIME_US if self._completing is None else self._completing()

    def tick(self, now_us: int) -> None:
        # the tick's start (here and in tick_timed, inline): the boot time, the count, the
        # transmitter's clock
        if self.boot_us is None:
            self.boot_us = now_us
        self.ticks += 1
        self.last_tick_us = now_us
        self._begin_tick(now_us)
        receive, measure, track, actuate, supervise, transmit = self.stages
        receive(now_us)
        measure(now_us)
        track(now_us)
        actuate(now_us)
        supervise(now_us)
        transmit(now_us)

    def tick_timed(self, now_us: int, out_ns) -> None:
        """:meth:`tick`, writing each stage's duration (ns, :data:`PHASES` order) into ``out_ns``."""
        if self.boot_us is None:                # (the tick's start, as in tick)
            self.boot_us = now_us
        self.ticks += 1
        self.last_tick_us = now_us
        self._begin_tick(now_us)
        clk = time.perf_counter_ns
        receive, measure, track, actuate, supervise, transmit = self.stages
        t0 = clk()
        receive(now_us)
        t1 = clk()
        measure(now_us)
        t2 = clk()
        track(now_us)
        t3 = clk()
        actuate(now_us)
        t4 = clk()
        supervise(now_us)
        t5 = clk()
        transmit(now_us)
        t6 = clk()
        if out_ns is not self._out:            # (its memoryview, made once: a store there is cheaper)
            self._out = out_ns
            self._outv = memoryview(out_ns) if hasattr(out_ns, "__array_interface__") else out_ns
        o = self._outv
        o[0], o[1], o[2] = t1 - t0, t2 - t1, t3 - t2
        o[3], o[4], o[5] = t4 - t3, t5 - t4, t6 - t5

    # --------------------------------------------------------------- status
    @property
    def poses(self) -> int:
        """POSEs sent as valid (magnetic and fused)."""
        return self.tx.poses

    @property
    def cycles(self) -> int:
        return self.status().get("cycles", 0)

    def status(self) -> dict:
        d = {"ticks": self.ticks, "poses": self.tx.poses, "windows_flagged": self.closer.flagged,
             "tx_errors": self.tx.tx_errors, "core": self.core}
        d.update(self.tracker.counters())
        d.setdefault("cycles", 0)
        d.update(self.receiver.counters())
        d.update(self.supervisor.counters())
        if "imu_samples" in d:
            d["fused_poses"] = self.tx.fused_poses
        if self.tx.signer is not None:
            d["tx_signed"] = self.tx.signer.signed
        return d
