"""``tools.analyses.adaptive_consistency``: its arguments (no bench run here: runs are commands)."""
import pytest

from coiltrack.tools.analyses import adaptive_consistency as tool


def test_set_values_are_parsed_as_json_or_kept_as_text():
    assert tool.set_keys(["reference_hold=mean", "unreached_share=0.8", "nis_feedback=false"]) == {
        "reference_hold": "mean", "unreached_share": 0.8, "nis_feedback": False}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        tool.set_keys(["reference_hold"])


@pytest.mark.parametrize("argv", [["--duration", "0"], ["--duration", "1", "--bin", "2"], ["--set", "novalue"],
                                  ["--set", "no_such_key=1", "--duration", "1", "--bin", "1"]])
def test_bad_arguments_exit_2_with_a_message(argv, capsys):
    assert tool.main(argv) == 2
    assert "adaptive_consistency:" in capsys.readouterr().err


def test_amplitude_errors_measure_the_correlation_of_pulses_sharing_a_baseline():
    """``amplitude_errors`` on made-up updates around a still sensor: amplitudes the model's own field
    plus errors ``e_k = u_k + s_k + s_{k-1}`` (``s`` shared with the neighbour, equal variances: the
    correlation of consecutive errors is 1/3) for pulses 100 ms apart (sharing a baseline), and
    independent errors for pulses 1 s apart (correlation 0); mean square 1 with the variance given."""
    from types import SimpleNamespace

    import numpy as np

    from coiltrack.firmware.actuate.coil_choice import SingleCoilModel
    from coiltrack.firmware.model.field import Coil
    from coiltrack.tools.scenarios import get

    cfg = get("schepers-adaptive").firmware_config()
    p, R = np.array([0.25, 0.1, 0.05]), np.eye(3)
    model = SingleCoilModel([Coil(c.center, c.axis, c.radius, c.turns) for c in cfg.source.coils])
    model.evaluate(p, R)
    rng = np.random.default_rng(7)
    n = 3000
    s = rng.normal(size=(n + 1, 3))
    u = rng.normal(size=(n, 3))
    e_shared = (u + s[1:] + s[:-1]) / np.sqrt(3.0)
    e_apart = rng.normal(size=(n, 3))
    var = np.full(3, 4e-16)
    ups = []
    for k in range(n):
        ups.append((5_000_000 + 100_000 * k, k % 3, 0.5, 0.5 * np.asarray(model.h[k % 3]) + 2e-8 * e_shared[k], var, 0))
    t0 = ups[-1][0] + 1_000_000
    for k in range(n):
        ups.append((t0 + 1_000_000 * k, k % 3, 0.5, 0.5 * np.asarray(model.h[k % 3]) + 2e-8 * e_apart[k], var, 0))

    class World:
        @staticmethod
        def sensor_kinematics(t):
            m = len(t)
            return SimpleNamespace(position=np.tile(p, (m, 1)), R=np.tile(R, (m, 1, 1)))
    out = tool.amplitude_errors(cfg, SimpleNamespace(world=World()), ups)
    assert out["pairs_shared"] == n - 1 and out["pairs_apart"] == n
    assert abs(out["corr_shared"] - 1 / 3) < 0.04
    assert abs(out["corr_apart"]) < 0.04
    assert abs(out["mean_square"] - 1.0) < 0.05
