"""The DBC export: cantools loads it and decodes the golden CAN frames of
single-frame messages, and the reassembled payloads of the others, to the
same physical values as the schema."""
import cantools
import pytest

from coiltrack.protocol.can import PDU_OVERHEAD, CanReassembler, build_pdu
from coiltrack.protocol.codec import physical
from coiltrack.protocol.dbc import payload_from_pdu
from coiltrack.protocol.examples import EXAMPLES
from coiltrack.protocol.golden import GOLDEN_DIR, read_can_log
from coiltrack.tools.cli import main


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    path = tmp_path_factory.mktemp("dbc") / "coiltrack.dbc"
    assert main(["dbc", "-o", str(path)]) == 0
    return cantools.database.load_file(str(path), frame_id_mask=0x7E0)


def expected(msg):
    return {f.name: physical(msg, f.name) for f in msg.DEF.fields}


def test_every_message_is_in_the_dbc(db):
    assert sorted(m.name for m in db.messages) == sorted(EXAMPLES)


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_dbc_decodes_golden_frames(db, name):
    ex = EXAMPLES[name]
    frames = read_can_log(GOLDEN_DIR / "can" / f"{name}.log")
    dm = db.get_message_by_frame_id(frames[0].arbitration_id)     # any sender, thanks to the mask
    assert dm.name == name
    if PDU_OVERHEAD + ex.msg.DEF.size <= 7:
        assert len(frames) == 1                                      # single frame: decode it as it is
        values = dm.decode(bytes(frames[0].data))
        assert values["SEQ"] == ex.seq
        assert values["ISOTP_PCI"] == PDU_OVERHEAD + ex.msg.DEF.size
    else:
        assert dm.is_fd
        r = CanReassembler()
        pdus = []
        r.on_frame = lambda h, m: pdus.append(build_pdu(m, h.seq, h.src))
        for f in frames:
            r.feed(f)
        assert len(pdus) == 1
        values = dm.decode(payload_from_pdu(pdus[0], ex.msg.DEF.size))
    for k, v in expected(ex.msg).items():
        assert values[k] == pytest.approx(v, rel=1e-12, abs=0), k
