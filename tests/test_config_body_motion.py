"""The ``[body_motion]`` keys: refused values name ``body_motion.key``, and a
TOML table of that name sets them."""
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
    """Catches the section missing from ``SECTIONS`` (the table would be refused or ignored)."""
    p = tmp_path / "fw.toml"
    p.write_text("[body_motion]\nbaseline_gyro = true\nacc_adapt_gain = 1.0\nacc_adapt_tau_s = 2.0\n")
    cfg = load_config(p)
    assert cfg.body.baseline_gyro is True and cfg.body.acc_adapt_gain == 1.0 and cfg.body.acc_adapt_tau_s == 2.0
    assert cfg.body.compass_heading_only is False
