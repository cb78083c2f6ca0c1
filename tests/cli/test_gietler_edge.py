"""``python -m coiltrack.tools.analyses.gietler_edge``: bad arguments refused before any run, and the
seed-98 crossing of Table I reported with the truth's and the estimate's range."""
from __future__ import annotations

import pytest

from coiltrack.tools.analyses.gietler_edge import main


@pytest.mark.parametrize("argv, word", [
    (["--noise-var", "-1e-4"], "--noise-var"),
    (["--noise-var", "nan"], "--noise-var"),
    (["--streams", "-1"], "--streams"),
    (["--seed", "x"], "--seed"),
    (["--scenario", "gietler-helix"], "--scenario"),
])
def test_bad_arguments_refused_with_status_2(argv, word, capsys):
    """A negative or non-finite noise variance, a negative stream count, a non-integer seed and a
    scenario without the eq-8 motion are refused with exit status 2 and a message naming the
    argument. Catches a value check dropped (a NaN variance would run and print NaNs)."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert word in capsys.readouterr().err


def test_seed_98_crossing_reported(capsys):
    """Seed 98 at sigma^2 = 1e-4 without the streams: the estimate crosses 2 m at step 193 with the
    truth at 1.9856 m (the truth's range from the bench's trajectory, ``hil.gietler``), and a budget
    of 30 iterates gives the same crossing. Catches the crossing's ranges taken from the wrong step
    (the truth's range one step late is 1.9986 m) or the scored steps counted up to the truth's exit
    (step 195) instead of the step before it."""
    assert main(["--seed", "98", "--noise-var", "1e-4", "--streams", "0", "--check-iterations", "30"]) == 0
    out = capsys.readouterr().out
    assert "crosses 2 m at step 193: |z| 1.9856 m" in out
    assert "(the same crossing)" in out
    assert "scored steps 1..194" in out
