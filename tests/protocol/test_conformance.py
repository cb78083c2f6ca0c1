"""The conformance suite against the emulator's own nodes (hil.nodes) on a
pseudo-terminal, on a virtual CAN bus, and on slcan over ptys; and against
nodes that break rules, to show the suite catches them."""
import json
import os

import pytest

from coiltrack.hil.nodes import DriverLimits
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
        hb = MSG["HEARTBEAT"](5, 3, 2, PROTOCOL_VERSION, SCHEMA_HASH ^ 0xFF, self.n * 1000, 0)
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
    rc = main(["conform", "--transport", "serial", "--port", path, "--observe", "0.4", "--lead-ms", "200",
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
               "--key", KEY.hex(), "--observe", "0.4", "--lead-ms", "200", "--sync-period", "1"])
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
