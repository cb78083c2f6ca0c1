"""The AC frequency plan is checked at start-up; a bad plan is refused naming ``ac.ac_freqs_hz``.

Each case breaks one rule of ``firmware_py/actuate/ac_plan.py`` (worked out by hand below)
and must be refused by ``FirmwareConfig.validate`` with the key and the reason, before any
firmware state exists; the defaults of the AC scenarios pass."""
import dataclasses

import pytest

from coiltrack.firmware.config import ConfigError, FirmwareConfig, config_from_dict
from coiltrack.firmware.actuate.ac_plan import check_plan, fold
from coiltrack.tools.scenarios.ac import ac_config


def _ac(**kw):
    return (ac_config(fusion=False)).with_keys(**kw)


def test_scenario_plans_pass():
    """215 / 315 / 465 Hz at 1 kHz, 18 ms blocks: every rule holds (the scenarios run)."""
    ac_config().validate()
    ac_config(fusion=False).validate()


@pytest.mark.parametrize("freqs, why", [
    ((215.0, 315.0), "one frequency per coil"),                  # a coil without a frequency
    ((215.0, 430.0, 330.0), "harmonic 2 (430 Hz"),                # 430 = 2 x 215
    ((300.0, 400.0, 230.0), "seen at 400 Hz"),                    # 2 x 300 = 600 Hz aliases to 400 at 1 kHz
    ((215.0, 315.0, 490.0), "Nyquist"),                           # 10 Hz below 500 Hz
    ((215.0, 255.0, 465.0), "closer than"),                       # 40 Hz < 1 / 18 ms = 55.6 Hz
    ((40.0, 315.0, 465.0), "less than one cycle"),                # 0.72 cycles in 18 ms
])
def test_bad_plans_are_refused_naming_the_key(freqs, why):
    """Catches a rule left out of the check (mains, harmonics, aliasing, Nyquist, resolution, DC)."""
    with pytest.raises(ConfigError) as e:
        _ac(ac_freqs_hz=freqs).validate()
    assert e.value.key == "ac.ac_freqs_hz"
    assert why in str(e.value)


@pytest.mark.parametrize("f, why", [(150.0, "mains 50 Hz harmonic 3"), (185.0, "mains 60 Hz harmonic 3"),
                                     (105.0, "mains 50 Hz harmonic 2"), (75.0, "mains 60 Hz harmonic 1")])
def test_mains_and_its_harmonics_are_kept_apart(f, why):
    """One coil 5-15 Hz from 150 = 3 x 50, 180 = 3 x 60, 100 = 2 x 50 or 60 Hz: catches the mains
    or its harmonics left out (with one coil no other rule applies)."""
    bad = check_plan((f,), 1, 1000.0, 18_000, 20.0, 3, (50.0, 60.0), 3)
    assert bad is not None and bad[0] == "ac_freqs_hz" and why in bad[1], bad
    assert check_plan((f,), 1, 1000.0, 18_000, 20.0, 3, (), 3) is None


def test_fold_is_the_sampled_alias():
    """600 Hz at 1 kHz shows at 400 Hz, 1100 Hz at 100 Hz, 250 Hz stays: catches a fold that
    does not mirror about Nyquist."""
    assert fold(600.0, 1000.0) == 400.0
    assert fold(1100.0, 1000.0) == pytest.approx(100.0)
    assert fold(250.0, 1000.0) == 250.0


def test_pulsed_configuration_is_not_plan_checked():
    """The thesis defaults (120 Hz magnetometer, pulsed DC) validate although the AC plan would not
    fit their rate: the plan is checked only with ``excitation = "ac"``."""
    FirmwareConfig().validate()
    assert check_plan((215.0, 315.0, 465.0), 3, 120.0, 18_000, 20.0, 3, (50.0, 60.0), 3) is not None


def test_toml_section_ac_and_other_bad_values():
    """The keys live in ``[ac]``; a bad excitation, a window that is not a multiple of the hop and
    AC with adaptive actuation are refused naming their keys."""
    base = {"pulse": {"mag_rate_hz": 1000.0}, "ac": {"excitation": "ac"}}
    config_from_dict(base).validate()
    with pytest.raises(ConfigError) as e:
        config_from_dict({"ac": {"excitation": "sine"}}).validate()
    assert e.value.key == "ac.excitation"
    with pytest.raises(ConfigError) as e:
        config_from_dict({**base, "ac": {"excitation": "ac", "ac_window_us": 20_000, "ac_hop_us": 9_000}}).validate()
    assert e.value.key == "ac.ac_window_us"
    with pytest.raises(ConfigError) as e:
        config_from_dict({**base, "adaptive": {"actuation": "adaptive"}}).validate()
    assert e.value.key == "adaptive.actuation"
