"""Configuration: defaults are valid, bad values are refused naming the key."""
import pytest

from coiltrack.firmware.config import ConfigError, FirmwareConfig, config_from_dict, load_config


def test_default_is_valid_and_thesis_timing():
    cfg = FirmwareConfig().validate()
    assert (cfg.timing.pulse_us, cfg.timing.cycle_us) == (60_000, 600_000)
    assert len(cfg.source.coils) == 3 and cfg.source.coils[0].turns == 50 and cfg.source.coils[0].radius == 0.055


@pytest.mark.parametrize("d, key", [
    ({"timing": {"pulse_us": -5}}, "timing.pulse_us"),
    ({"timing": {"pulse_us": 1.5}}, "timing.pulse_us"),
    ({"timing": {"cycle_us": 100_000}}, "timing.cycle_us"),
    ({"source": {"field_model": "magic"}}, "source.field_model"),
    ({"pulse": {"mag_sigma_t": 0.0}}, "pulse.mag_sigma_t"),
    ({"timing": {"bogus_key": 1}}, "timing.bogus_key"),
    ({"timing": {"align_us": -1}}, "timing.align_us"),
    ({"timing": {"align_us": 600_000}}, "timing.align_us"),          # not below cycle_us
    ({"timing": {"align_slew_us": 0}}, "timing.align_slew_us"),
    ({"timing": {"align_slew_us": 251}}, "timing.align_slew_us"),     # over a quarter of the 1 ms tick
    ({"source": {"coils": [{"radius": -1.0}]}}, "source.coils[0].radius"),
    ({"source": {"coils": [{"turns": 0}]}}, "source.coils[0].turns"),
    ({"source": {"coils": [{"axis": [0, 0, 0]}]}}, "source.coils[0].axis"),
    ({"source": {"coils": [{"current": 5.0}]}}, "source.coils[0].current"),
    ({"source": {"coils": [{"colour": "red"}]}}, "source.coils[0].colour"),
    ({"pulse": {"ring_capacity": 10}}, "pulse.ring_capacity"),
    ({"link": {"sensor_ids": []}}, "link.sensor_ids"),
])
def test_bad_values_name_the_key(d, key):
    with pytest.raises(ConfigError) as ei:
        config_from_dict(d)
    assert ei.value.key == key
    assert f"'{key}'" in str(ei.value)


def test_load_toml(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('[timing]\npulse_us = 40000\n[source]\nfield_model = "dipole"\n'
                 '[[source.coils]]\naxis = [1.0, 0.0, 0.0]\n'
                 '[[source.coils]]\naxis = [0.0, 1.0, 0.0]\ncenter = [0.0, 0.01, 0.0]\n')
    cfg = load_config(p)
    assert cfg.timing.pulse_us == 40000 and cfg.source.field_model == "dipole" and len(cfg.source.coils) == 2
    assert cfg.source.coils[1].center == (0.0, 0.01, 0.0)


def test_load_toml_syntax_error(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("pulse_us = = 3\n")
    with pytest.raises(ConfigError):
        load_config(p)


@pytest.mark.parametrize("d, key", [
    ({"fusion": {"fusion": 1}}, "fusion.fusion"),
    ({"fusion": {"measurement_model": 4}}, "fusion.measurement_model"),
    ({"fusion": {"fusion_gate_probability": 0.5}}, "fusion.fusion_gate_probability"),
    ({"link": {"source_imu_id": 16}}, "link.source_imu_id"),
    ({"fusion": {"fusion_replay_capacity": 10}}, "fusion.fusion_replay_capacity"),
    ({"orientation": {"acc_motion_sigma": -1.0}}, "orientation.acc_motion_sigma"),
    ({"orientation": {"dist_corr": 1.5}}, "orientation.dist_corr"),
    ({"orientation": {"ori_update_every": 0}}, "orientation.ori_update_every"),
    ({"imu": {"gravity_mps2": [0.0, 0.0, 0.0]}}, "imu.gravity_mps2"),
    ({"fusion": {"xi_heading_sigma_floor": -0.1}}, "fusion.xi_heading_sigma_floor"),
])
def test_bad_fusion_values_name_the_key(d, key):
    with pytest.raises(ConfigError) as ei:
        config_from_dict(d)
    assert ei.value.key == key


def test_load_toml_with_fusion_keys(tmp_path):
    p = tmp_path / "f.toml"
    p.write_text('[imu]\nimu_rate_hz = 120.0\n[fusion]\nmeasurement_model = 1\nmotion_compensation = false\n'
                 '[link]\nsource_imu_id = 8\n[orientation]\nori_update_every = 2\n')
    cfg = load_config(p)
    assert cfg.fusion.measurement_model == 1 and cfg.fusion.motion_compensation is False and cfg.link.source_imu_id == 8


@pytest.mark.parametrize("d, key, words", [
    ({"pulse_us": 40000}, "timing.pulse_us", "belongs in section [timing]"),
    ({"fusion": {"pulse_us": 40000}}, "fusion.pulse_us", "belongs in section [timing]"),
    ({"timingg": {}}, "timingg", "unknown section"),
    ({"link": {"node_id": 300}}, "link.node_id", "1..255"),
    ({"budget": {"track_budget_evals": 0}}, "budget.track_budget_evals", "positive"),
])
def test_keys_live_in_their_section(d, key, words):
    """A key outside its section, or an unknown section, is refused naming where it belongs."""
    with pytest.raises(ConfigError) as ei:
        config_from_dict(d)
    assert ei.value.key == key and words in str(ei.value)


def test_round_trip_through_sections():
    """config_to_dict then config_from_dict gives back the same configuration, and every
    key of FirmwareConfig appears in exactly one section."""
    from dataclasses import fields

    from coiltrack.firmware.config import SECTION_TYPES, SECTIONS, config_to_dict

    cfg = FirmwareConfig().with_(timing={"pulse_us": 40_000}, fusion={"fusion": False}, link={"node_id": 3})
    assert config_from_dict(config_to_dict(cfg)) == cfg
    keys = [k for ks in SECTIONS.values() for k in ks]
    assert sorted(keys) == sorted(f.name for cls in SECTION_TYPES.values() for f in fields(cls))
    assert len(keys) == len(set(keys))
    assert [f.name for f in fields(FirmwareConfig)] == list(SECTIONS)


def test_config_error_survives_pickling():
    """A sweep's worker process sends a refused value back to the parent."""
    import pickle

    with pytest.raises(ConfigError) as ei:
        config_from_dict({"timing": {"pulse_us": -5}})
    back = pickle.loads(pickle.dumps(ei.value))
    assert back.key == "timing.pulse_us" and str(back) == str(ei.value)


@pytest.mark.parametrize("d, key", [
    ({"recovery": {"dead_reckon_after_us": 0}}, "recovery.dead_reckon_after_us"),
    ({"recovery": {"dead_reckon_limit_us": 500_000}}, "recovery.dead_reckon_limit_us"),    # below the 1 s default
    ({"recovery": {"recovery_keep_biases": 1}}, "recovery.recovery_keep_biases"),
    ({"recovery": {"recovery_bias_gate_sigmas": -4.0}}, "recovery.recovery_bias_gate_sigmas"),
    ({"fusion": {"dead_reckon_limit_us": 3_000_000}}, "fusion.dead_reckon_limit_us"),      # not its section
])
def test_bad_recovery_values_name_the_key(d, key):
    """Each bad value of the recovery section is refused naming section.key: catches a
    limit shorter than the dead-reckoning onset (poses invalid before they are flagged)."""
    with pytest.raises(ConfigError) as ei:
        config_from_dict(d)
    assert ei.value.key == key
