"""``tools.analyses.adaptive_consistency``: its arguments (no bench run here: runs are commands)."""
import pytest

from coiltrack.tools.analyses import adaptive_consistency as tool


def test_set_values_are_parsed_as_json_or_kept_as_text():
    assert tool._keys(["reference_hold=mean", "unreached_share=0.8", "nis_feedback=false"]) == {
        "reference_hold": "mean", "unreached_share": 0.8, "nis_feedback": False}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        tool._keys(["reference_hold"])


@pytest.mark.parametrize("argv", [["--duration", "0"], ["--duration", "1", "--bin", "2"], ["--set", "novalue"],
                                  ["--set", "no_such_key=1", "--duration", "1", "--bin", "1"]])
def test_bad_arguments_exit_2_with_a_message(argv, capsys):
    assert tool.main(argv) == 2
    assert "adaptive_consistency:" in capsys.readouterr().err
