"""Golden byte vectors (protocol/golden/): regenerated and compared byte for
byte; each decodes back to its example on its link."""
import pytest

from coiltrack.protocol import FrameDecoder, SignatureVerifier, decode_frame
from coiltrack.protocol.can import CanReassembler, is_direct
from coiltrack.protocol.examples import EXAMPLES, SIGNING_KEY, example_context
from coiltrack.protocol.golden import GOLDEN_DIR, check_golden, format_can_log, golden_files, read_can_log, write_golden


def test_golden_files_are_current():
    """Fails when the schema, the codecs or the examples change the bytes:
    review the change, then run `coiltrack golden --write`."""
    assert check_golden() == []


def test_golden_covers_every_message_and_link():
    files = golden_files()
    for name in EXAMPLES:
        assert f"serial/{name}.bin" in files and f"can/{name}.log" in files
        assert (GOLDEN_DIR / "serial" / f"{name}.bin").is_file()
        assert (GOLDEN_DIR / "can" / f"{name}.log").is_file()


def test_write_golden_to_another_directory(tmp_path):
    written = write_golden(tmp_path)
    assert len(written) == len(golden_files())
    assert check_golden(tmp_path) == []
    assert write_golden(tmp_path) == []                     # unchanged files are not rewritten
    (tmp_path / "serial" / "MAG_SAMPLE.bin").write_bytes(b"\x00")
    (tmp_path / "can" / "EXTRA.log").write_text("")
    assert check_golden(tmp_path) == ["differs serial/MAG_SAMPLE.bin", "unexpected can/EXTRA.log"]


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_serial_vector_decodes(name):
    ex = EXAMPLES[name]
    data = (GOLDEN_DIR / "serial" / f"{name}.bin").read_bytes()
    assert decode_frame(data) == ex.msg
    d = FrameDecoder()
    assert d.feed(data) == [ex.msg] and (d.header.src, d.header.seq) == (ex.src, ex.seq)


@pytest.mark.parametrize("name", list(EXAMPLES))
@pytest.mark.parametrize("variant", ["", ".fd"])
def test_can_vector_reads_with_python_can_and_reassembles(name, variant):
    ex = EXAMPLES[name]
    path = GOLDEN_DIR / "can" / f"{name}{variant}.log"
    frames = read_can_log(path)
    assert frames and all(f.is_fd == bool(variant) for f in frames)
    assert format_can_log(frames).encode() == path.read_bytes()        # python-can reads what we wrote
    r = CanReassembler(context=example_context())   # the bus forms of command and status: against the examples
    out = [p for f in frames for p in r.feed_with_headers(f)]
    assert [m for _, m in out] == [ex.msg]
    # a single frame carries no seq: the receiver numbers it (0: the first from that sender)
    direct = is_direct(ex.msg.ID, bool(variant))
    src = ex.msg.node if direct and ex.msg.DEF.sender_field else ex.src
    assert (out[0][0].src, out[0][0].seq) == (src, 0 if direct else ex.seq)


@pytest.mark.parametrize("name", [n for n, e in EXAMPLES.items() if e.msg.DEF.signable])
def test_signed_vectors_verify_on_both_links(name):
    ex = EXAMPLES[name]
    d = FrameDecoder(verifier=SignatureVerifier(SIGNING_KEY))
    assert d.feed((GOLDEN_DIR / "serial" / f"{name}.signed.bin").read_bytes()) == [ex.msg]
    r = CanReassembler(verifier=SignatureVerifier(SIGNING_KEY))
    frames = read_can_log(GOLDEN_DIR / "can" / f"{name}.signed.log")
    assert [m for f in frames for m in r.feed(f)] == [ex.msg]


def test_examples_are_exact_round_trips():
    for ex in EXAMPLES.values():
        assert ex.msg == decode_frame(golden_files()[f"serial/{ex.name}.bin"])
