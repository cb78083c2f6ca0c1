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
    assert config_from_dict({"core": {"impl": "python"}}).core.impl == "python"
    assert config_to_dict(FirmwareConfig())["core"] == {"impl": "compiled"}


def test_compiled_falls_back_to_python_once_where_not_built(capsys):
    """Without the extension, ``compiled`` loads the Python core with one line on stderr, said
    once per process; ``python`` is said nothing; an unknown core is refused."""
    core._say_python_fallback.cache_clear()
    assert core.load("python", ext=None) is core.PYTHON
    assert capsys.readouterr().err == ""
    assert core.load("compiled", ext=None) is core.PYTHON
    assert core.load("compiled", ext=None).ext is None
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Python core" in err
    assert core.resolve("compiled", ext=None) == "python"
    with pytest.raises(ValueError, match="impl"):
        core.resolve("numba")
    with pytest.raises(ValueError, match="extension"):
        core.Core("compiled", None)


def _cores(obj) -> dict:
    """``{class name: {core names}}`` of every firmware object reachable from ``obj`` that binds
    kernels (has a ``core`` name)."""
    seen: set[int] = set()
    found: dict[str, set] = {}

    def walk(o, depth: int) -> None:
        if depth > 14 or id(o) in seen:
            return
        seen.add(id(o))
        if isinstance(o, dict):
            for v in o.values():
                walk(v, depth + 1)
        elif isinstance(o, (list, tuple)):
            for v in o:
                walk(v, depth + 1)
        elif (getattr(type(o), "__module__", "") or "").startswith("coiltrack.firmware"):
            c = getattr(o, "core", None)
            if isinstance(c, str):
                found.setdefault(type(o).__name__, set()).add(c)
            for v in getattr(o, "__dict__", {}).values():
                walk(v, depth + 1)

    walk(obj, 0)
    return found


# one scenario of each pipeline: burst fusion (LM), tight fusion, adaptive single coil, the
# fixed single-coil cycle, Raab's tracker, AC fused, AC magnetic only
PIPELINES = ("roetenberg-fusion", "roetenberg-flexion-back", "schepers-adaptive", "schepers-fixed-910",
             "raab-acquire", "raab-ac", "ac-vs-dc-metal")


@pytest.mark.parametrize("scenario", PIPELINES)
@pytest.mark.parametrize("impl", ["python", "compiled"])
def test_firmware_passes_its_core_to_every_component(impl, scenario):
    """A Firmware composed with ``impl`` runs that core in every component that binds kernels
    (signal models, Kalman updates, covariance predictions, strapdowns, solvers, receive,
    transmit), whatever the pipeline; a second Firmware on the other core changes nothing of the
    first's (no state is shared between them)."""
    if impl == "compiled":
        pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools import scenarios
    from coiltrack.tools.bench.links import inproc_pair

    cfg = scenarios.get(scenario).firmware_config()
    fw = Firmware(cfg.with_(core={"impl": impl}), inproc_pair()[0])
    found = _cores(fw)
    for cls in ("SignalModel", "Transmitter", "Receiver"):
        assert cls in found, (cls, sorted(found))
    assert {name: c for name, c in found.items() if c != {impl}} == {}
    assert fw.status()["core"] == impl
    other = "python" if impl == "compiled" else "compiled"
    if other == "compiled" and not core.available():
        return
    Firmware(cfg.with_(core={"impl": other}), inproc_pair()[0])
    assert _cores(fw) == found


def test_bench_reports_are_the_same_with_either_core():
    """roetenberg-fusion, seed 1, 2 s, on each core: every report key that is not measured on the
    wall clock is equal (the compiled kernels are bit-identical to the reference, so the whole
    closed loop is), and each report says its core."""
    pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
    from coiltrack.tools import scenarios
    from coiltrack.tools.outputs.report import is_wall_clock
    from coiltrack.tools.bench.runner import run_inproc

    sc = scenarios.get("roetenberg-fusion")
    reps = {impl: run_inproc(sc, 1, 2.0, cfg=sc.firmware_config().with_(core={"impl": impl}))
            for impl in ("python", "compiled")}
    assert reps["python"]["core"] == "python" and reps["compiled"]["core"] == "compiled"
    assert reps["compiled"]["poses"] > 0
    keys = {k for k in reps["python"] if not is_wall_clock(k) and k != "core"}
    assert keys == {k for k in reps["compiled"] if not is_wall_clock(k) and k != "core"}
    for k in sorted(keys):
        assert reps["compiled"][k] == reps["python"][k], k
