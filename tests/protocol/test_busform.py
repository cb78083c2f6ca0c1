"""Protocol v3/v4 bus forms: the frequent messages longer than 8 bytes (HEARTBEAT, TIME_SYNC,
COIL_PULSE_CMD, COIL_STATUS, TIME_SYNC_REPLY) in one classic frame, decoded straight off the bus by cantools
with the exported DBC, restored by the receiver exactly, refused at a wrong length, and sent
in full (29-bit identifier, segmented) whenever the form cannot carry a message exactly."""
from __future__ import annotations

import can
import cantools
import pytest

from coiltrack.protocol.busform import BusContext, restore_start
from coiltrack.protocol.can import CanCodec, CanReassembler, can_id, ext_id
from coiltrack.protocol.codec import MSG
from coiltrack.protocol.errors import LengthError
from coiltrack.protocol.examples import EXAMPLES, example_context
from coiltrack.protocol.golden import GOLDEN_DIR, read_can_log
from coiltrack.protocol.schema import BUS_FORMS, NODE_COIL_DRIVER, NODE_FIRMWARE
from coiltrack.tools.cli import main

BUS = ("HEARTBEAT", "TIME_SYNC", "COIL_PULSE_CMD", "COIL_STATUS", "TIME_SYNC_REPLY")
CMD = EXAMPLES["COIL_PULSE_CMD"].msg
#: the golden field values by hand, as cantools must give them (physical units of the DBC)
WANT = {
    "HEARTBEAT": dict(role=2, state=2, proto_version=4, errors=3, schema_hash=EXAMPLES["HEARTBEAT"].msg.schema_hash),
    "TIME_SYNC": dict(master_time_us=2_000_150_250, sync_seq=42),
    # start modulo 8 us * 2^18 = 2097152 us; duration in us (16 us units times 16)
    "COIL_PULSE_CMD": dict(coil=1, pulse_id=513, current_ma=1.5, start_8us=2_000_200_000 % 2_097_152,
                           duration_us=60_000),
    # the status's edges less the command's: 13 us late, 12 us early
    "COIL_STATUS": dict(coil=1, pulse_id=513, current_ma=1.497, faults=64, start_late_us=13, end_late_us=-12),
    # sync_seq 42 mod 64; node time less (TIME_SYNC master time 2000150250 + offset -127): 377 us late
    "TIME_SYNC_REPLY": dict(sync_seq_lo=42, node_time_late_us=377, offset_us=-127, drift_ppb=-2500),
}


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    path = tmp_path_factory.mktemp("dbc") / "coiltrack.dbc"
    assert main(["dbc", "-o", str(path)]) == 0
    return cantools.database.load_file(str(path), frame_id_mask=0x7C0)


def test_the_bus_forms_are_the_frequent_long_messages():
    """One bus form per frequent message longer than 8 bytes, each exactly 64 bits without
    overlaps (a field one bit too wide overlaps the next and corrupts it)."""
    assert [b.name for b in BUS_FORMS] == list(BUS)
    for b in BUS_FORMS:
        bits = [0] * 64
        for f in b.fields:
            for k in range(f.first_bit, f.first_bit + f.bits):
                bits[k] += 1
        assert bits == [1] * 64, b.name


@pytest.mark.parametrize("variant", ["", ".fd"])
@pytest.mark.parametrize("name", BUS)
def test_cantools_decodes_the_golden_single_frame(db, name, variant):
    """The golden frame of each frequent message is one 8-byte frame on the 11-bit identifier,
    and cantools (``get_message_by_frame_id(id).decode(data)``, the DBC from ``coiltrack dbc``)
    gives the example's field values (a DBC with a start bit, a sign or a scale wrong, or one
    still describing the segmented or FD layout, gives other values or raises)."""
    (f,) = read_can_log(GOLDEN_DIR / "can" / f"{name}{variant}.log")
    assert len(f.data) == 8 and not f.is_extended_id and f.is_fd == bool(variant)
    dm = db.get_message_by_frame_id(f.arbitration_id)
    assert dm.name == name and dm.length == 8
    got = dm.decode(bytes(f.data))
    assert set(got) == set(WANT[name])
    for k, v in WANT[name].items():
        assert got[k] == pytest.approx(v, rel=1e-12, abs=0), k


@pytest.mark.parametrize("name", BUS)
def test_receiver_restores_the_example_exactly(name):
    """A station that heard the TIME_SYNC and the command restores each golden frame to the full
    example (lossless: a rounded duration, a start unwrapped into the wrong 2.1 s window or an
    edge offset with the wrong sign differ)."""
    (f,) = read_can_log(GOLDEN_DIR / "can" / f"{name}.log")
    r = CanReassembler(context=example_context())
    assert r.feed(f) == [EXAMPLES[name].msg] and r.frames_bad == 0


@pytest.mark.parametrize("n", [0, 7])
@pytest.mark.parametrize("name", BUS)
def test_a_frame_of_the_wrong_length_is_refused(db, name, n):
    """7 bytes (or none) on a bus-form identifier: the reassembler counts a length error and
    gives nothing, the strict decoder raises LengthError, cantools refuses it (a decoder that
    zero-filled the missing byte would give a wrong schema hash, time or edge)."""
    (f,) = read_can_log(GOLDEN_DIR / "can" / f"{name}.log")
    short = can.Message(arbitration_id=f.arbitration_id, is_extended_id=False, data=bytes(f.data)[:n])
    r = CanReassembler(context=example_context())
    assert r.feed(short) == [] and r.length_errors == 1
    with pytest.raises(LengthError):
        CanCodec.decode_frames([short], context=example_context())
    with pytest.raises(Exception):
        db.get_message_by_frame_id(f.arbitration_id).decode(bytes(f.data)[:n])


def _window_reference(bits: int, ref: int) -> int:
    """The start by enumeration: of every multiple of 8 us within 3 s of ``ref`` whose us / 8 has
    these low 18 bits, the one in [ref - 524288, ref + 1572864)."""
    cands = (8 * (bits + j * (1 << 18)) for j in range((ref - 3_000_000) // 2_097_152, (ref + 3_000_000) // 2_097_152 + 2))
    hits = [t for t in cands if ref - 524_288 <= t < ref + 1_572_864]
    assert len(hits) == 1
    return hits[0]


@pytest.mark.parametrize("ref", [2_000_150_250, 1_048_576, 600_000, 2**47 + 3])
def test_start_restores_within_its_window(ref):
    """Starts across the window (late by up to 0.52 s, ahead by up to 1.57 s, at the wrap of the
    18 bits) restore to the brute-force answer; just outside it they alias by 2.097152 s (a window
    centred on ``ref``, or a truncating rather than flooring unwrap, fails here)."""
    for t in (ref - 524_288, ref - 524_288 + 8, ref - 1000, ref, ref + 400_000, ref + 1_572_864 - 8):
        t -= t % 8
        if t < ref - 524_288:
            t += 8
        bits = (t // 8) % (1 << 18)
        assert restore_start(bits, ref) == _window_reference(bits, ref) == t, t
    edge = ref + 1_572_864 + 8 - (ref % 8)
    assert restore_start((edge // 8) % (1 << 18), ref) == edge - 2_097_152


def _heard(ref: int = 2_000_150_250) -> BusContext:
    ctx = BusContext()
    ctx.note(MSG["TIME_SYNC"](ref, 1))
    return ctx


@pytest.mark.parametrize("change", [
    dict(start_us=2_000_200_004),        # off the 8 us grid
    dict(duration_us=60_008),            # off the 16 us grid
    dict(duration_us=270_000),           # above 262.128 ms
    dict(pulse_id=4096),                 # 13 bits
    dict(coil=16),
    dict(start_us=2_000_150_250 + 1_600_000),   # beyond the window ahead of the TIME_SYNC
])
def test_a_command_the_form_cannot_carry_goes_in_full(change):
    """Lossless: a command outside the bus form travels as the segmented full PDU on the 29-bit
    identifier and arrives unchanged (a codec that rounded or masked it would execute another
    pulse than the one commanded)."""
    cmd = CMD._replace(**change)
    codec = CanCodec(context=_heard())
    fr = codec.encode(cmd, 7, NODE_FIRMWARE)
    assert len(fr) > 1 and all(f.is_extended_id and f.arbitration_id >> 18 == can_id(cmd.ID, 1) for f in fr)
    assert codec.fallbacks == 1
    r = CanReassembler(context=_heard())
    assert [m for f in fr for m in r.feed(f)] == [cmd] and r.frames_bad == 0


def test_no_time_sync_heard_sends_in_full_and_a_bus_form_is_not_guessed():
    """Before any TIME_SYNC the sender has no window: the full form. A receiver that heard none
    drops a bus-form command and counts it (restoring it against 0 would schedule a pulse 2000 s
    early)."""
    fr = CanCodec().encode(CMD, 3, NODE_FIRMWARE)
    assert all(f.is_extended_id for f in fr) and len(fr) == 3
    (bus_frame,) = CanCodec(context=_heard()).encode(CMD, 3, NODE_FIRMWARE)
    r = CanReassembler()
    assert r.feed(bus_frame) == [] and r.unresolved == 1 and r.frames_bad == 1


def test_status_edges_relative_to_the_heard_command():
    """The driver's status goes as a bus form only with its command heard and its edges within
    2047 us; 2048 us late, a refusal's zero edges or an unknown pulse id go in full; a receiver
    restores each exactly (an edge relative to the status's own start, or a sign lost, differs)."""
    drv = CanCodec(context=_heard())
    drv.context.note(CMD)
    st = MSG["COIL_STATUS"](1, 513, 1490, CMD.start_us - 2047, CMD.start_us + CMD.duration_us + 2047, 0)
    for msg, frames in ((st, 1), (st._replace(start_us=CMD.start_us + 2048), 4),
                        (st._replace(start_us=0, end_us=0, faults=16), 4), (st._replace(pulse_id=514), 4),
                        (st._replace(coil=2), 4)):
        fr = drv.encode(msg, 4, NODE_COIL_DRIVER)
        assert len(fr) == frames, msg
        fw = CanReassembler(context=_heard())
        fw.context.note(CMD)
        assert [m for f in fr for m in fw.feed(f)] == [msg]


def test_canlink_stations_learn_the_context_from_the_bus():
    """Firmware and driver links: the firmware's TIME_SYNC and command teach both sides, so the
    command and the driver's status travel as one frame each and arrive whole (a link that did
    not note what it sent itself, or what it heard, falls back or drops the status)."""
    from coiltrack.protocol import FrameDecoder, encode_frame
    from coiltrack.protocol.can import virtual_link_pair

    fw, drv = virtual_link_pair(NODE_FIRMWARE, NODE_COIL_DRIVER)
    try:
        ts = MSG["TIME_SYNC"](2_000_150_250, 9)
        fw.write(encode_frame(ts, 1, NODE_FIRMWARE) + encode_frame(CMD, 2, NODE_FIRMWARE))
        assert FrameDecoder().feed(drv.read()) == [ts, CMD]
        st = EXAMPLES["COIL_STATUS"].msg
        drv.write(encode_frame(st, 5, NODE_COIL_DRIVER))
        assert FrameDecoder().feed(fw.read()) == [st]
        assert fw.frames_tx == 2 and drv.frames_tx == 1
        assert fw.codec.fallbacks == drv.codec.fallbacks == 0 and fw.reassembler.frames_bad == 0
    finally:
        fw.close()
        drv.close()


def test_signed_command_stays_segmented_and_teaches_the_context():
    """A signed command is never a bus form (the signature covers the full payload); its receiver
    still learns the command, so the status of a signed pulse is one frame too."""
    from coiltrack.protocol.examples import SIGNING_KEY
    from coiltrack.protocol.signing import Signer

    raw = Signer(SIGNING_KEY, 1).signed_frame(CMD, 3, NODE_FIRMWARE, 5)
    codec = CanCodec(context=_heard())
    fr = codec.frames_from_raw(raw)
    assert len(fr) > 1 and all(f.is_extended_id and f.arbitration_id == ext_id(can_id(CMD.ID, 1)) for f in fr)
    r = CanReassembler(context=_heard())
    assert [m for f in fr for m in r.feed(f)] == [CMD]
    assert r.context.commands[513] == (1, CMD.start_us, CMD.duration_us)
