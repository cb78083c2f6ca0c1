"""docs/protocol.md describes the reference nodes' behaviour where the
message table cannot (refusal bits, duplicates, time-sync signs, flips):
each rule here is read from the document and checked against the emulated
nodes (hil.nodes), driven directly on simulated time."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from coiltrack.hil.clock import NodeClock
from coiltrack.hil.faults import BenchFaults, TimedFault
from coiltrack.hil.nodes import CoilDriverNode, SensorNode
from coiltrack.protocol import MSG
from coiltrack.protocol.schema import STAMP_FLIP, STAMP_LSB_US, STAMP_MASK

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
Cmd, Sync, Flip = MSG["COIL_PULSE_CMD"], MSG["TIME_SYNC"], MSG["MAG_FLIP_CMD"]
T0 = 1_000_000


@pytest.fixture(scope="module")
def doc() -> str:
    return DOC.read_text()


class Bus:
    """Collects what a node sends; drives it on simulated time."""

    def __init__(self, node):
        self.node = node
        self.out = []
        self.now = 0

    def send(self, _node, msg) -> None:
        self.out.append(msg)

    def named(self, name: str) -> list:
        return [m for m in self.out if m.NAME == name]

    def deliver(self, msg) -> None:
        self.node.handle(msg, self.now, self.send)

    def run_to(self, t_us: int, step_us: int = 1000) -> None:
        while self.now < t_us:
            self.now = min(t_us, self.now + step_us)
            self.node.tick(self.now, self.send)


def synced_driver(world, faults=None) -> Bus:
    bus = Bus(CoilDriverNode(2, world, faults=faults))
    bus.run_to(T0)
    bus.deliver(Sync(T0, 0))
    return bus


def refusal_values(doc: str) -> list[int]:
    table = re.search(r"^\| check \(in this order\) \| `faults` \| value \|\n\|[-:| ]+\|\n(.*?)\n\n", doc, re.S | re.M)
    assert table is not None, "docs/protocol.md lost its refusal table"
    return [int(row.rsplit("|", 2)[1]) for row in table.group(1).split("\n")]


def _duty_refusal(bus):
    for k in range(3):      # 3 x 200 ms in the 1.2 s window: 50 %, at the limit
        bus.deliver(Cmd(1, 10 + k, 1000, T0 + 10_000 + k * 200_000, 200_000))
    assert not bus.named("COIL_STATUS")
    return Cmd(1, 13, 1000, T0 + 610_000, 200_000)


def test_refusal_table_is_what_the_reference_driver_sends(doc, world_factory):
    """Each row of the document's refusal table, in its order, against the driver: the faults
    value and the refusal's COIL_STATUS (no current, start = end = the commanded start)."""
    scenarios = [
        lambda bus: Cmd(7, 1, 500, T0 + 50_000, 20_000),            # no such coil
        None,                                                         # not synchronised
        lambda bus: Cmd(0, 3, 30_000, T0 + 50_000, 20_000),          # over current
        lambda bus: Cmd(0, 4, 500, T0 + 50_000, 10_000_000),         # too long
        lambda bus: Cmd(0, 5, 500, T0 + 100, 20_000),                # lead below the minimum
        _duty_refusal,                                                # duty
        lambda bus: Cmd(2, 7, 500, T0 + 50_000, 20_000),             # winding too hot
    ]
    values = refusal_values(doc)
    assert len(values) == len(scenarios)
    for k, (make, want) in enumerate(zip(scenarios, values)):
        if make is None:
            bus = Bus(CoilDriverNode(2, world_factory()))
            bus.run_to(T0)
            cmd = Cmd(0, 2, 500, T0 + 50_000, 20_000)
        else:
            hot = BenchFaults(timed=[TimedFault("overheat", 0, None, 2, 150.0)])
            bus = synced_driver(world_factory(), faults=hot)
            cmd = make(bus)
        bus.deliver(cmd)
        bus.run_to(cmd.start_us + min(cmd.duration_us, 300_000) + 5_000)
        (st,) = [s for s in bus.named("COIL_STATUS") if s.pulse_id == cmd.pulse_id]
        assert (st.coil, st.faults, st.current_ma, st.start_us, st.end_us) == \
            (cmd.coil, want, 0, cmd.start_us, cmd.start_us), f"refusal table row {k + 1}"


def test_zero_length_pulse_is_refused_without_a_reason_bit(world_factory):
    bus = synced_driver(world_factory())
    bus.deliver(Cmd(0, 9, 500, T0 + 50_000, 0))
    assert [s.faults for s in bus.named("COIL_STATUS")] == [16]


def test_repeated_pulse_command_is_executed_once(doc, world_factory):
    """The document's rule for a repeated unsigned COIL_PULSE_CMD on serial."""
    assert "So a\n  repeated unsigned `COIL_PULSE_CMD` is executed **once**." in doc
    bus = synced_driver(world_factory())
    cmd = Cmd(0, 42, 1000, T0 + 20_000, 30_000)
    bus.deliver(cmd)
    bus.deliver(cmd)
    bus.run_to(T0 + 20_000)
    bus.deliver(cmd)                 # again, after it started
    bus.run_to(T0 + 80_000)
    assert len(bus.node.executed) == 1
    assert [s.pulse_id for s in bus.named("COIL_STATUS")] == [42]


def test_time_sync_reply_fields_as_the_doc_defines_them(doc):
    """node_time_us raw, offset_us = node - master, drift_ppb positive for a fast node clock;
    a TIME_SYNC not newer than the last (a restarted master) leaves the fit as it was."""
    assert "**positive when the node's clock runs fast**" in doc
    assert "the node's estimate of `node clock - master clock`" in doc
    assert "the node's **raw** clock" in doc
    clock = NodeClock(offset_us=5_000, drift_ppm=100.0)
    bus = Bus(CoilDriverNode(2, _NoWorld(), clock=clock))
    for k in range(1, 41):           # a perfect master: master time = true time
        bus.now = k * 250_000
        bus.deliver(Sync(bus.now, k))
    r = bus.named("TIME_SYNC_REPLY")[-1]
    assert r.node_time_us == clock.local(bus.now)
    assert r.offset_us == pytest.approx(clock.local(bus.now) - bus.now, abs=2)
    assert r.drift_ppb == pytest.approx(100_000, rel=0.01)
    bus.now += 250_000
    bus.deliver(Sync(1_000, 41))     # the master restarted: its clock reads less
    assert bus.named("TIME_SYNC_REPLY")[-1].offset_us == r.offset_us
    assert "keeps its old fit" in doc


class _NoWorld:
    """A driver's world with no coils (the time-sync test needs none)."""
    coils = ()
    currents = ()
    supply_v = 0.0


def _sensor(world):
    bus = Bus(SensorNode(16, world, seed=5))
    bus.deliver(Sync(0, 0))
    return bus


def _flip_bits(bus, after_us=-1):
    """(time, set/reset bit) of the node's samples: MAG_PACKED, its 14-bit stamp restored against the
    bus's clock at the end of the run (the doc's rule; the samples are less than 114 ms old only
    for the last ones, so the times are restored from the full stamps the node's ground truth keeps)."""
    node = bus.node
    packed = bus.named("MAG_PACKED")
    stamps = node.stamps[-len(packed):] if packed else []
    out = []
    for t, m in zip(stamps, packed):
        assert (t // STAMP_LSB_US) & STAMP_MASK == m.stamp & STAMP_MASK
        if t > after_us:
            out.append((t, 1 if m.stamp & STAMP_FLIP else 0))
    return out


def test_flip_command_rules(doc, world_factory):
    """The first sample at or after at_us shows the new bit; a past at_us means now; target 0 is
    ignored; no flip of its own within 3 s of a command."""
    for phrase in ("the first `MAG_SAMPLE` (`MAG_PACKED`) taken\n  at or after `at_us` shows the new `flip` bit",
                   "an `at_us` in the past", "target 0 is not a broadcast",
                   "**but never within 3 s of the last `MAG_FLIP_CMD` it received**"):
        assert phrase in doc, phrase
    bus = _sensor(world_factory())
    bus.run_to(200_000)
    state = _flip_bits(bus)[-1][1]
    bus.deliver(Flip(0, bus.now, state ^ 1))          # target 0: not a broadcast
    at = bus.now + 30_000
    bus.deliver(Flip(16, at, state ^ 1))
    bus.run_to(at + 50_000)
    after = _flip_bits(bus, 200_000)
    assert any(t < at for t, _ in after) and any(t >= at for t, _ in after)
    assert all(bit == state for t, bit in after if t < at)
    assert all(bit == state ^ 1 for t, bit in after if t >= at)
    t_past = bus.now
    bus.deliver(Flip(16, 1_000, state))               # in the past: now
    bus.run_to(t_past + 9_000)
    assert _flip_bits(bus, t_past)[0][1] == state
    bus.run_to(t_past + 2_900_000)                    # commanded: no flip of its own
    assert {bit for _, bit in _flip_bits(bus, t_past)} == {state}
    bus.run_to(t_past + 3_200_000)                    # 3 s after: it flips on its own again
    assert {bit for _, bit in _flip_bits(bus, t_past + 3_000_000)} == {0, 1}


def _num(doc: str, pattern: str) -> float:
    m = re.search(pattern, doc, re.S)
    assert m is not None, f"docs/protocol.md no longer says /{pattern}/"
    return float(m.group(1))


def test_timing_and_capability_figures_are_the_defaults(doc):
    """The limits the spec gives a node are the firmware's and the reference driver's defaults."""
    from coiltrack.firmware.config import FirmwareConfig
    from coiltrack.firmware.supervise.health import HealthConfig
    from coiltrack.firmware.supervise.supervisor import SupervisorConfig
    from coiltrack.hil.nodes import DriverLimits

    h, s, cfg, lim = HealthConfig(), SupervisorConfig(), FirmwareConfig(), DriverLimits()
    assert _num(doc, r"is within \*\*(\d+) us\*\* of a whole number of periods") == h.stamp_interval_tol_us
    assert _num(doc, r"stamp at most \*\*(\d+) us\*\* after the master clock") == h.stamp_future_tol_us
    assert _num(doc, r"a\s+reply more than (\d+) us from the prediction") == s.sync_step_threshold_us
    assert _num(doc, r"firmware: every (\d+) ms,\s+`sync_period_us`") * 1000 == s.sync_period_us
    assert _num(doc, r"a\s+sensor silent for (\d+) ms") * 1000 == h.sensor_timeout_us
    assert _num(doc, r"the largest configured current: \*\*([\d.]+) A\*\*") == \
        max(max(c.current for c in cfg.source.coils), cfg.adaptive.adaptive_max_current_a)
    assert _num(doc, r"\| pulse length \| (\d+) ms \(`pulse_us`\)") * 1000 == cfg.timing.pulse_us
    assert _num(doc, r"\*\*(\d+) ms\*\* minimum lead") * 1000 == min(cfg.timing.lead_us, cfg.adaptive.adaptive_lead_us)
    assert _num(doc, r"the largest configured current: \*\*[\d.]+ A\*\* \| ([\d.]+) A \|") == lim.max_current_a
    assert _num(doc, r"\| \*\*60 ms\*\* \| (\d+) ms \|") * 1000 == lim.max_pulse_us
    assert _num(doc, r"must not refuse as late a command 10 ms ahead \| (\d+) us \|") == lim.min_lead_us
    assert _num(doc, r"default \*\*([\d.]+) Hz\*\*; `imu_rate_hz`") == cfg.pulse.mag_rate_hz
