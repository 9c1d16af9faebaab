"""docs/reference/run-file.md is the schema as it is: regenerated, it is unchanged."""

from pathlib import Path

from reachwatch.pipeline.reference import main, reference_markdown

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "reference" / "run-file.md"


def test_reference_matches_the_schema():
    assert PAGE.read_text() == reference_markdown(), (
        "docs/reference/run-file.md is out of date with the run-file dataclasses; "
        "regenerate it: python -m reachwatch.pipeline.reference docs/reference/run-file.md")


def test_reference_names_every_section_and_key(tmp_path):
    assert main([str(tmp_path / "ref.md")]) == 0
    text = (tmp_path / "ref.md").read_text()
    for section in ("## RunSpec", "## Scenario", "## MonitorConfig", "## LabelSpec",
                    "## GuardSpec", "## Environment"):
        assert section in text
    assert "| `flag_budget` | float \\| null | null |" in text
    assert "`run.train[]`" in text and "`run.scenario.environment`" in text
    assert main([]) == 2
