"""Every tracker, actuation policy, measurement, pose solver and link against its Protocol.

The seams of issue 31 (``firmware_py/compose.py``): each component is built the way the
firmware builds it (one :class:`Firmware` per entry of the composition table ``TRACKERS``)
and checked twice: ``isinstance`` against the ``runtime_checkable`` Protocol (every member is
there) and, for every method of the Protocol, ``inspect.signature(...).bind`` with the
Protocol's own parameters (the method accepts the call the contract makes). A class that
misses a method, or takes it with another arity, fails.
"""
from __future__ import annotations

import dataclasses
import inspect
import os

import pytest

from coiltrack.firmware import compose
from coiltrack.firmware.actuate import Actuation
from coiltrack.firmware.loop import Firmware
from coiltrack.firmware.measure import Demodulation, Measurement, WindowExtractor
from coiltrack.firmware.pose import Solver
from coiltrack.firmware.port import Port
from coiltrack.firmware.track import BurstTracker, Tracker
from coiltrack.tools import scenarios
from coiltrack.tools.bench.links import inproc_pair


def _scenario(name: str, **changes):
    return lambda: (scenarios.get(name).firmware_config()).with_keys(**changes)


def _single_coil_fixed():
    from coiltrack.tools.scenarios.thesis import schepers_fixed_config

    return schepers_fixed_config()


#: every entry of ``compose.TRACKERS`` -> a configuration that chooses it
CONFIGS = {
    "magnetic": _scenario("roetenberg-bench", fusion=False),
    "burst-fusion": _scenario("roetenberg-fusion"),
    "tight-fusion": _scenario("roetenberg-flexion-arm"),
    "single-coil-adaptive": _scenario("schepers-adaptive"),
    "single-coil-fixed": _single_coil_fixed,
    "ac-magnetic": _scenario("ac-vs-dc-clean"),
    "ac-fusion": _scenario("raab-ac"),
}
#: the pose solvers of ``compose.SOLVERS`` -> a configuration of a burst tracker that uses it
SOLVER_CONFIGS = {"lm": _scenario("roetenberg-fusion"), "raab": _scenario("raab-acquire")}


def problems(obj_or_cls, proto) -> list[str]:
    """What ``obj_or_cls`` lacks of the Protocol ``proto``: members missing (on an instance:
    ``isinstance``), methods whose signature does not take the Protocol's call."""
    out = []
    cls = obj_or_cls if isinstance(obj_or_cls, type) else type(obj_or_cls)
    if not isinstance(obj_or_cls, type) and not isinstance(obj_or_cls, proto):
        out.append(f"{cls.__name__} is not a {proto.__name__}")
    for name, member in inspect.getmembers(proto):
        if name.startswith("_") or not inspect.isfunction(member):
            continue
        impl = getattr(cls, name, None)
        if impl is None or not callable(impl):
            out.append(f"{cls.__name__}.{name} missing")
            continue
        want = list(inspect.signature(member).parameters.values())[1:]       # the Protocol's call, self aside
        args = [None] * sum(1 for p in want if p.default is inspect.Parameter.empty)
        try:
            inspect.signature(impl).bind(None, *args)
            inspect.signature(impl).bind(None, *([None] * len(want)))
        except TypeError as exc:
            out.append(f"{cls.__name__}.{name}{inspect.signature(impl)} does not take "
                       f"{proto.__name__}.{name}{inspect.signature(member)}: {exc}")
    return out


def _firmware(cfg) -> Firmware:
    fw_end, _ = inproc_pair()
    return Firmware(cfg, fw_end)


def test_every_entry_of_the_composition_table_is_checked():
    assert set(CONFIGS) == set(compose.TRACKERS)
    assert set(SOLVER_CONFIGS) == set(compose.SOLVERS)


@pytest.mark.parametrize("key", sorted(CONFIGS))
def test_the_pipeline_of_each_choice_keeps_its_contracts(key):
    cfg = CONFIGS[key]()
    assert compose.pipeline_choice(cfg) == key
    fw = _firmware(cfg)
    tracker = fw.tracker
    assert problems(tracker, Tracker) == []
    stages = (fw.pipeline.actuate, fw.pipeline.measure, fw.pipeline.track)
    for stage in stages:
        inspect.signature(stage).bind(0)                  # step(now_us)
    if key.startswith("single-coil"):
        return                                            # actuates and measures itself (its own stages)
    assert problems(tracker, BurstTracker) == []
    assert problems(fw.pipeline.actuate.__self__, Actuation) == []
    measurement = fw.pipeline.measure.__self__
    assert problems(measurement, Measurement) == []
    for name in ("solver", "comp_solver"):
        if hasattr(tracker, name):
            assert problems(getattr(tracker, name), Solver) == []
    for ch in fw.channels:
        assert problems(ch.extractor, WindowExtractor) == []
    for d in getattr(measurement, "demods", ()):
        assert problems(d, Demodulation) == []


@pytest.mark.parametrize("name", sorted(SOLVER_CONFIGS))
def test_each_pose_solver_keeps_the_solver_contract(name):
    cfg = SOLVER_CONFIGS[name]()
    assert cfg.pose.pose_solver == name
    from coiltrack.firmware.model.field import Coil

    tracker = _firmware(cfg).tracker
    built = compose.SOLVERS[name](cfg, [Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.source.coils], 0.999)
    assert type(tracker.solver) is type(built)
    assert problems(tracker.solver, Solver) == [] and problems(built, Solver) == []


def test_the_window_extractor_with_gyro_baseline_keeps_the_contract():
    cfg = CONFIGS["tight-fusion"]()
    assert cfg.body.baseline_gyro
    fw = _firmware(cfg)
    from coiltrack.firmware.measure.gyro_baseline import GyroBaselineExtractor

    assert all(isinstance(ch.extractor, GyroBaselineExtractor) for ch in fw.channels)
    assert all(problems(ch.extractor, WindowExtractor) == [] for ch in fw.channels)


def test_every_link_is_a_port():
    """The links of the bench (subclasses), of the protocol package and the bench's faulty link
    (structural: neither imports the firmware), classes and live instances."""
    import can

    from coiltrack.firmware.port import SerialPort
    from coiltrack.hil.faults import FaultyLink, LinkFaults
    from coiltrack.protocol.can import CanLink
    from coiltrack.protocol.serial_link import FdPort, SerialLink
    from coiltrack.tools.bench.framelog import RecordingPort, ReplayPort
    from coiltrack.tools.bench.links import FdLink, GuardedPort, InprocEnd
    from coiltrack.tools.bench.linktap import TapPort

    for cls in (SerialPort, CanLink, FdPort, SerialLink, RecordingPort, ReplayPort, FdLink, GuardedPort, InprocEnd,
                TapPort, FaultyLink):
        assert problems(cls, Port) == [], cls
    a, b = inproc_pair()
    assert problems(a, Port) == [] and problems(TapPort(a), Port) == []
    assert problems(FaultyLink(b, LinkFaults()), Port) == []
    bus = can.Bus(interface="virtual", channel="test-seams-port", receive_own_messages=False)
    try:
        assert problems(CanLink(bus, 1), Port) == []
    finally:
        bus.shutdown()
    r, w = os.pipe()
    try:
        assert problems(FdPort(r), Port) == []
    finally:
        os.close(r)
        os.close(w)


def test_a_class_that_breaks_a_contract_is_caught():
    """The check itself: a tracker without ``on_coil_status``, one whose ``on_imu`` takes one
    argument, a solver without its data members."""
    class NoStatus:
        def on_mag(self, msg, lsb):
            pass

        def on_imu(self, msg, now_us):
            pass

        def counters(self):
            return {}

    class ShortImu(NoStatus):
        def on_imu(self, msg):
            pass

        def on_coil_status(self, msg):
            pass

    assert any("on_coil_status missing" in p for p in problems(NoStatus(), Tracker))
    assert any("on_imu" in p for p in problems(ShortImu(), Tracker))
    assert problems(ShortImu, Tracker) and not isinstance(object(), Solver)


# --------------------------------------------------------------------------- the owners' methods
def test_the_transmitter_takes_the_tick_time_and_keeps_the_first_as_boot():
    """``Transmitter.begin_tick`` (the loop no longer sets the transmitter's clock): the first
    tick's time is the boot time, later ticks move only ``now_us``, and an event is stamped with
    the tick's time; catches the boot time moved by every tick."""
    from coiltrack.firmware.transmit import Transmitter
    from coiltrack.protocol import FrameDecoder

    a, b = inproc_pair()
    tx = Transmitter(a, 1, 100_000, FrameDecoder())
    tx.begin_tick(5_000)
    tx.begin_tick(7_000)
    tx.event(3, 9)
    assert (tx.boot_us, tx.now_us) == (5_000, 7_000)
    msgs = FrameDecoder().feed(b.read())
    assert [(m.NAME, m.t_us, m.code, m.detail) for m in msgs] == [("FAULT_EVENT", 7_000, 3, 9)]
    fw = _firmware(CONFIGS["magnetic"]())
    fw.tick(11_000)
    fw.tick(12_000)
    assert (fw.tx.boot_us, fw.tx.now_us, fw.boot_us) == (11_000, 12_000, 11_000)


def test_a_node_back_asks_the_time_sync_once():
    """``Health.take_kick_sync``: a node heard again after it was lost asks for one restart of
    the time sync, and the request is taken once (the supervisor no longer clears it)."""
    from coiltrack.firmware.supervise.health import Health

    h = Health((16,), 2, 120.0)
    h.heard(16, 0)
    h.step(10_000_000)                  # silent for 10 s: lost
    assert not h.take_kick_sync()
    h.heard(16, 10_000_001)
    assert h.take_kick_sync() and not h.take_kick_sync()


def test_a_cleared_sample_ring_takes_any_time_again():
    """``SampleRing.clear`` (the gyro-baseline extractor refills its scratch ring every window):
    after it a sample older than the last one before is taken, not refused as out of order."""
    from coiltrack.firmware.measure.pulse import SampleRing

    r = SampleRing(8)
    r.push(1_000, 1e-6, 0.0, 0.0, False, 0)
    r.push(500, 1e-6, 0.0, 0.0, False, 0)
    assert len(r) == 1 and r.rejected == 1
    r.clear()
    r.push(500, 2e-6, 0.0, 0.0, False, 0)
    assert len(r) == 1 and r.rejected == 1 and r.latest_t_us == 500


def test_the_ac_inertial_parts_are_built_with_their_own_compass_gate_and_timing():
    """The AC fused tracker builds each sensor's inertial part with the always-quiet compass
    gate, a block and three hops of compass age and the block's rms time ``T_w / sqrt(12)``
    (they were set after construction); the source keeps the pulse gate."""
    import math

    cfg = CONFIGS["ac-fusion"]()
    tracker = _firmware(cfg).tracker
    for ins in tracker.inertial.values():
        assert ins.ori.gate.quiet(0) and ins.ori.gate.quiet(123_456)
        assert ins.ori.max_age_us == cfg.ac.ac_window_us + 3 * cfg.ac.ac_hop_us
        assert ins.burst_rms_s == pytest.approx(cfg.ac.ac_window_us * 1e-6 / math.sqrt(12.0), rel=1e-15)
    pulsed = _firmware(CONFIGS["burst-fusion"]()).tracker
    n = len(pulsed.cfg.source.coils)
    for ins in pulsed.inertial.values():
        assert ins.burst_rms_s == pytest.approx(pulsed.cfg.timing.spacing_us * 1e-6 * math.sqrt((n * n - 1) / 12.0))
        assert ins.ori.max_age_us == int(2e6 / pulsed.cfg.imu.imu_rate_hz) + int(2e6 / pulsed.cfg.pulse.mag_rate_hz)
