"""Static checks over every Python file of the repository: pyflakes' rules (undefined
names, unused imports and variables, redefinitions) through flake8, which honours
``# noqa`` on the imports kept on purpose. The benchmarks run in no other test, so this
is what catches a benchmark that still calls a function a refactor renamed."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
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
