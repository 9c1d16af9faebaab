"""Subcommand flags that repeat a run-file field default to the run file's value, read
from the schema's dataclass defaults when the command runs, so that the two cannot
drift apart (``guard --check-starts`` once defaulted to 0 against the run file's 200,
the grids of sweep, brt, guard and evaluate to three other shapes)."""

import argparse
import dataclasses as dc
import typing

import pytest

from reachwatch.pipeline import cli
from reachwatch.pipeline.commands import RunFileDefault, fill_run_file_defaults
from reachwatch.pipeline.spec import run_file_schema
from reachwatch.reach.application import load_application
from reachwatch.taxi.application import TAXI_APPLICATION

#: The run file's schema with the default application's (the taxi's) environments.
SCHEMA = run_file_schema(load_application(TAXI_APPLICATION))

#: Flags whose names are run-file fields' but which set something else, and what.
NOT_THE_RUN_FILES = {
    "--scenario": "the file itself",
    "simulate --start": "the one run's start state (a runway's start is where it begins)",
    "sweep --chunk-size": "grid states per sweep chunk (dataset.chunk_size is images)",
    "brt --chunk-size": "grid states per sweep chunk (dataset.chunk_size is images)",
    "evaluate --train": "the paper's 12 environments, where a run file lists its own",
    "evaluate --test": "the paper's 18 held-out environments, where a run file lists its own",
    "evaluate --solved-py-max": "the paper's run file's 290 m: the run file's 250 m leaves "
                                "the real-loop check no room at the default horizon",
    "taxinet train --samples": "TaxiNet's training set, not the detector's dataset",
    "taxinet train --epochs": "TaxiNet's training, not the detector's",
    "taxinet train --seed": "TaxiNet's training, not the detector's",
    "taxinet train --arch": "TaxiNet's architecture, not the detector's",
    "taxinet evaluate --hours": "hours of the catalog environments evaluated",
    "taxinet evaluate --checkpoint": "the TaxiNet evaluated (default: the shipped one)",
    "taxinet evaluate --samples": "states per environment for the estimation error",
    "taxinet evaluate --starts": "closed-loop starts per environment of the evaluation",
    "taxinet evaluate --seed": "seed of the evaluation's states and starts",
}


def _options(parser, path=()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, path + (name,))
        elif action.option_strings and action.dest not in ("help", "version"):
            yield " ".join(path), action


def _field_names(schema, seen=None) -> set:
    """Every field name of ``schema`` and of the dataclasses inside it."""
    seen = set() if seen is None else seen
    names = set()
    for field in dc.fields(schema):
        names.add(field.name)
        for t in [typing.get_type_hints(schema)[field.name]]:
            inner = [t] + list(typing.get_args(t))
            for candidate in inner:
                if dc.is_dataclass(candidate) and candidate not in seen:
                    seen.add(candidate)
                    names |= _field_names(candidate, seen)
    return names


def _schema_default(path: str):
    """The default at ``path`` read from the dataclass fields' declared defaults (not
    from an instance, as `RunFileDefault` reads it)."""
    schema, value = SCHEMA, None
    for part in path.split("."):
        field = {f.name: f for f in dc.fields(schema)}[part]
        value = (field.default if field.default is not dc.MISSING else field.default_factory())
        schema = typing.get_type_hints(schema)[part]
    return value


def test_no_flag_repeats_a_run_file_field_with_a_default_of_its_own():
    fields = _field_names(SCHEMA)
    own = [f"{command} {action.option_strings[0]}"
           for command, action in _options(cli.build_parser()) if action.dest.replace("-", "_") in fields
           and not isinstance(action.default, RunFileDefault)
           and f"{command} {action.option_strings[0]}" not in NOT_THE_RUN_FILES
           and action.option_strings[0] not in NOT_THE_RUN_FILES]
    assert own == [], f"give these the run file's default (RunFileDefault): {own}"


def test_every_run_file_default_is_the_schemas_and_a_value_the_flag_takes():
    found = 0
    for command, action in _options(cli.build_parser()):
        default = action.default
        if not isinstance(default, RunFileDefault):
            continue
        found += 1
        value = default.value()
        expected = [_schema_default(p) for p in default.paths]
        expected = expected[0] if len(expected) == 1 else expected
        if default.convert:
            expected = default.convert(expected)
        assert value == expected, (command, action.option_strings)
        items = value if isinstance(value, list) else [value]
        if action.nargs not in (None, "?"):
            assert isinstance(value, list) and (
                not isinstance(action.nargs, int) or len(value) == action.nargs)
        for item in items:
            if item is None:
                continue
            if action.type is not None:             # the flag's own check takes it
                assert action.type(str(item)) == item, (command, action.option_strings, item)
            if action.choices is not None:
                assert item in action.choices, (command, action.option_strings, item)
    assert found >= 30


@pytest.mark.parametrize("argv, name, path", [
    (["guard", "--scenario", "s.yaml", "--out", "o"], "check_starts", "guard.check_starts"),
    (["guard", "--scenario", "s.yaml", "--out", "o"], "shape", "grid"),
    (["guard", "--scenario", "s.yaml", "--out", "o"], "fallbacks", "guard.strategies"),
    (["sweep", "--out", "o"], "shape", "grid"),
    (["brt", "--out", "o"], "seed", "fidelity.seed"),
    (["evaluate", "--out", "o"], "shape", "grid"),
    (["evaluate", "--out", "o"], "samples", "dataset.samples"),
])
def test_a_flag_not_given_is_the_run_files(argv, name, path):
    args = fill_run_file_defaults(cli.build_parser().parse_args(argv))
    assert getattr(args, name) == _schema_default(path)
    given = fill_run_file_defaults(cli.build_parser().parse_args(argv + [
        f"--{name.replace('_', '-')}", *(["3", "3", "3"] if name == "shape" else
                                         ["brake"] if name == "fallbacks" else ["7"])]))
    assert getattr(given, name) in ([3, 3, 3], ["brake"], 7)
