"""The DBC export: cantools loads it and decodes the golden CAN frames straight
off the bus (every single frame: the classic samples, every CAN FD frame) and
the reassembled payloads of classic segmented messages, to the same physical
values as the schema."""
import cantools
import pytest

from coiltrack.protocol.can import CanReassembler, build_pdu, is_direct
from coiltrack.protocol.codec import physical
from coiltrack.protocol.dbc import dbc_data
from coiltrack.protocol.examples import EXAMPLES
from coiltrack.protocol.golden import GOLDEN_DIR, read_can_log
from coiltrack.protocol.schema import STAMP_FLIP, STAMP_LSB_US, STAMP_MASK, STAMP_SATURATED
from coiltrack.tools.cli import main

#: the frequent messages of issue 11: they must decode straight off the bus
FREQUENT = ("MAG_PACKED", "IMU_DELTA", "COIL_PULSE_CMD", "COIL_STATUS", "HEARTBEAT", "TIME_SYNC",
            "TIME_SYNC_REPLY")
#: the frequent messages longer than 8 bytes: their bus forms (protocol v3; the reply's v4)
BUS_FORMS = ("COIL_PULSE_CMD", "COIL_STATUS", "HEARTBEAT", "TIME_SYNC", "TIME_SYNC_REPLY")


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    path = tmp_path_factory.mktemp("dbc") / "coiltrack.dbc"
    assert main(["dbc", "-o", str(path)]) == 0
    return cantools.database.load_file(str(path), frame_id_mask=0x7C0)


def expected_bus_form(msg):
    """Physical values of a bus form's signals, by hand from the example values: the command's
    start modulo 8 us * 2**18, the status's edges less the example command's (13 us late, 12 us
    early), role and state as they are."""
    cmd = EXAMPLES["COIL_PULSE_CMD"].msg
    if msg.NAME == "HEARTBEAT":
        return dict(role=msg.role, state=msg.state, proto_version=msg.proto_version, errors=msg.errors,
                    schema_hash=msg.schema_hash)
    if msg.NAME == "TIME_SYNC":
        return dict(master_time_us=msg.master_time_us, sync_seq=msg.sync_seq)
    if msg.NAME == "COIL_PULSE_CMD":
        return dict(coil=msg.coil, pulse_id=msg.pulse_id, current_ma=msg.current_ma * 1e-3,
                    start_8us=msg.start_us % (8 << 18), duration_us=msg.duration_us)
    if msg.NAME == "TIME_SYNC_REPLY":
        ts = EXAMPLES["TIME_SYNC"].msg        # the echoed broadcast (same sync_seq)
        return dict(sync_seq_lo=msg.sync_seq % 64, node_time_late_us=msg.node_time_us - ts.master_time_us - msg.offset_us,
                    offset_us=msg.offset_us, drift_ppb=msg.drift_ppb)
    assert msg.NAME == "COIL_STATUS"
    return dict(coil=msg.coil, pulse_id=msg.pulse_id, current_ma=msg.current_ma * 1e-3, faults=msg.faults,
                start_late_us=msg.start_us - cmd.start_us, end_late_us=msg.end_us - cmd.start_us - cmd.duration_us)


def expected(msg):
    """Physical values per DBC signal, computed from the schema (the sender byte is the id's)."""
    if msg.NAME in BUS_FORMS:
        return expected_bus_form(msg)
    out = {}
    for i, f in enumerate(msg.DEF.fields):
        if i == 0 and msg.DEF.sender_field:
            continue
        raw = getattr(msg, f.name)
        if f.bits:
            for name, b0, n, scale, _ in f.bits:
                out[name] = ((raw >> b0) & ((1 << n) - 1)) * scale
        else:
            out[f.name] = physical(msg, f.name)
    return out


def check(values, msg):
    want = expected(msg)
    assert set(values) == set(want)
    for k, v in want.items():
        assert values[k] == pytest.approx(v, rel=1e-12, abs=0), k


def test_every_message_is_in_the_dbc(db):
    assert sorted(m.name for m in db.messages) == sorted(EXAMPLES)


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_dbc_decodes_fd_frames_straight_off_the_bus(db, name):
    """Every message is one CAN FD frame; ``get_message_by_frame_id(id).decode(data)`` on it
    gives the schema values (a DBC that kept the v1 ISO-TP or reassembled-payload layout,
    or kept the sender byte, decodes garbage or raises)."""
    ex = EXAMPLES[name]
    frames = read_can_log(GOLDEN_DIR / "can" / f"{name}.fd.log")
    assert len(frames) == 1
    f = frames[0]
    dm = db.get_message_by_frame_id(f.arbitration_id)      # any sender, thanks to the mask
    assert dm.name == name
    check(dm.decode(bytes(f.data)), ex.msg)
    if ex.msg.DEF.sender_field:
        assert f.arbitration_id & 0x3F == ex.msg.node


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_dbc_decodes_classic_frames(db, name):
    """Classic bus: a single frame decodes as it is; a segmented message's reassembled payload
    decodes after ``dbc_data``."""
    ex = EXAMPLES[name]
    frames = read_can_log(GOLDEN_DIR / "can" / f"{name}.log")
    dm = db.get_message_by_frame_id(frames[0].arbitration_id)
    assert dm.name == name
    if is_direct(ex.msg.ID, False):
        assert len(frames) == 1 and len(frames[0].data) <= 8 and not dm.is_fd
        values = dm.decode(bytes(frames[0].data))
    else:
        r = CanReassembler()
        pdus = []
        r.on_frame = lambda h, m: pdus.append(build_pdu(m, h.seq, h.src))
        for f in frames:
            r.feed(f)
        assert len(pdus) == 1
        values = dm.decode(dbc_data(ex.msg.ID, pdus[0][1:1 + ex.msg.DEF.size]))
    check(values, ex.msg)


def test_frequent_messages_decode_straight_off_the_bus(db):
    """The issue's list: every frequent message is one 8-byte frame off a classic bus and off a
    CAN FD bus, and the stamp's sub-fields are signals of their own (a mask or start bit off by
    one mixes the flip bit into the time)."""
    for name in FREQUENT:
        for variant in ("", ".fd"):
            f = read_can_log(GOLDEN_DIR / "can" / f"{name}{variant}.log")
            assert len(f) == 1 and len(f[0].data) == 8 and not f[0].is_extended_id, (name, variant)
            dm = db.get_message_by_frame_id(f[0].arbitration_id)
            assert dm.length == 8 and not dm.is_fd, name
    ex = EXAMPLES["MAG_PACKED"]
    f = read_can_log(GOLDEN_DIR / "can" / "MAG_PACKED.log")[0]
    v = db.get_message_by_frame_id(f.arbitration_id).decode(bytes(f.data))
    assert v["flip"] == bool(ex.msg.stamp & STAMP_FLIP) == 1
    assert v["saturated"] == bool(ex.msg.stamp & STAMP_SATURATED) == 0
    assert v["t_8us"] == (ex.msg.stamp & STAMP_MASK) * STAMP_LSB_US == (2_000_208_336 % 131_072)
