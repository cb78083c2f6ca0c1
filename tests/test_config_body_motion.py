"""The body-worn motion keys (section ``[body]``, merged there from a section of their own):
refused values name ``body.key``, a ``[body]`` table sets them, and a table of the old layout
is refused naming their new place."""
import pytest

from coiltrack.firmware.config import ConfigError, config_from_dict, load_config


@pytest.mark.parametrize("d,key", [
    ({"body": {"baseline_gyro": 1}}, "body.baseline_gyro"),
    ({"body": {"acc_adapt_gain": -0.5}}, "body.acc_adapt_gain"),
    ({"body": {"acc_adapt_gain": float("nan")}}, "body.acc_adapt_gain"),
    ({"body": {"acc_adapt_tau_s": 0.0}}, "body.acc_adapt_tau_s"),
    ({"body": {"compass_heading_only": "yes"}}, "body.compass_heading_only"),
])
def test_bad_body_motion_values_name_the_key(d, key):
    """Catches a key left out of validation or filed in the wrong section."""
    with pytest.raises(ConfigError) as e:
        config_from_dict(d).validate()
    assert e.value.key == key


def test_load_toml_with_body_motion_keys(tmp_path):
    """Catches the keys missing from ``SECTIONS`` (the table would be refused or ignored)."""
    p = tmp_path / "fw.toml"
    p.write_text("[body]\nbaseline_gyro = true\nacc_adapt_gain = 1.0\nacc_adapt_tau_s = 2.0\n")
    cfg = load_config(p)
    assert cfg.body.baseline_gyro is True and cfg.body.acc_adapt_gain == 1.0 and cfg.body.acc_adapt_tau_s == 2.0
    assert cfg.body.compass_heading_only is False


def test_old_body_motion_table_names_the_new_place(tmp_path):
    """A file of the old layout is refused with the key's new section, not a bare 'unknown'."""
    p = tmp_path / "fw.toml"
    p.write_text("[body_motion]\nbaseline_gyro = true\n")  # config-codemod: keep
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert e.value.key == "body_motion.baseline_gyro" and "[body]" in str(e.value)  # config-codemod: keep
