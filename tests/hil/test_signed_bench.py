"""Signed end to end: the firmware signs its coil commands, the emulated nodes require signatures.

The nodes' verifier is the protocol library's (HMAC-SHA256 over the frame, timestamp newer than the
last accepted): these tests check that the firmware's frames pass it with the right key and are
refused, counted and never executed, without it."""
from __future__ import annotations

import dataclasses

from coiltrack.firmware.loop import Firmware
from coiltrack.protocol import FrameDecoder, SignatureVerifier
from coiltrack.protocol.framing import FLAG_SIGNED
from coiltrack.protocol.signing import key_from_text, parse_signature
from coiltrack.tools.outputs import report as report_mod
from coiltrack.tools import scenarios
from coiltrack.tools.bench.links import inproc_pair
from coiltrack.tools.bench.runner import BenchSetup

DURATION = 4.0
KEY = "a bench passphrase"


class _Tap:
    """The firmware's end of the link, keeping a copy of what the firmware wrote."""

    def __init__(self, end):
        self.end = end
        self.sent = bytearray()

    def write(self, b):
        self.sent += b
        self.end.write(b)

    def read(self):
        return self.end.read()


def _run(fw_key: str, node_key: str, sign_ts0: int = 123_456_789):
    sc = scenarios.get("static")
    fw_end, emu_end = inproc_pair()
    base = sc.firmware_config()
    bench = BenchSetup(sc, 2, DURATION, emu_end, None, cfg=base.with_(signing={"signing_key": node_key}))
    cfg = base.with_(signing={"signing_key": fw_key})
    tap = _Tap(fw_end)
    fw = Firmware(cfg, tap, sign_ts0=sign_ts0)
    t = 0
    while t <= int(DURATION * 1e6):
        bench.emulator.step(t)
        fw.tick(t)
        t += cfg.timing.tick_us
    bench.emulator.step(t)
    bench.sent = bytes(tap.sent)
    return bench, fw, report_mod.build(bench, fw.status(), DURATION, transport="inproc", cfg=cfg)


def test_signed_commands_are_accepted_and_executed():
    """Same key: every command the firmware signed is accepted and the run makes its poses. Catches a
    firmware that does not sign (the nodes would refuse every pulse: no pose) or signs with a stale
    timestamp (replays refused)."""
    bench, fw, rep = _run(KEY, KEY)
    sg = rep["signing"]
    assert sg["firmware_signed"] > 0 and sg["accepted"] == sg["firmware_signed"]
    assert sg["unsigned"] == sg["forged"] == sg["replayed"] == 0
    # every accepted command is a pulse (but those commanded ahead for after the end of the run)
    assert sg["accepted"] - 3 <= len(bench.driver.executed) <= sg["accepted"]
    assert rep["poses"] >= int(DURATION / 0.6) - 2


def test_unsigned_or_forged_commands_are_refused_and_never_executed():
    """A firmware without the key (unsigned) or with another key (forged): every command is refused,
    counted by kind, and no coil is ever driven. Catches a verifier that lets an unsigned signable
    command through, or a MAC that does not cover the frame."""
    bench, fw, rep = _run("", KEY)
    assert rep["signing"]["unsigned"] > 0 and rep["signing"]["accepted"] == 0
    assert bench.driver.executed == [] and rep["poses"] == 0
    bench, fw, rep = _run("another key", KEY)
    assert rep["signing"]["forged"] > 0 and rep["signing"]["accepted"] == 0
    assert bench.driver.executed == [] and rep["poses"] == 0


def test_signature_timestamps_follow_the_master_clock():
    """The signature's timestamp is the boot value plus the master clock in 10 us units, strictly
    increasing; only the signable commands are signed. Catches a wall-clock timestamp in the loop
    (not injected) and a signer applied to every frame (each frame 13 bytes longer)."""
    bench, fw, rep = _run(KEY, KEY, sign_ts0=5_000_000)
    seen = []
    ver = SignatureVerifier(key_from_text(KEY))
    # the decoder reuses its header object: keep copies of the fields
    raw = FrameDecoder(verifier=lambda h, m: seen.append((h.flags, bytes(h.signature or b''), m)) or ver(h, m))
    msgs = list(raw.feed(bench.sent))
    signed = [(sig, m) for fl, sig, m in seen if fl & FLAG_SIGNED]
    assert signed and all(m.NAME == "COIL_PULSE_CMD" for _, m in signed)
    assert all(not (fl & FLAG_SIGNED) for fl, _, m in seen if m.NAME != "COIL_PULSE_CMD")
    ts = [parse_signature(sig)[1] for sig, _ in signed]
    assert ts == sorted(set(ts))
    assert 5_000_000 < ts[0] and ts[-1] <= 5_000_000 + int(DURATION * 1e5) + len(ts)
    assert ver.accepted == len(signed) and ver.rejected == 0 and len(msgs) == len(seen)
