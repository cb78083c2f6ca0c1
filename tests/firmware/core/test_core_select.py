"""Choosing the numeric core (coiltrack.firmware.core, ``[core] impl``, ``--core``): refused
values, the Python fallback said once, the choice made at composition and carried by every
report, and the two cores' bench reports the same."""
import dataclasses

import pytest

from coiltrack.firmware import core
from coiltrack.firmware.config import ConfigError, FirmwareConfig, config_from_dict, config_to_dict


def test_bad_impl_is_refused_naming_the_key():
    """``[core] impl = "fast"`` is refused with a ConfigError naming ``impl``; the key lives in
    section ``core`` (a key put in another section is refused)."""
    with pytest.raises(ConfigError, match="impl"):
        config_from_dict({"core": {"impl": "fast"}})
    with pytest.raises(ConfigError, match=r"belongs in section \[core\]"):
        config_from_dict({"timing": {"impl": "python"}})
    assert config_from_dict({"core": {"impl": "python"}}).impl == "python"
    assert config_to_dict(FirmwareConfig())["core"] == {"impl": "compiled"}


def test_compiled_falls_back_to_python_once_where_not_built(monkeypatch, capsys):
    """Without the extension, ``compiled`` resolves to ``python`` with one line on stderr, said
    once per process; ``python`` is said nothing."""
    monkeypatch.setattr(core, "_ext", None)
    monkeypatch.setitem(core._state, "said", False)
    monkeypatch.setitem(core._state, "selected", "python")
    assert core.resolve("python") == "python"
    assert capsys.readouterr().err == ""
    assert core.select("compiled") == "python"
    assert core.extension() is None
    assert core.resolve("compiled") == "python"
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Python core" in err
    with pytest.raises(ValueError, match="impl"):
        core.resolve("numba")


@pytest.mark.parametrize("impl", ["python", "compiled"])
def test_firmware_binds_the_chosen_core_at_composition(impl, monkeypatch):
    """A Firmware composed with ``impl`` runs that core in every signal model it built (and says
    so in its status); a later composition with the other core does not change the first's."""
    if impl == "compiled":
        pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
    from coiltrack.firmware.loop import Firmware
    from coiltrack.firmware.model.signal import SignalModel
    from coiltrack.tools.commands.perf import instances
    from coiltrack.tools.bench.links import inproc_pair

    monkeypatch.setitem(core._state, "selected", core._state["selected"])
    fw = Firmware(dataclasses.replace(FirmwareConfig(), impl=impl), inproc_pair()[0])
    models = instances(fw, SignalModel)
    assert models and {m.core for m in models} == {impl}
    assert fw.status()["core"] == impl
    other = "python" if impl == "compiled" else "compiled"
    if other == "compiled" and not core.available():
        return
    Firmware(dataclasses.replace(FirmwareConfig(), impl=other), inproc_pair()[0])
    assert {m.core for m in models} == {impl}


def test_bench_reports_are_the_same_with_either_core(monkeypatch):
    """roetenberg-fusion, seed 1, 2 s, on each core: every report key that is not measured on the
    wall clock is equal (the compiled kernels are bit-identical to the reference, so the whole
    closed loop is), and each report says its core."""
    pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
    from coiltrack.tools import scenarios
    from coiltrack.tools.outputs.report import is_wall_clock
    from coiltrack.tools.bench.runner import run_inproc

    monkeypatch.setitem(core._state, "selected", core._state["selected"])
    sc = scenarios.get("roetenberg-fusion")
    reps = {impl: run_inproc(sc, 1, 2.0, cfg=dataclasses.replace(sc.firmware_config(), impl=impl))
            for impl in ("python", "compiled")}
    assert reps["python"]["core"] == "python" and reps["compiled"]["core"] == "compiled"
    assert reps["compiled"]["poses"] > 0
    keys = {k for k in reps["python"] if not is_wall_clock(k) and k != "core"}
    assert keys == {k for k in reps["compiled"] if not is_wall_clock(k) and k != "core"}
    for k in sorted(keys):
        assert reps["compiled"][k] == reps["python"][k], k
