"""The configuration in sections (``coiltrack.firmware.config``): one dataclass per section,
read as ``cfg.section.key``; a file of the old layout keeps loading where its sections were
kept, and a key of a merged section or one that left the firmware's configuration is refused
naming its new place; every key's bad value is refused naming ``section.key``;
``examples/firmware.toml`` is the generated one."""
from dataclasses import fields
from pathlib import Path

import pytest

from coiltrack.firmware.config import (SECTION_TYPES, SECTIONS, ConfigError, FirmwareConfig, config_from_dict,
                                       config_to_dict, load_config)
from coiltrack.tools.docsgen.reference import example_toml

ROOT = Path(__file__).resolve().parents[1]

#: examples/firmware.toml as it was in the flat-in-section layout (every table a section kept)
OLD_LAYOUT = """
[link]
node_id = 1
coil_driver_id = 2
sensor_ids = [16]
stale_us = 2000000

[timing]
tick_us = 1000
pulse_us = 50000
cycle_us = 600000
spacing_us = 100000
lead_us = 40000

[pulse]
settle_us = 3000
fall_us = 3000
guard_us = 2000
baseline_us = 35000
mag_rate_hz = 120.0
mag_sigma_t = 1e-7

[limits]
max_current_a = 2.0

[budget]
track_budget_evals = 9
replay_budget_steps = 8
window_evals = 0
imu_sample_evals = 0

[source]
field_model = "dipole"

[[source.coils]]
axis = [1.0, 0.0, 0.0]
radius = 0.055
turns = 50
current = 1.5

[[source.coils]]
axis = [0.0, 1.0, 0.0]
radius = 0.055
turns = 50
current = 1.5
"""


def test_old_layout_file_loads_into_the_sections(tmp_path):
    """A file written for the flat configuration loads when its sections are kept: each value
    lands in its section (a key dropped on the way would keep its default)."""
    p = tmp_path / "old.toml"
    p.write_text(OLD_LAYOUT)
    cfg = load_config(p)
    assert cfg.timing.pulse_us == 50_000 and cfg.timing.lead_us == 40_000
    assert cfg.pulse.mag_sigma_t == 1e-7 and cfg.source.field_model == "dipole"
    assert len(cfg.source.coils) == 2 and cfg.source.coils[1].axis == (0.0, 1.0, 0.0)
    assert cfg.link.sensor_ids == (16,)
    assert cfg.orientation == FirmwareConfig().orientation    # sections the file does not name: defaults


@pytest.mark.parametrize("table, where", [
    ({"adaptive_policy": {"nis_feedback": False}}, "[adaptive]"),       # config-codemod: keep
    ({"body_motion": {"baseline_gyro": True}}, "[body]"),               # config-codemod: keep
    ({"lm": {"lm_cost_tol": 1e-3}}, "[pose]"),                          # config-codemod: keep
    ({"raab_cost": {"raab_step_sigma": 0.1}}, "[pose]"),                # config-codemod: keep
    ({"imu_delta": {"imu_delta_rate_hz": 20.0}}, "[imu]"),              # config-codemod: keep
    ({"imu_delta": {"imu_steps_per_tick": 3}}, "[budget]"),             # config-codemod: keep
])
def test_merged_section_is_refused_naming_the_new_one(table, where):
    """A table of a merged section: the error names the key's section now (not 'unknown')."""
    with pytest.raises(ConfigError) as e:
        config_from_dict(table)
    (sec, t), = table.items()
    (key, _), = t.items()
    assert e.value.key == f"{sec}.{key}" and where in str(e.value)


def test_gietler_key_left_the_firmware_configuration():
    """The Gietler filters' keys are the experiment's: a firmware file naming them is refused
    with where they went, a flat read says the same, and the sweep still takes them."""
    with pytest.raises(ConfigError) as e:
        config_from_dict({"gietler": {"gietler_iterations": 5}})
    assert "unknown section" in str(e.value)
    with pytest.raises(ConfigError) as e:
        config_from_dict({"pose": {"gietler_iterations": 5}})
    assert "GietlerFilterConfig" in str(e.value)
    with pytest.raises(AttributeError, match="GietlerFilterConfig"):
        FirmwareConfig().gietler_iterations
    from coiltrack.tools.scenarios.gietler import _split
    spec, filt = _split("gietler-air", (("gietler.gietler_iterations", 5), ("noise.var", 1e-3)))
    assert filt.gietler_iterations == 5 and filt.gietler_noise_var == spec.noise_var == 1e-3
    with pytest.raises(ConfigError, match="timing.pulse_us"):
        _split("gietler-air", (("timing.pulse_us", 5),))


def test_flat_read_names_the_section():
    """A use site the rewrite missed fails loudly, naming where the key is."""
    with pytest.raises(AttributeError, match=r"cfg\.timing\.pulse_us"):
        FirmwareConfig().pulse_us                          # config-codemod: keep
    assert not hasattr(FirmwareConfig(), "mag_sigma_t")


def test_with_changes_only_the_named_keys():
    base = FirmwareConfig()
    cfg = base.with_(timing={"pulse_us": 40_000}, pulse={"settle_us": 5_000})
    assert cfg.timing.pulse_us == 40_000 and cfg.pulse.settle_us == 5_000
    assert cfg.timing.cycle_us == base.timing.cycle_us and cfg.pulse.guard_us == base.pulse.guard_us
    assert cfg.orientation is base.orientation             # untouched sections are shared, not copied
    assert base.timing.pulse_us == 60_000                  # the base is unchanged (frozen)
    assert cfg == base.with_keys(pulse_us=40_000, settle_us=5_000)
    with pytest.raises(TypeError, match=r"pulse\.mag_sigma_t"):
        base.with_(timing={"mag_sigma_t": 1e-7})           # a key given to the wrong section
    with pytest.raises(TypeError, match="no section"):
        base.with_(timings={"pulse_us": 1})
    with pytest.raises(TypeError, match="GietlerFilterConfig"):
        base.with_keys(gietler_p0=1.0)


def _bad_value(default):
    """A value of the wrong TOML type for a key whose default is ``default``."""
    if isinstance(default, bool):
        return "yes"
    if isinstance(default, (int, float, tuple)):
        return "x"
    return 1


@pytest.mark.parametrize("sec", list(SECTIONS))
def test_every_key_refuses_a_bad_value_naming_section_key(sec):
    """Each key of each section: a value of the wrong type is refused as ``section.key`` (a key
    filed in the wrong dataclass or missing from SECTIONS would be named otherwise)."""
    default = getattr(FirmwareConfig(), sec)
    for key in SECTIONS[sec]:
        with pytest.raises(ConfigError) as e:
            config_from_dict({sec: {key: _bad_value(getattr(default, key))}})
        assert e.value.key == f"{sec}.{key}"


@pytest.mark.parametrize("table, key", [
    ({"pulse": {"settle_us": 59_000}}, "timing.pulse_us"),               # timing against pulse
    ({"limits": {"max_current_a": 1.0}}, "source.coils[0].current"),     # source against limits
    ({"imu": {"imu_rate_hz": 1000.0}}, "fusion.fusion_replay_capacity"),  # fusion against imu, timing
    ({"ac": {"excitation": "ac"}, "adaptive": {"actuation": "adaptive"}}, "adaptive.actuation"),
    ({"tight": {"tight_fusion": True}, "adaptive": {"single_coil_fusion": True}}, "tight.tight_fusion"),
    ({"adaptive": {"actuation": "adaptive"}, "pulse": {"mag_rate_hz": 20.0}}, "timing.pulse_us"),
])
def test_checks_across_sections_name_the_key(table, key):
    """The checks that join sections still run, each naming the key it refuses."""
    with pytest.raises(ConfigError) as e:
        config_from_dict(table)
    assert e.value.key == key


def test_defaults_are_those_of_the_section_dataclasses():
    """One set of defaults: FirmwareConfig's sections are the dataclasses' own defaults, and the
    TOML form round-trips."""
    cfg = FirmwareConfig()
    for sec, cls in SECTION_TYPES.items():
        assert getattr(cfg, sec) == cls()
        assert [f.name for f in fields(cls)] == list(SECTIONS[sec])
    assert config_from_dict(config_to_dict(cfg)) == cfg.validate()


def test_example_file_is_the_generated_one():
    """examples/firmware.toml is what `python -m coiltrack.tools.docsgen --example
    examples/firmware.toml` writes, names every key, and loads as the defaults."""
    path = ROOT / "examples" / "firmware.toml"
    assert path.read_text() == example_toml(), \
        "run: python -m coiltrack.tools.docsgen --example examples/firmware.toml"
    assert load_config(path) == FirmwareConfig()
    text = path.read_text()
    for sec, keys in SECTIONS.items():
        assert f"\n[{sec}]\n" in text
        for k in keys:
            assert f"\n{k} = " in text or k == "coils", f"{sec}.{k}"
