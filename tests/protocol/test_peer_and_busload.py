"""Peer admission (schema hash) and the bus load figures."""
import json

import pytest

from coiltrack.protocol import MSG, PROTOCOL_VERSION, SCHEMA_HASH, SchemaMismatchError, check_peer
from coiltrack.protocol.busload import Traffic, bus_load, classic_frame_bits, message_bits
from coiltrack.tools.cli import main

Hb = MSG["HEARTBEAT"]


def test_check_peer_admits_same_schema():
    hb = Hb(16, 2, 2, PROTOCOL_VERSION, SCHEMA_HASH, 5, 0)
    assert check_peer(hb) is hb


def test_check_peer_refuses_other_schema_clearly():
    with pytest.raises(SchemaMismatchError) as e:
        check_peer(Hb(16, 2, 2, PROTOCOL_VERSION, SCHEMA_HASH ^ 1, 5, 0))
    text = str(e.value)
    assert "node 16 (sensor)" in text and f"{SCHEMA_HASH ^ 1:#010x}" in text and f"{SCHEMA_HASH:#010x}" in text
    with pytest.raises(SchemaMismatchError, match="protocol version 9"):
        check_peer(Hb(2, 1, 2, 9, SCHEMA_HASH, 5, 0))
    with pytest.raises(TypeError):
        check_peer(MSG["TIME_SYNC"](1, 2))


def test_worst_case_stuffing_formula():
    # Davis et al. 2007: 135 bits for 8 bytes, 55 for 0 bytes (11-bit id); 160 for 8 bytes (29-bit)
    assert classic_frame_bits(8) == 135
    assert classic_frame_bits(0) == 55
    assert classic_frame_bits(8, extended=True) == 160
    sizes, bits = message_bits("MAG_SAMPLE")
    assert sizes == [8, 8, 7] and bits == 135 + 135 + 125


def test_bus_load_eight_nodes_at_500k():
    rep = bus_load(Traffic(sensors=8), 500_000)
    mag = next(r for r in rep["rows"] if r["message"] == "MAG_SAMPLE")
    assert mag["frames_per_msg"] == 3
    assert mag["bits_per_s"] == pytest.approx(8 * 120 * 395)
    assert rep["total_bits_per_s"] == pytest.approx(sum(r["bits_per_s"] for r in rep["rows"]), rel=1e-9)
    assert not rep["fits"] and rep["max_sensor_nodes"] == 4
    assert bus_load(Traffic(sensors=8), 500_000, fd=True)["fits"]


def test_busload_command(capsys):
    assert main(["busload", "--nodes", "8", "--bitrate", "500000", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["bitrate"] == 500_000 and rep["traffic"]["sensors"] == 8
    assert {r["message"] for r in rep["rows"]} >= {"MAG_SAMPLE", "IMU_SAMPLE", "HEARTBEAT", "COIL_PULSE_CMD",
                                                    "COIL_STATUS", "TIME_SYNC", "POSE"}
    assert main(["busload", "--nodes", "2", "--imu-rate", "0"]) == 0
    out = capsys.readouterr().out
    assert "MAG_SAMPLE" in out and "IMU_SAMPLE" not in out and "fits" in out
