"""The conformance suite against the emulator's own nodes (hil.nodes) on a
pseudo-terminal, on a virtual CAN bus, and on slcan over ptys; and against
nodes that break rules, to show the suite catches them."""
import json
import os

import pytest

from coiltrack.hil.nodes import DriverLimits, SensorNode
from coiltrack.protocol import MSG, PROTOCOL_VERSION, SCHEMA_HASH, FrameEncoder, SignatureVerifier
from coiltrack.protocol.can import CanLink, open_bus, unique_channel, virtual_link_pair
from coiltrack.protocol.conformance import FAIL, PASS, SKIP, Conformance, ConformOptions, run_conformance
from coiltrack.protocol.serial_link import FdPort, SerialLink, open_pty
from coiltrack.protocol.slcan import SlcanBridge
from coiltrack.tools.cli import main

KEY = bytes(range(32))
CORE = ("heartbeat", "frames_valid", "sequence")
NODE_RULES = {2: ("heartbeat_version", "pulse_status", "refuse_over_current", "refuse_too_long",
                  "survives_garbage", "heartbeat_period", "src_matches_node", "time_sync"),
              16: ("heartbeat_version", "mag_stream", "mag_timestamps", "survives_garbage",
                   "heartbeat_period", "src_matches_node", "time_sync")}


def assert_conforms(rep, signed=False):
    assert rep.nodes == {2: "coil driver", 16: "sensor"}, rep.format()
    for rule in CORE:
        assert rep.result(rule).status == PASS, rep.format()
    for node, rules in NODE_RULES.items():
        for rule in rules:
            assert rep.result(rule, node).status == PASS, rep.format()
    for rule in ("signed_accepted", "unsigned_rejected", "forged_rejected", "replay_rejected"):
        assert rep.result(rule, 2).status == (PASS if signed else SKIP), rep.format()
    assert rep.ok and rep.failed == 0
    assert rep.messages["MAG_SAMPLE"]["bad"] == 0 and rep.messages["COIL_STATUS"]["count"] >= 3


@pytest.fixture
def pty():
    master, slave, path = open_pty()
    yield master, path
    os.close(master)
    os.close(slave)


def test_serial_pty(pty, emulator_factory, wall):
    master, path = pty
    link = SerialLink(path)                       # open before the node starts: its first heartbeat is heard
    emulator_factory(FdPort(master))
    rep = run_conformance(link, ConformOptions(**wall), transport="serial")
    link.close()
    assert_conforms(rep)


def run_lockstep(lockstep, tester, node_side, options, transport, **emulator_kw):
    """The suite on injected time: tester and emulator nodes in one thread."""
    ls = lockstep(node_side, **emulator_kw)
    return Conformance(tester, options, transport, clock=ls.now, sleep=ls.sleep).run()


def test_virtual_can_with_signing_driver(lockstep, fast):
    tester, node_side = virtual_link_pair(1, 2)
    verifier = SignatureVerifier(KEY)
    rep = run_lockstep(lockstep, tester, node_side, ConformOptions(key=KEY, **fast), "CAN virtual",
                       verifier=verifier)
    tester.close()
    assert_conforms(rep, signed=True)
    # the identical re-sent frame is already dropped as a duplicate by the CAN
    # reassembler; the command with a stale timestamp reaches the verifier
    assert verifier.unsigned >= 1 and verifier.forged >= 1 and verifier.replayed >= 1
    assert verifier.replayed + node_side.reassembler.duplicates >= 2
    assert tester.reassembler.frames_bad == 0


def test_slcan_over_ptys(emulator_factory, wall):
    with SlcanBridge(2) as br:
        node_side = CanLink(open_bus("slcan", br.paths[0]), 2)
        tester = CanLink(open_bus("slcan", br.paths[1]), 1)
        assert br.wait_open()
        emu = emulator_factory(node_side)
        rep = run_conformance(tester, ConformOptions(**wall), transport="CAN slcan")
        emu.stop()
        tester.close()
        node_side.close()
        assert br.bad_lines == 0
    assert_conforms(rep)


def test_driver_without_limits_fails_refusal_rules(pipes, lockstep, fast):
    tester, node_side = pipes()
    rep = run_lockstep(lockstep, tester, node_side, ConformOptions(node=2, **fast), "in-memory serial",
                       limits=DriverLimits(max_current_a=100.0, max_pulse_us=60_000_000, max_duty=1.0,
                                           duty_window_us=10**9))
    assert rep.result("pulse_status", 2).status == PASS
    assert rep.result("refuse_over_current", 2).status == FAIL
    assert rep.result("refuse_too_long", 2).status == FAIL
    assert not rep.ok and 16 not in rep.nodes


def test_unsigned_tester_against_signing_driver_explains(lockstep, fast):
    tester, node_side = virtual_link_pair(1, 2)
    rep = run_lockstep(lockstep, tester, node_side, ConformOptions(node=2, **fast), "CAN virtual",
                       verifier=SignatureVerifier(KEY))
    tester.close()
    r = rep.result("pulse_status", 2)
    assert r.status == FAIL and "pass a key" in r.detail


class _BadNode:
    """A node built from another schema: wrong hash, skips sequence numbers,
    sends a corrupted frame now and then."""

    def __init__(self):
        self.enc = FrameEncoder(5)
        self.n = 0

    def read(self) -> bytes:
        self.n += 1
        hb = MSG["HEARTBEAT"](5, 3, 2, PROTOCOL_VERSION, SCHEMA_HASH ^ 0xFF, 0)
        out = self.enc.encode(hb)
        if self.n % 50 == 0:
            self.enc.seq += 3
        if self.n % 70 == 0:
            out = out[:4] + bytes([out[4] ^ 0x40]) + out[5:]
        return out

    def write(self, data: bytes) -> None:
        pass


def test_bad_node_is_reported(sim_clock):
    rep = Conformance(_BadNode(), ConformOptions(observe_s=0.2, optional_wait_s=0.02), "fake",
                      clock=sim_clock.now, sleep=sim_clock.sleep).run()
    assert rep.result("heartbeat").status == PASS
    v = rep.result("heartbeat_version", 5)
    assert v.status == FAIL and "schema hash" in v.detail
    assert rep.result("frames_valid").status == FAIL
    assert rep.result("sequence").status == FAIL
    assert rep.result("time_sync", 5).status == FAIL
    assert rep.messages["HEARTBEAT"]["bad"] > 0
    assert not rep.ok
    assert json.loads(rep.to_json())["failed"] == rep.failed


def test_no_node_at_all(sim_clock):
    class Silent:
        def read(self):
            return b""

        def write(self, data):
            pass

    rep = Conformance(Silent(), ConformOptions(heartbeat_timeout_s=0.1), "fake", clock=sim_clock.now,
                      sleep=sim_clock.sleep).run()
    assert rep.result("heartbeat").status == FAIL and not rep.ok


# ------------------------------------------------------------- the command
def test_conform_command_serial(pty, emulator_factory, capsys, tmp_path):
    master, path = pty
    emulator_factory(FdPort(master))
    out_json = tmp_path / "conform.json"
    rc = main(["conform", "--transport", "serial", "--port", path, "--observe", "0.4", "--lead-ms", "200", "--answer-timeout", "5",
               "--sync-period", "1", "--json", str(out_json)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "CONFORMS" in text and "MAG_SAMPLE" in text and "refuse_over_current" in text
    assert json.loads(out_json.read_text())["ok"] is True


def test_conform_command_virtual_can_with_key(emulator_factory, capsys):
    channel = unique_channel("conform")
    node_side = CanLink(open_bus("virtual", channel), 2)
    emulator_factory(node_side, verifier=SignatureVerifier(KEY))
    rc = main(["conform", "--transport", "can", "--interface", "virtual", "--channel", channel,
               "--key", KEY.hex(), "--observe", "0.4", "--lead-ms", "200", "--answer-timeout", "5", "--sync-period", "1"])
    text = capsys.readouterr().out
    assert rc == 0, text
    for rule in ("unsigned_rejected", "forged_rejected", "replay_rejected"):
        assert any(line.split()[:1] == ["PASS"] and rule in line for line in text.splitlines()), text


def test_conform_against_emulator_process():
    """`coiltrack emulator --create-pty` in its own process (scenario
    `static`), the conformance command in this one."""
    import subprocess
    import sys

    emu = subprocess.Popen([sys.executable, "-m", "coiltrack.tools.cli", "emulator", "--create-pty", "--scenario", "static",
                            "--duration", "20"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        path = emu.stdout.readline().strip()
        assert path.startswith("/dev/"), emu.stderr.read() if emu.poll() is not None else path
        rep = run_conformance(SerialLink(path), ConformOptions(observe_s=0.4, lead_ms=200.0, pulse_ms=10.0,
                                                               silence_s=0.12, optional_wait_s=0.1,
                                                               answer_timeout_s=5.0, sync_period_s=1.0),
                               transport="serial")
        assert_conforms(rep)
    finally:
        emu.kill()
        emu.wait(timeout=5)


class _SteppingSync:
    """A node's time sync that takes each broadcast's offset at once (no envelope, no slewing): what
    a plausible first implementation does. Same interface as hil.clock.NodeSync."""

    def __init__(self):
        self.off = 0
        self.synced = False

    def reset(self):
        self.synced = False

    def update(self, local_rx_us, master_us):
        self.off = int(master_us) - int(local_rx_us)
        self.synced = True
        return False

    def to_master(self, local_us):
        return int(local_us) + self.off

    def to_local(self, master_us):
        return int(master_us) - self.off

    offset_us = property(lambda self: -self.off)
    drift_ppb = property(lambda self: 0)


class _SteppingSensor(SensorNode):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.sync = _SteppingSync()


class _LateWorld:
    """The world as a sensor sees it that applies the coil field 70 ms late (after a 60 ms pulse has
    ended): every field is the one of 70 ms before."""

    def __init__(self, world, lag_us=70_000):
        self.world, self.lag = world, lag_us

    def field_sensor_frame(self, t):
        return self.world.field_sensor_frame(t - self.lag)

    def precompute(self, ts):
        return self.world.precompute([t - self.lag for t in ts])

    def __getattr__(self, name):
        return getattr(self.world, name)


class _LateFieldSensor(SensorNode):
    def __init__(self, node_id, world, **kw):
        super().__init__(node_id, _LateWorld(world), **kw)


BENCH = dict(bench=True, bench_pulses=4)


def test_stepping_clock_correction_fails_mag_grid(pipes, lockstep, fast):
    """A sensor whose clock correction steps at every broadcast passes every other rule (its stamps
    increase, at the right rate), yet with the firmware its stamps jump off the sample grid whenever a
    broadcast arrives late: mag_grid fails it, with the interval it was off. The reference node (which
    slews) passes with its margin. Catches a grid rule that ignores late broadcasts or a tolerance
    looser than the firmware's 400 us."""
    tester, node_side = pipes()
    rep = run_lockstep(lockstep, tester, node_side, ConformOptions(node=16, **fast), "in-memory serial",
                       sensor_cls=_SteppingSensor)
    r = rep.result("mag_grid", 16)
    assert r.status == FAIL and "slew" in r.detail, r.detail
    assert rep.result("mag_stream", 16).status == PASS and rep.result("mag_timestamps", 16).status == PASS
    tester, node_side = pipes()
    rep = run_lockstep(lockstep, tester, node_side, ConformOptions(node=16, **fast), "in-memory serial")
    r = rep.result("mag_grid", 16)
    assert r.status == PASS and "margin" in r.detail, r.detail


def test_bench_mode_pulse_seen_in_the_window(pipes, lockstep, fast):
    """Bench mode with the reference driver and sensor on one coil: the pulse is seen in every
    window sample and nowhere else; the edges are bracketed to a quarter of the 8.3 ms sample period
    and lie within the coil's L/R rise (2.3 ms) of the command. Catches edges measured against the
    wrong reference (a pulse-length offset) or a bracket that never narrows."""
    tester, node_side = pipes()
    rep = run_lockstep(lockstep, tester, node_side, ConformOptions(**BENCH, **fast), "in-memory serial")
    r = rep.result("bench_pulse", 16)
    assert r.status == PASS, r.detail
    import re
    rise = [float(v) for v in re.search(r"rise edge at ([+-]\d+)\.\.([+-]\d+) us", r.detail).groups()]
    fall = [float(v) for v in re.search(r"fall edge at ([+-]\d+)\.\.([+-]\d+) us", r.detail).groups()]
    assert -8_400 / 4 - 1 <= rise[0] <= rise[1] <= 2_300 + 8_400 / 4 and rise[1] - rise[0] <= 8_400 / 4 + 1
    assert -8_400 / 4 - 1 <= fall[0] <= fall[1] <= 2_300 + 8_400 / 4 and fall[1] - fall[0] <= 8_400 / 4 + 1


def test_bench_mode_fails_a_sensor_that_applies_the_field_late(pipes, lockstep, fast):
    """A sensor that shows each pulse's field only after the pulse ended passed every rule of the
    plain suite (the firmware's poses were then a metre off): bench mode fails it."""
    tester, node_side = pipes()
    rep = run_lockstep(lockstep, tester, node_side, ConformOptions(**BENCH, **fast), "in-memory serial",
                       sensor_cls=_LateFieldSensor)
    assert rep.result("mag_stream", 16).status == PASS
    r = rep.result("bench_pulse", 16)
    assert r.status == FAIL and ("no field in the window" in r.detail or "quiet samples" in r.detail), r.detail
