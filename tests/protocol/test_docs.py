"""docs/protocol.md carries the current generated message table."""
from pathlib import Path

from coiltrack.protocol.docgen import BEGIN, END, extract_generated, markdown_table
from coiltrack.tools.cli import main

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"


def test_protocol_md_contains_current_table():
    text = DOC.read_text()
    assert extract_generated(text) == markdown_table(), (
        "docs/protocol.md is out of date: replace the generated block with `coiltrack schema --markdown`")


def test_schema_command_prints_the_table(capsys):
    assert main(["schema", "--markdown"]) == 0
    out = capsys.readouterr().out
    assert out == markdown_table() and out.startswith(BEGIN) and out.rstrip().endswith(END)
    assert main(["schema", "--json"]) == 0
    assert '"MAG_SAMPLE"' in capsys.readouterr().out
