"""The command line answers at once: building its parser (``--help``, a refused
argument) imports neither drake nor torch, the constants the parser copies from the
library stay the library's, every option says what it does, and a command whose
inputs cannot work says so before its sweeps, not after them."""

import argparse
import json
import subprocess
import sys

import pytest

from reachwatch.pipeline import cli

#: Top-level packages the parser must not import (each takes seconds to load).
HEAVY = ("torch", "pydrake", "triton", "torchvision", "numpy", "scipy", "matplotlib", "cv2")

#: In a fresh interpreter: every command's ``--help`` through the real parser, then
#: the heavy modules (and reachwatch's packages outside the pipeline) it loaded.
PROBE = f"""
import contextlib, io, json, sys
from reachwatch.pipeline.cli import build_parser
commands = [[], ["render"], ["graph"], ["simulate"], ["sweep"], ["brt"], ["evaluate"],
            ["guard"], ["run"], ["taxinet"], ["taxinet", "train"], ["taxinet", "evaluate"]]
for argv in commands:
    with contextlib.redirect_stdout(io.StringIO()):
        try:
            build_parser().parse_args(argv + ["--help"])
        except SystemExit as e:
            assert e.code == 0, argv
loaded = [m for m in sys.modules if m.split(".")[0] in {HEAVY!r}
          or m.startswith("reachwatch.") and m.split(".")[1] != "pipeline"]
print(json.dumps(sorted(loaded)))
"""


def test_help_imports_neither_drake_nor_torch():
    done = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    loaded = json.loads(done.stdout.splitlines()[-1])
    assert loaded == [], f"building the parser imported {loaded[:10]}"


def test_the_console_entry_point_prints_help():
    done = subprocess.run([sys.executable, "-m", "reachwatch.pipeline.cli", "--help"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    for command in ("render", "graph", "simulate", "sweep", "brt", "evaluate", "guard",
                    "run", "taxinet"):
        assert command in done.stdout


def test_the_parser_copies_of_library_constants_match_the_library():
    from reachwatch.pipeline import (evaluate_commands, reach_commands, run, run_commands,
                                     taxinet_commands)
    from reachwatch.reach import ACCURACIES
    from reachwatch.training.labels import DISTRUSTED_CHOICES, LABEL_SOURCES
    from reachwatch.taxi.taxinet_train import TaxiNetTrainConfig
    assert sorted(reach_commands.ACCURACIES) == sorted(ACCURACIES)
    assert tuple(evaluate_commands.LABEL_SOURCES) == tuple(LABEL_SOURCES)
    assert tuple(evaluate_commands.DISTRUSTED_CHOICES) == tuple(DISTRUSTED_CHOICES)
    assert taxinet_commands.TRAIN_SAMPLES == TaxiNetTrainConfig.samples
    assert taxinet_commands.TRAIN_EPOCHS == TaxiNetTrainConfig.epochs
    assert tuple(run_commands.STAGES) == tuple(run.STAGES)
    assert run_commands.SLICE_UNTIL == run.SLICE_UNTIL


def _options(parser, path=()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, path + (name,))
        elif action.option_strings:
            yield " ".join(path), action


def test_every_option_says_what_it_does():
    missing = [f"{command} {action.option_strings[-1]}"
               for command, action in _options(cli.build_parser()) if not action.help]
    assert missing == []


def test_help_texts_name_the_right_keys_and_defaults():
    options = {(command, action.option_strings[-1]): action.help
               for command, action in _options(cli.build_parser())}
    assert "monitor.detector" in options["guard", "--scenario"]
    assert "pipeline.detector" not in options["guard", "--scenario"]
    assert "test_environments()" in options["evaluate", "--test"]
    assert "18" in options["evaluate", "--test"]
    assert "docs/concepts.md#label-sources" in options["evaluate", "--labels"]


def test_brt_runs_no_real_loop_check_unless_asked():
    args = cli.build_parser().parse_args(["brt", "--out", "o"])
    assert args.drake_starts == 0
    args = cli.build_parser().parse_args(["brt", "--out", "o", "--drake-starts", "50"])
    assert args.drake_starts == 50


def test_guard_without_a_detector_fails_before_any_sweep(tmp_path, capsys):
    scenario = tmp_path / "s.yaml"
    scenario.write_text("environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    assert cli.main(["guard", "--scenario", str(scenario), "--shape", "3", "3", "3",
                     "--executor", "inline", "--cache", str(tmp_path / "cache"),
                     "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "monitor.detector is not set" in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists() and not (tmp_path / "cache").exists()


def test_guard_with_a_file_that_is_not_a_detector_fails_before_any_sweep(tmp_path, capsys):
    from reachwatch.diagrams import REFERENCE_TAXINET
    scenario = tmp_path / "s.yaml"
    scenario.write_text(f"monitor: {{detector: {REFERENCE_TAXINET}}}\n")
    assert cli.main(["guard", "--scenario", str(scenario), "--executor", "inline",
                     "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "o")]) == 2
    assert "error:" in capsys.readouterr().err
    assert not (tmp_path / "o").exists() and not (tmp_path / "cache").exists()


@pytest.mark.parametrize("argv", [
    ["sweep", "--executor", "inline", "--cache", "CACHE"],
    ["brt", "--executor", "inline", "--cache", "CACHE"],
    ["simulate"],
])
def test_out_naming_a_file_fails_before_any_work(tmp_path, capsys, argv):
    (tmp_path / "taken").write_text("a file")
    argv = [str(tmp_path / "cache") if a == "CACHE" else a for a in argv]
    assert cli.main(argv + ["--out", str(tmp_path / "taken")]) == 2
    err = capsys.readouterr().err
    assert "a file stands where a folder is needed" in err and err.count("\n") == 1
    assert not (tmp_path / "cache").exists()                # nothing swept


def test_simulate_guarded_without_a_detector_fails_before_it_writes(tmp_path, capsys):
    assert cli.main(["simulate", "--loop", "guarded", "--out", str(tmp_path / "o")]) == 2
    assert "monitor.detector is not set" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_an_application_without_a_method_is_one_line_not_a_traceback(monkeypatch, capsys,
                                                                    tmp_path):
    """A stage asking an application for what it does not implement (its one-line
    NotImplementedError) ends the command with exit 2 and that line."""
    def missing(args):
        raise NotImplementedError("CartApplication.fallback_rollouts is not implemented; "
                                  "set guard.candidates: 0")
    argv = ["guard", "--scenario", str(tmp_path / "s.yaml"), "--out", str(tmp_path / "out")]
    parser = cli.build_parser()
    args = parser.parse_args(argv)
    monkeypatch.setattr(cli, "build_parser", lambda: _Fixed(parser, args, missing))
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fallback_rollouts is not implemented" in err


class _Fixed:
    """A parser that returns ``args`` with ``func`` replaced."""
    def __init__(self, parser, args, func):
        self._parser, self._args, self._func = parser, args, func

    def parse_args(self, argv):
        self._args.func = self._func
        return self._args

    def __getattr__(self, name):
        return getattr(self._parser, name)
