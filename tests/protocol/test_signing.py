"""Signing: HMAC-SHA256/48-bit, 48-bit timestamp, link id; the verifier
rejects unsigned signable commands, forgeries and replays and counts each;
a coil driver in the emulator that requires signatures; signed frames over
CAN."""
import pytest

from coiltrack.protocol import MSG, FrameDecoder, SignatureError, SignatureVerifier, SignedFrameEncoder, Signer, encode_frame
from coiltrack.protocol.can import virtual_link_pair
from coiltrack.protocol.examples import EXAMPLES, SIGNING_KEY, SIGNING_LINK_ID, SIGNING_TIMESTAMP
from coiltrack.protocol.framing import FLAG_SIGNED, SIG_LEN, cobs_decode, parse_frame, DecodedFrame
from coiltrack.protocol.signing import compute_mac, key_from_text, parse_signature

KEY = bytes(range(100, 132))
Cmd = MSG["COIL_PULSE_CMD"]


def cmd(pid=1, start=100_000):
    return Cmd(0, pid, 500, start, 20_000)


def test_signed_frame_layout():
    s = Signer(KEY, link_id=7)
    raw = s.signed_frame(cmd(), seq=3, src=1, timestamp=0x0000_1234_5678)
    hdr = DecodedFrame()
    assert parse_frame(raw, hdr) == cmd()
    assert hdr.flags == FLAG_SIGNED and len(hdr.signature) == SIG_LEN
    link, ts, mac = parse_signature(hdr.signature)
    assert (link, ts) == (7, 0x0000_1234_5678)
    assert mac == compute_mac(KEY, hdr.signed_part, 7, ts)
    assert hdr.signed_part == raw[:-SIG_LEN]


def test_golden_signed_vector_verifies():
    ex = EXAMPLES["COIL_PULSE_CMD"]
    v = SignatureVerifier(SIGNING_KEY)
    d = FrameDecoder(verifier=v)
    from coiltrack.protocol.golden import golden_files
    data = golden_files()["serial/COIL_PULSE_CMD.signed.bin"]
    assert d.feed(data) == [ex.msg]
    link, ts, _ = parse_signature(d.header.signature)
    assert (link, ts) == (SIGNING_LINK_ID, SIGNING_TIMESTAMP)
    assert v.accepted == 1


def test_verifier_rejects_and_counts_each_kind():
    v = SignatureVerifier(KEY, require=True)
    d = FrameDecoder(verifier=v)
    s = Signer(KEY, link_id=1)
    good = s.encode_signed(cmd(1), 0, 1, timestamp=1000)
    assert d.feed(good) == [cmd(1)]
    assert d.feed(good) == []                                               # replay
    assert d.feed(s.encode_signed(cmd(2), 1, 1, timestamp=1000)) == []      # not newer
    assert d.feed(encode_frame(cmd(3), 2, 1)) == []                         # unsigned signable
    assert d.feed(Signer(b"wrong key", 1).encode_signed(cmd(4), 3, 1, timestamp=2000)) == []  # forged
    raw = bytearray(cobs_decode(s.encode_signed(cmd(5), 4, 1, timestamp=3000)[:-1]))
    raw[-7] ^= 1                                                            # altered MAC
    from coiltrack.protocol.framing import cobs_encode
    assert d.feed(cobs_encode(bytes(raw)) + b"\x00") == []
    raw = bytearray(cobs_decode(s.encode_signed(cmd(6), 5, 1, timestamp=4000)[:-1]))
    raw[-12] ^= 1                                                           # altered timestamp
    assert d.feed(cobs_encode(bytes(raw)) + b"\x00") == []
    assert d.feed(encode_frame(MSG["TIME_SYNC"](1, 2), 6, 1)) == [MSG["TIME_SYNC"](1, 2)]  # not signable
    assert d.feed(s.encode_signed(cmd(7), 7, 1, timestamp=5000)) == [cmd(7)]
    assert v.counters() == {"accepted": 2, "unsigned": 1, "forged": 3, "replayed": 2, "passed_unsigned": 1}
    assert d.rejected == 6
    # another link id has its own timestamp history
    assert d.feed(Signer(KEY, link_id=2).encode_signed(cmd(8), 8, 1, timestamp=10)) == [cmd(8)]


def test_verify_raises_signature_error():
    v = SignatureVerifier(KEY)
    d = FrameDecoder()
    d.feed(encode_frame(cmd(), 0, 1))
    with pytest.raises(SignatureError, match="not signed"):
        v.verify(d.header, cmd())


def test_optional_signing_accepts_unsigned():
    v = SignatureVerifier(KEY, require=False)
    d = FrameDecoder(verifier=v)
    assert d.feed(encode_frame(cmd(), 0, 1)) == [cmd()]
    assert d.feed(Signer(b"x" * 32).encode_signed(cmd(), 1, 1)) == []   # a bad signature still fails


def test_signer_timestamps_increase_and_encoder_signs_signable_only():
    s = Signer(KEY)
    a = s.next_timestamp()
    b = s.next_timestamp()
    assert b > a > 0
    enc = SignedFrameEncoder(1, s)
    d = FrameDecoder(verifier=SignatureVerifier(KEY))
    out = d.feed(enc.encode(cmd()) + enc.encode(MSG["TIME_SYNC"](1, 1)) + enc.encode(cmd(2)))
    assert out == [cmd(), MSG["TIME_SYNC"](1, 1), cmd(2)]
    assert d.seq_gaps == 0


def test_key_from_text():
    assert key_from_text("00" * 32) == bytes(32)
    assert len(key_from_text("a passphrase")) == 32
    assert key_from_text("a passphrase") != key_from_text("another")


def test_emulated_coil_driver_requiring_signatures(pipes, world_factory):
    """hil's coil driver behind an Emulator with a verifier: unsigned, forged
    and replayed pulse commands are rejected (and counted); a signed one runs."""
    from coiltrack.hil.emulator import Emulator
    from coiltrack.hil.nodes import CoilDriverNode, Recorder, SensorNode

    world = world_factory()
    host, emu_end = pipes()
    driver = CoilDriverNode(2, world)
    v = SignatureVerifier(KEY)
    emu = Emulator(world, emu_end, driver, [SensorNode(16, world)], Recorder(world), verifier=v)
    signer = Signer(KEY, link_id=1)
    t = 0
    statuses = []
    dec = FrameDecoder(on_frame=lambda h, m: statuses.append(m) if m.NAME == "COIL_STATUS" else None)

    def run_until(t_end):
        nonlocal t
        while t <= t_end:
            emu.step(t)
            dec.feed(host.read())
            t += 1000

    host.write(encode_frame(MSG["TIME_SYNC"](0, 1), 0, 1))                          # the master's clock
    good = signer.encode_signed(cmd(10, 50_000), 0, 1)
    host.write(good)
    host.write(encode_frame(cmd(11, 60_000), 1, 1))                                  # unsigned
    host.write(Signer(b"not the key", 1).encode_signed(cmd(12, 70_000), 2, 1))       # forged
    host.write(good)                                                                  # replayed
    host.write(signer.encode_signed(cmd(13, 400_000), 3, 1, timestamp=signer.last_timestamp))  # stale
    run_until(500_000)
    assert [s.pulse_id for s in statuses] == [10]
    assert statuses[0].faults == 0
    assert v.counters() == {"accepted": 1, "unsigned": 1, "forged": 1, "replayed": 2, "passed_unsigned": 1}
    assert emu.decoder.rejected == 4
    assert len(driver.executed) == 1 and driver.refused == 0


def test_signed_commands_survive_can_transport():
    fw, emu = virtual_link_pair(1, 2)
    try:
        s = Signer(KEY, link_id=3)
        fw.write(s.encode_signed(cmd(1), 0, 1))
        fw.write(encode_frame(cmd(2), 1, 1))
        v = SignatureVerifier(KEY)
        d = FrameDecoder(verifier=v)
        assert d.feed(emu.read()) == [cmd(1)]
        assert v.accepted == 1 and v.unsigned == 1
    finally:
        fw.close()
        emu.close()
