"""The README's tour runs as written (at a tiny grid size)."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def tour_blocks():
    return re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)


def test_readme_tour_runs(tmp_path, monkeypatch):
    blocks = tour_blocks()
    assert len(blocks) >= 3
    monkeypatch.chdir(tmp_path)                      # out/ and cache/ land here
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    namespace = {"__name__": "readme_tour"}
    for block in blocks:
        code = block.replace("(41, 41, 41)", "(3, 3, 3)")
        exec(compile(code, "README.md", "exec"), namespace)
    assert (tmp_path / "out" / "world.dot").is_file()
    assert namespace["value"].values.shape == (3, 3, 3)
    assert namespace["controller"].HasInputPort("color_image")
