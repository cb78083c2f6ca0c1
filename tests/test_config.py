"""Configuration: defaults are valid, bad values are refused naming the key."""
import pytest

from coiltrack.firmware.config import ConfigError, FirmwareConfig, config_from_dict, load_config


def test_default_is_valid_and_thesis_timing():
    cfg = FirmwareConfig().validate()
    assert (cfg.pulse_us, cfg.cycle_us) == (60_000, 600_000)
    assert len(cfg.coils) == 3 and cfg.coils[0].turns == 50 and cfg.coils[0].radius == 0.055


@pytest.mark.parametrize("d, key", [
    ({"pulse_us": -5}, "pulse_us"),
    ({"pulse_us": 1.5}, "pulse_us"),
    ({"cycle_us": 100_000}, "cycle_us"),
    ({"field_model": "magic"}, "field_model"),
    ({"mag_sigma_t": 0.0}, "mag_sigma_t"),
    ({"bogus_key": 1}, "bogus_key"),
    ({"coils": [{"radius": -1.0}]}, "coils[0].radius"),
    ({"coils": [{"turns": 0}]}, "coils[0].turns"),
    ({"coils": [{"axis": [0, 0, 0]}]}, "coils[0].axis"),
    ({"coils": [{"current": 5.0}]}, "coils[0].current"),
    ({"coils": [{"colour": "red"}]}, "coils[0].colour"),
    ({"ring_capacity": 10}, "ring_capacity"),
    ({"sensor_ids": []}, "sensor_ids"),
])
def test_bad_values_name_the_key(d, key):
    with pytest.raises(ConfigError) as ei:
        config_from_dict(d)
    assert ei.value.key == key
    assert f"'{key}'" in str(ei.value)


def test_load_toml(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('pulse_us = 40000\nfield_model = "dipole"\n[[coils]]\naxis = [1.0, 0.0, 0.0]\n'
                 '[[coils]]\naxis = [0.0, 1.0, 0.0]\ncenter = [0.0, 0.01, 0.0]\n')
    cfg = load_config(p)
    assert cfg.pulse_us == 40000 and cfg.field_model == "dipole" and len(cfg.coils) == 2
    assert cfg.coils[1].center == (0.0, 0.01, 0.0)


def test_load_toml_syntax_error(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("pulse_us = = 3\n")
    with pytest.raises(ConfigError):
        load_config(p)


@pytest.mark.parametrize("d, key", [
    ({"fusion": 1}, "fusion"),
    ({"measurement_model": 4}, "measurement_model"),
    ({"fusion_gate_probability": 0.5}, "fusion_gate_probability"),
    ({"source_imu_id": 16}, "source_imu_id"),
    ({"fusion_replay_capacity": 10}, "fusion_replay_capacity"),
    ({"acc_motion_sigma": -1.0}, "acc_motion_sigma"),
    ({"dist_corr": 1.5}, "dist_corr"),
    ({"ori_update_every": 0}, "ori_update_every"),
    ({"gravity_mps2": [0.0, 0.0, 0.0]}, "gravity_mps2"),
    ({"xi_heading_sigma_floor": -0.1}, "xi_heading_sigma_floor"),
])
def test_bad_fusion_values_name_the_key(d, key):
    with pytest.raises(ConfigError) as ei:
        config_from_dict(d)
    assert ei.value.key == key


def test_load_toml_with_fusion_keys(tmp_path):
    p = tmp_path / "f.toml"
    p.write_text('imu_rate_hz = 120.0\nmeasurement_model = 1\nmotion_compensation = false\n'
                 'source_imu_id = 8\nori_update_every = 2\n')
    cfg = load_config(p)
    assert cfg.measurement_model == 1 and cfg.motion_compensation is False and cfg.source_imu_id == 8
