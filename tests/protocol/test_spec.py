"""docs/protocol.md stands alone: its algorithms, worked examples, numbers
and hex frames are recomputed here from the document's own text (with the
standard library: hashlib, a bitwise CRC as the document gives it) and
compared with what the code computes, so neither can drift from the other."""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

import can
import pytest

from coiltrack import protocol
from coiltrack.protocol import FrameDecoder, SignatureVerifier, Signer
from coiltrack.protocol.can import MAX_PDU, CanCodec
from coiltrack.protocol.examples import EXAMPLES, SIGNING_KEY, example_context
from coiltrack.protocol.framing import MAX_ENCODED, DecodedFrame, cobs_decode, cobs_encode, frame_crc, parse_frame
from coiltrack.protocol.schema import BUS_FORMS, BY_NAME, MESSAGES, PROTOCOL_VERSION

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
SPACE_MARK = "\u2423"     # the document shows a line's final space as this


@pytest.fixture(scope="module")
def doc() -> str:
    return DOC.read_text()


def blocks(text: str, info: str) -> list[str]:
    """Contents of the fenced code blocks with info string ``info``."""
    return re.findall(r"^```" + re.escape(info) + r"\n(.*?)^```", text, re.S | re.M)


def one(pattern: str, text: str) -> re.Match:
    m = re.search(pattern, text, re.S)
    assert m is not None, f"docs/protocol.md no longer says /{pattern}/"
    return m


def doc_tables(text: str) -> dict[str, tuple[int, list[tuple[str, str]]]]:
    """Message name -> (id, [(type, field), ...]) from the document's field tables."""
    out = {}
    for m in re.finditer(r"^#### `(0x[0-9a-f]{2})` (\w+)\n(.*?)(?=^####|\Z)", text, re.S | re.M):
        rows = re.findall(r"^\| \d+ \| (\w+) \| (\w+) \|", m.group(3), re.M)
        out[m.group(2)] = (int(m.group(1), 16), [(t, f) for f, t in rows])
    return out


def canonical(name: str, fields) -> str:
    """The document's canonical text: NAME, then TYPE FIELD, each followed by a space."""
    return name + " " + "".join(f"{t} {f} " for t, f in fields)


def doc_bus_forms(text: str) -> list[tuple[str, list[tuple[str, str, str]]]]:
    """[(message, [(field, first bit, type), ...]), ...] from the document's bus form tables, in order."""
    out = []
    for m in re.finditer(r"^#### Bus form of (\w+)\n(.*?)(?=^####|\Z)", text, re.S | re.M):
        out.append((m.group(1), re.findall(r"^\| (\d+) \| (\w+) \| ([ui]\d+) \|", m.group(2), re.M)))
    return [(n, [(f, b, t) for b, f, t in rows]) for n, rows in out]


def doc_schema_text(text: str) -> str:
    """The schema-hash input built as the document's algorithm says, from its tables."""
    version = int(one(r"Protocol version (\d+), schema hash", text).group(1))
    lines = [f"coiltrack v{version}"]
    for name, (mid, fields) in sorted(doc_tables(text).items(), key=lambda kv: kv[1][0]):
        lines.append(f"0x{mid:02x} {canonical(name, fields)}")
    for name, fields in doc_bus_forms(text):
        lines.append(f"bus {name} " + "".join(f"{f} {b} {t} " for f, b, t in fields))
    return "\n".join(lines)


def crc16_doc(data: bytes, crc: int = 0xFFFF) -> int:
    """The bitwise CRC of the document's C listing."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


# ------------------------------------------------------------------ schema hash

def test_doc_tables_cover_the_schema(doc):
    """Every message is in the document's field tables (else the hash below would pass on a subset)."""
    tables = doc_tables(doc)
    assert {n: (i, [tuple(x) for x in f]) for n, (i, f) in tables.items()} == {
        m.name: (m.id, [(f.type, f.name) for f in m.fields]) for m in MESSAGES}


def test_doc_bus_form_tables_cover_the_bus_forms(doc):
    """Every bus form is in the document's tables, field by field (else the hash below would pass
    on a document missing one, and an implementer would build another layout)."""
    assert doc_bus_forms(doc) == [(b.name, [(f.name, str(f.first_bit), f"{'i' if f.signed else 'u'}{f.bits}")
                                            for f in b.fields]) for b in BUS_FORMS]


def test_schema_hash_worked_example_follows_the_algorithm(doc):
    """The worked input text is what the described algorithm builds from the tables;
    its SHA-256 and the hash read from it are the document's and the code's."""
    (block,) = blocks(doc, "schema-hash-input")
    text = block.rstrip("\n").replace(SPACE_MARK, " ")
    assert text == doc_schema_text(doc)
    assert len(text.encode()) == int(one(r"the text is (\d+) bytes", doc).group(1))
    digest = hashlib.sha256(text.encode("ascii")).digest()
    assert digest.hex() == one(r"SHA-256 of it:\s*`([0-9a-f]{64})`", doc).group(1)
    first4 = one(r"first four bytes `([0-9a-f ]{11})`", doc).group(1)
    assert bytes.fromhex(first4) == digest[:4]
    stated = int(one(r"\*\*schema hash `(0x[0-9a-f]{8})`\*\*", doc).group(1), 16)
    assert int.from_bytes(digest[:4], "little") == stated == protocol.SCHEMA_HASH
    assert int(one(r"schema hash `0x[0-9a-f]{8}`\*\* \(decimal (\d+)\)", doc).group(1)) == stated
    assert PROTOCOL_VERSION == int(one(r"`PROTOCOL_VERSION` \((\d+)\)", doc).group(1))


# ------------------------------------------------------------------ CRC extra and CRC

def test_crc_extra_worked_example(doc):
    (block,) = blocks(doc, "crc-extra-example")
    canon = one(r"canonical text:\s+(.*?)\n", block).group(1).replace(SPACE_MARK, " ")
    name = canon.split(" ")[0]
    mid, fields = doc_tables(doc)[name]
    assert canon == canonical(name, fields)
    d = hashlib.sha256(canon.encode("ascii")).digest()
    assert d.hex().startswith(one(r"SHA-256:\s+([0-9a-f]+)\.\.\.", block).group(1))
    b0, b1, extra = (int(x, 16) for x in one(r"(0x[0-9a-f]{2}) \^ (0x[0-9a-f]{2}) = (0x[0-9a-f]{2})", block).groups())
    assert (b0, b1) == (d[0], d[1]) and extra == d[0] ^ d[1] == BY_NAME[name].crc_extra


def test_every_crc_extra_in_the_doc_follows_the_algorithm(doc):
    """The CRC extra in each message heading is byte0 ^ byte1 of SHA-256 of the doc's canonical text."""
    tables = doc_tables(doc)
    stated = dict(re.findall(r"^#### `0x[0-9a-f]{2}` (\w+)\n\n.*? CRC extra `(0x[0-9a-f]{2})`", doc, re.M))
    assert stated.keys() == tables.keys()
    for name, (_, fields) in tables.items():
        d = hashlib.sha256(canonical(name, fields).encode("ascii")).digest()
        assert int(stated[name], 16) == d[0] ^ d[1] == BY_NAME[name].crc_extra, name


def test_crc16_as_the_doc_describes_it(doc):
    """The document's CRC (its C listing, its check value, its worked example) is the codec's."""
    check = int(one(r"Check value of the plain CRC for ASCII\s+`123456789`: (0x[0-9A-F]{4})", doc).group(1), 16)
    assert crc16_doc(b"123456789") == check
    (block,) = blocks(doc, "crc-example")
    over, extra, final = (int(x, 16) for x in one(
        r"over header\+payload: (0x[0-9A-F]{4})\ncrc after crc extra (0x[0-9A-F]{2}): (0x[0-9A-F]{4})", block).groups())
    ex = EXAMPLES["MAG_SAMPLE"]
    raw = parse_hex_blocks(doc)[("serial frame, before COBS", "MAG_SAMPLE", False)]
    body = raw[:-2]
    assert crc16_doc(body) == over
    assert extra == BY_NAME[ex.name].crc_extra
    assert crc16_doc(bytes([extra]), over) == final == frame_crc(body, ex.msg.ID)
    assert raw[-2:] == final.to_bytes(2, "little")


# ------------------------------------------------------------------ inline hex frames

_KINDS = ("serial frame, before COBS", "serial frame", "can frames", "can fd frames")


def hex_blocks(text: str):
    """(kind, name, header dict, fields dict, signed, body lines) of every frame example."""
    out = []
    for body in blocks(text, "text"):
        lines = body.strip("\n").split("\n")
        kind = lines[0].removeprefix("# ").strip()
        if kind not in _KINDS:
            continue
        m = re.fullmatch(r"# (\w+) src=(\d+) seq=(\d+)( signed)?: (.*)", lines[1])
        assert m is not None, f"unparsed frame example header: {lines[1]!r}"
        fields = dict(kv.split("=") for kv in m.group(5).split())
        out.append((kind, m.group(1), int(m.group(2)), int(m.group(3)), bool(m.group(4)), fields, lines[2:]))
    return out


def parse_hex_blocks(text: str) -> dict:
    """(kind, name, signed) -> the serial bytes of each serial example."""
    return {(k, n, s): bytes.fromhex(" ".join(b)) for k, n, _, _, s, _, b in hex_blocks(text) if k.startswith("serial")}


def _can_frames(lines, fd: bool) -> list:
    frames = []
    for line in lines:
        ident, data = line.split("##" if fd else "#")
        flags = int(data[0], 16) if fd else 0
        frames.append(can.Message(arbitration_id=int(ident, 16), is_extended_id=False, is_fd=fd,
                                  bitrate_switch=bool(flags & 1), data=bytes.fromhex(data[1:] if fd else data)))
    return frames


def decode_example(kind: str, lines, hdr: DecodedFrame):
    if kind.startswith("serial"):
        data = bytes.fromhex(" ".join(lines))
        if kind == "serial frame":
            assert data.endswith(b"\x00") and data.count(0) == 1, "one COBS frame with its delimiter"
            data = cobs_decode(data[:-1])
        return parse_frame(data, hdr)
    # a station that heard the TIME_SYNC and the command the document shows first (the bus forms
    # of COIL_PULSE_CMD and COIL_STATUS are relative to them)
    return CanCodec.decode_frames(_can_frames(lines, kind == "can fd frames"), hdr, context=example_context())


def _value(text: str):
    return float(text) if "." in text else int(text, 0)


def test_every_inline_hex_frame_decodes_to_the_message_the_doc_says(doc):
    examples = hex_blocks(doc)
    assert {k for k, *_ in examples} == set(_KINDS), "an example of each kind of frame"
    assert len(examples) >= 12
    for kind, name, src, seq, signed, fields, lines in examples:
        hdr = DecodedFrame()
        msg = decode_example(kind, lines, hdr)
        where = f"{kind} {name} in docs/protocol.md"
        assert msg.NAME == name, where
        assert (hdr.src, hdr.seq, bool(hdr.flags & 1)) == (src, seq, signed), where
        assert set(fields) == set(msg._fields), f"{where}: the example names every field"
        assert {k: _value(v) for k, v in fields.items()} == msg._asdict(), where
        if signed:   # signed with the test key the document names
            assert SignatureVerifier(SIGNING_KEY)(hdr, msg), where


def test_doc_frames_are_the_golden_vectors(doc):
    """The serial examples are byte for byte the shipped golden files of the same message."""
    from coiltrack.protocol.golden import GOLDEN_DIR

    for (kind, name, signed), data in parse_hex_blocks(doc).items():
        if kind == "serial frame":
            assert data == (GOLDEN_DIR / "serial" / f"{name}{'.signed' if signed else ''}.bin").read_bytes(), name


# ------------------------------------------------------------------ maximum frame length

def test_maximum_encoded_frame_length(doc):
    """The stated maximum is the codec's bound, is reached by a signed POSE (which a receiver
    accepts), and one byte more is an overflow; the delimiter is not counted."""
    m = one(r"5 \+ (\d+) \+ 2 \+ 13 = (\d+) bytes\s+before COBS", doc)
    n_max = int(one(r"longest\s+encoded frame is \*\*(\d+) bytes, not counting the 0x00 delimiter\*\* \((\d+) with it\)",
                    doc).group(1))
    assert int(m.group(2)) == 5 + int(m.group(1)) + 2 + 13 and int(m.group(1)) == BY_NAME["POSE"].size
    assert n_max == MAX_ENCODED
    pose = EXAMPLES["POSE"]
    enc = cobs_encode(Signer(SIGNING_KEY, 1).signed_frame(pose.msg, pose.seq, pose.src, 1))
    assert len(enc) == n_max
    dec = FrameDecoder()
    assert [x.NAME for x in dec.feed(enc + b"\x00")] == ["POSE"] and dec.frames_bad == 0
    dec.feed(bytes([1]) * (n_max + 1) + b"\x00")
    assert dec.overflows == 1
    unsigned, unsigned_enc = (int(x) for x in one(r"Unsigned, the longest is `POSE` at (\d+) bytes, (\d+) encoded", doc).groups())
    assert len(protocol.encode_frame(pose.msg)) - 1 == unsigned_enc == unsigned + 1
    pdu = one(r"The longest PDU is a signed\s+`POSE`: 1 \+ (\d+) \+ 2 \+ 13 = (\d+) bytes", doc)
    assert int(pdu.group(1)) == BY_NAME["POSE"].size and int(pdu.group(2)) == MAX_PDU


# ------------------------------------------------------------------ links

def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_every_section_link_resolves(doc):
    """A renamed section must not leave the checklist or the contents pointing nowhere."""
    anchors = {_slug(h) for h in re.findall(r"^#{1,4} (.+)$", doc, re.M)}
    links = set(re.findall(r"\]\(#([^)]+)\)", doc))
    assert len(links) >= 20
    assert links <= anchors, sorted(links - anchors)
