"""Peer admission (schema hash) and the bus load figures."""
import json

import pytest

from coiltrack.protocol import MSG, PROTOCOL_VERSION, SCHEMA_HASH, SchemaMismatchError, check_peer
from coiltrack.protocol.busload import Traffic, bus_load, classic_frame_bits, message_bits
from coiltrack.tools.cli import main

Hb = MSG["HEARTBEAT"]


def test_check_peer_admits_same_schema():
    hb = Hb(16, 2, 2, PROTOCOL_VERSION, SCHEMA_HASH, 0)
    assert check_peer(hb) is hb


def test_check_peer_refuses_other_schema_clearly():
    with pytest.raises(SchemaMismatchError) as e:
        check_peer(Hb(16, 2, 2, PROTOCOL_VERSION, SCHEMA_HASH ^ 1, 0))
    text = str(e.value)
    assert "node 16 (sensor)" in text and f"{SCHEMA_HASH ^ 1:#010x}" in text and f"{SCHEMA_HASH:#010x}" in text
    with pytest.raises(SchemaMismatchError, match="protocol version 9"):
        check_peer(Hb(2, 1, 2, 9, SCHEMA_HASH, 0))
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
    """v1 traffic: MAG_SAMPLE's 19-byte PDU takes 3 frames (395 bits worst case), 4 nodes fit."""
    rep = bus_load(Traffic(sensors=8, compact=False, host_outputs=True), 500_000)
    mag = next(r for r in rep["rows"] if r["message"] == "MAG_SAMPLE")
    assert mag["frames_per_msg"] == 3
    assert mag["bits_per_s"] == pytest.approx(8 * 120 * 395)
    assert rep["total_bits_per_s"] == pytest.approx(sum(r["bits_per_s"] for r in rep["rows"]), rel=1e-9)
    assert not rep["fits"] and rep["max_sensor_nodes"] == 4
    assert bus_load(Traffic(sensors=8, compact=False, host_outputs=True), 500_000, fd=True)["fits"]


def test_bus_budget_sixteen_classic_thirty_two_fd():
    """Issue 11's budget, worst-case stuffing: 16 sensors on 500 kbit/s classic and 32 on CAN FD
    500 k / 2 M at most 70 %. MAG_PACKED is one 8-byte frame, 135 bits (Davis et al. 2007: 34 + 64
    + 13 + floor(97 / 4) = 135); the IMU is 2 x 10 frames per second; a codec that segmented the
    samples, or a model that counted POSE on the sensor bus, fails the bound."""
    rep = bus_load(Traffic(sensors=16), 500_000)
    mag = next(r for r in rep["rows"] if r["message"] == "MAG_PACKED")
    imu = next(r for r in rep["rows"] if r["message"] == "IMU_DELTA")
    assert mag["frame_bytes"] == [8] and mag["bits_per_msg"] == 135.0
    assert mag["bits_per_s"] == pytest.approx(16 * 120 * 135) and imu["bits_per_s"] == pytest.approx(16 * 20 * 135)
    assert "POSE" not in {r["message"] for r in rep["rows"]}
    assert rep["load_pct"] <= 70.0
    assert bus_load(Traffic(sensors=32), 500_000, fd=True, data_bitrate=2_000_000)["load_pct"] <= 70.0
    assert bus_load(Traffic(sensors=32), 500_000)["load_pct"] > 100.0     # 32 need FD


def test_busload_command(capsys):
    assert main(["busload", "--nodes", "8", "--bitrate", "500000", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["bitrate"] == 500_000 and rep["traffic"]["sensors"] == 8
    assert {r["message"] for r in rep["rows"]} >= {"MAG_PACKED", "IMU_DELTA", "HEARTBEAT", "COIL_PULSE_CMD",
                                                    "COIL_STATUS", "TIME_SYNC"}
    assert main(["busload", "--nodes", "2", "--imu-rate", "0"]) == 0
    out = capsys.readouterr().out
    assert "MAG_PACKED" in out and "IMU_DELTA" not in out and "fits" in out
    assert main(["busload", "--nodes", "32", "--fd", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["load_pct"] <= 70.0
    assert main(["busload", "--nodes", "2", "--v1", "--host-outputs"]) == 0
    out = capsys.readouterr().out
    assert "MAG_SAMPLE" in out and "POSE" in out
