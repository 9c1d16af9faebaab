"""docs/reference/run-file.md is the schema as it is: regenerated, it is unchanged."""

import re
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
    # a class below one met again is found at every path too
    assert ("Where: `run.train_random.runway`, `run.test_random.runway`, "
            "`run.monitor.family.runway`." in text)
    assert "`run.test[].runway_spec.surface`" in text.split("## SurfaceSpec")[1].split("\n")[2]
    assert main([]) == 2


def test_a_keys_section_becomes_the_meaning_column(tmp_path):
    assert main([str(tmp_path / "ref.md")]) == 0
    text = (tmp_path / "ref.md").read_text()
    section = text.split("## MonitorStudySpec")[1].split("\n## ")[0]
    assert "| key | type | default | bounds | meaning |" in section
    assert "| `train` | int | 12 | [1, 1000] | environments the monitors train on. |" in section
    assert "Keys:" not in section
    assert "| key | type | default | bounds |\n" in text.split("## GuardSpec")[1]   # no section


def test_a_keys_section_describes_every_key_once():
    import dataclasses as dc

    import pytest

    from reachwatch.pipeline.reference import class_doc

    @dc.dataclass
    class Spec:
        """What it is.

        Keys:

        ``a``: the first,
        on two lines.

        ``b``: the second."""
        a: int = 1
        b: int = 2

    assert class_doc(Spec) == ("What it is.", {"a": "the first, on two lines.",
                                               "b": "the second."})
    for keys, said in [("``a``: one.\n\n``c``: none.", "not keys: ['c']"),
                       ("``a``: one.\n\n``a``: again.", "twice: ['a']"),
                       ("``a``: one.", "left out: ['b']")]:
        Spec.__doc__ = f"What it is.\n\nKeys:\n\n{keys}"
        with pytest.raises(ValueError, match=re.escape(said)):
            class_doc(Spec)
