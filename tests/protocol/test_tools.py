"""The protocol subcommands: decode, golden, dbc (the others are tested with
their subject)."""
import can
import pytest

from coiltrack.protocol import encode_frame
from coiltrack.protocol.can import CanCodec
from coiltrack.protocol.examples import EXAMPLES
from coiltrack.protocol.golden import GOLDEN_DIR
from coiltrack.tools.cli import main


def test_decode_serial_capture_with_bad_frames(tmp_path, capsys):
    data = bytearray()
    for ex in EXAMPLES.values():
        data += encode_frame(ex.msg, ex.seq, ex.src)
    good = encode_frame(EXAMPLES["MAG_SAMPLE"].msg, 1, 16)
    bad = bytearray(good)
    bad[6] ^= 0x01
    data += bytes(bad) + b"\x11\x22\x33\x00" + good
    path = tmp_path / "capture.bin"
    path.write_bytes(bytes(data))
    assert main(["decode", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(EXAMPLES) + 2
    assert lines[0].startswith("src=16  seq=7   HEARTBEAT node=16")
    assert any("MAG_SAMPLE" in l and "x=1234 (6.17e-06 T)" in l for l in lines)
    assert "crc_errors=1" in lines[-1] and "framing_errors=1" in lines[-1]


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log"])
def test_decode_python_can_logs(tmp_path, capsys, suffix):
    path = tmp_path / f"bus{suffix}"
    codec = CanCodec()
    with can.Logger(str(path)) as log:
        t = 1.0
        for ex in EXAMPLES.values():
            for f in codec.encode(ex.msg, ex.seq, ex.src, timestamp=t):
                f.channel = 0
                log(f)
                t += 0.001
        # a lost consecutive frame: counted, not fatal
        frames = codec.encode(EXAMPLES["POSE"].msg, 200, 1, timestamp=t)
        for f in frames[:3] + frames[4:]:
            log(f)
    assert main(["decode", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(EXAMPLES) + 1
    assert "COIL_PULSE_CMD" in lines[3] and "current_ma=1500 (1.5 A)" in lines[3]
    assert "out_of_order=1" in lines[-1]


def test_decode_signed_golden(capsys):
    assert main(["decode", str(GOLDEN_DIR / "serial" / "CONFIG_SET.signed.bin")]) == 0
    assert "CONFIG_SET [signed] node=2 key=258 value=1.75" in capsys.readouterr().out


def test_decode_json(capsys):
    assert main(["decode", "--json", str(GOLDEN_DIR / "can" / "MAG_SAMPLE.log")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert '"name": "MAG_SAMPLE"' in out[0] and '"kind": "can"' in out[-1]


def test_golden_command(tmp_path, capsys):
    assert main(["golden"]) == 0
    assert "match" in capsys.readouterr().out
    assert main(["golden", "--dir", str(tmp_path)]) == 1
    assert main(["golden", "--write", "--dir", str(tmp_path)]) == 0
    assert main(["golden", "--dir", str(tmp_path)]) == 0
