"""Static checks over every Python file of the repository: pyflakes' rules (undefined
names, unused imports and variables, redefinitions) through flake8, which honours
``# noqa`` on the imports kept on purpose. The benchmarks run in no other test, so this
is what catches a benchmark that still calls a function a refactor renamed; each one's
``--help`` catches one that imports a name that no longer exists (flake8 cannot)."""

import ast
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
SCRIPTS = sorted(p.name for p in BENCHMARKS.glob("*.py") if p.name != "guard_common.py")
CHECKED = ("systems", "diagrams", "reach", "taxi", "training", "pipeline", "benchmarks",
           "examples", "tests")


def flake8(*paths):
    return subprocess.run([sys.executable, "-m", "flake8", "--select=F", *map(str, paths)],
                          capture_output=True, text=True, cwd=ROOT)


def test_no_pyflakes_findings():
    done = flake8(*CHECKED)
    assert "No module named flake8" not in done.stderr, \
        "flake8 is missing: install the dev extras (pip install -e '.[dev]')"
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_check_sees_an_undefined_name(tmp_path):
    script = tmp_path / "renamed.py"
    script.write_text("from reachwatch.reach import Grid\n\n\ndef main():\n"
                      "    return Grid, solve_brt_renamed()\n")
    done = flake8(script)
    assert done.returncode == 1 and "undefined name 'solve_brt_renamed'" in done.stdout, done.stdout


def test_every_benchmark_is_checked_here():
    assert len(SCRIPTS) >= 13 and "fidelity.py" in SCRIPTS and "online.py" in SCRIPTS


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_benchmark_imports_and_explains_its_options(script, monkeypatch, capsys):
    """Each benchmark run as a script with ``--help``: its imports resolve (a name a
    refactor removed fails here) and it prints its usage instead of starting work."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))          # guard_common, as the script sees it
    monkeypatch.setattr(sys, "argv", [script, "--help"])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(BENCHMARKS / script), run_name="__main__")
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "usage:" in out
    # the description is the docstring's whole first paragraph, not a line cut mid-sentence
    doc = ast.get_docstring(ast.parse((BENCHMARKS / script).read_text()))
    # (compared without whitespace: argparse rewraps it, also after hyphens)
    assert "".join(doc.split("\n\n")[0].split()) in "".join(out.split())
