"""``bench.noise_draw``: repeats of one trajectory with the bench's other draws taken anew
(``tools.bench.runner.BenchSetup``, a ``coiltrack sweep --set`` axis).

Draw 0 is the seed's own bench (every figure as without the key); a draw k > 0 keeps the world
(the trajectory) and takes the driver's, sensor's, faults' and clocks' seeds from
``SeedSequence([seed, k])``: the driver's static gain errors differ, the trajectory does not. A
draw that is no integer >= 0 is refused by name before any work."""
import numpy as np
import pytest

from coiltrack.firmware.config import ConfigError
from coiltrack.tools.bench import sweep
from coiltrack.tools.bench.runner import BenchSetup, sim_link_pair
from coiltrack.tools.cli import main
from coiltrack.tools.scenarios import get


def _setup(draw):
    return BenchSetup(get("schepers-adaptive"), 7, 2.0, sim_link_pair("inproc")[1], noise_draw=draw)


def test_a_draw_keeps_the_trajectory_and_redraws_the_nodes():
    base, zero, one, two = BenchSetup(get("schepers-adaptive"), 7, 2.0, sim_link_pair("inproc")[1]), \
        _setup(0), _setup(1), _setup(2)
    t = np.arange(0, 2_000_000, 50_000, dtype=np.int64)
    ref = base.world.sensor_kinematics(t)
    for b in (zero, one, two):
        k = b.world.sensor_kinematics(t)
        assert np.array_equal(k.position, ref.position) and np.array_equal(k.R, ref.R)
    assert zero.driver.gain_error == base.driver.gain_error
    gains = {tuple(b.driver.gain_error) for b in (base, one, two)}
    assert len(gains) == 3                                 # each draw its own driver


def test_the_key_splits_off_and_bad_draws_are_refused_by_name():
    assert sweep.split_noise_draw((("pulse_us", 4), (sweep.NOISE_DRAW_KEY, 3))) == (3, (("pulse_us", 4),))
    assert sweep.split_noise_draw((("pulse_us", 4),)) == (0, (("pulse_us", 4),))
    for bad in (-1, 1.5, "x", True):
        with pytest.raises(ConfigError, match="bench.noise_draw"):
            sweep.split_noise_draw(((sweep.NOISE_DRAW_KEY, bad),))


def test_sweep_refuses_a_bad_draw_before_any_work(monkeypatch, capsys):
    monkeypatch.setattr(sweep, "run_tasks", lambda *a, **k: pytest.fail("work started"))
    assert main(["sweep", "--scenario", "static", "--seeds", "1", "--set", "bench.noise_draw=-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("coiltrack sweep: ") and "bench.noise_draw" in err and "\n" not in err


def test_draw_zero_is_the_seed_and_another_draw_moves_the_figures():
    """static, 1.5 s: the key at 0 gives every figure of the run without it; at 1 other figures."""
    run = lambda ov: sweep.run_task(sweep.Task("static", 2, 1.5, ov))["figures"]  # noqa: E731
    plain, zero, one = run(()), run(((sweep.NOISE_DRAW_KEY, 0),)), run(((sweep.NOISE_DRAW_KEY, 1),))
    assert zero == plain
    assert one["position_rms_mm"] != plain["position_rms_mm"]
