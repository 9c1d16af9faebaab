"""The README's tour runs as pasted: every ```python block, in order, in one namespace,
from an empty working directory. A block whose first line is ``# NAME.py`` is a file the
reader saves (step 1 of "your own controller"): it is written there, not executed."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def python_blocks(path):
    return re.findall(r"```python\n(.*?)```", Path(path).read_text(), re.S)


def run_blocks(blocks, workdir, source):
    """Exec ``blocks`` in order from ``workdir``; file blocks are saved there instead."""
    namespace = {"__name__": "readme_tour"}
    for block in blocks:
        first = block.splitlines()[0].strip()
        name = re.fullmatch(r"#\s*([\w./-]+\.py)", first)
        if name:
            (workdir / name.group(1)).write_text(block)
            continue
        exec(compile(block, source, "exec"), namespace)
    return namespace


def test_readme_tour_runs(tmp_path, monkeypatch):
    blocks = python_blocks(ROOT / "README.md")
    assert len(blocks) >= 5
    assert not any("41, 41, 41" in b or "101, 101, 101" in b for b in blocks), \
        "the tour must run as pasted: keep its grids small"
    monkeypatch.chdir(tmp_path)                      # out/, cache/ and my_controller.py land here
    namespace = run_blocks(blocks, tmp_path, "README.md")
    assert (tmp_path / "out" / "world.dot").is_file()
    assert (tmp_path / "my_controller.py").is_file()
    assert namespace["value"].values.shape == (5, 5, 5)
    assert namespace["controller"].HasInputPort("color_image")
    assert namespace["run"].state.shape[1] == 3
