"""Every declared bound of a run-file or scenario-file key is the one enforced: for each
numeric key with a bound (`reachwatch.systems.bounds`), a value just outside it is
refused when the file is loaded, with a one-line error naming the key, and a value at
it (just inside an open end) is accepted. The cases are read from the declarations, so a
new bound is tested without a new test."""

import copy
import dataclasses as dc
import math
import re
import typing
from typing import List, Optional

import pytest
import yaml

from reachwatch.diagrams import ScenarioError, load_scenario
from reachwatch.pipeline.reference import _classes
from reachwatch.pipeline.spec import load_run_spec, run_file_schema
from reachwatch.reach.application import load_application
from reachwatch.taxi.application import TAXI_APPLICATION
from reachwatch.systems.bounds import Bound, bounds, check_bounds
from tiny_run import TINY

#: Other keys a value at a bound needs set, because a relation between keys (checked
#: by the schema's validate, after the bounds) would refuse it otherwise: ``(key, end)``
#: -> ``{key: value}`` (``SAME``: the value under test).
SAME = object()
COMPANIONS = {
    ("run.scenario.camera.near", "high"): {"run.scenario.camera.far": 1e5},
    # a runway holds its threshold stripes between its edge lines
    ("run.scenario.environment.runway_spec.half_width", "low"): {
        "run.scenario.environment.runway_spec.markings.threshold_stripes": 0},
    ("run.scenario.environment.runway_spec.markings.edge_line_width", "high"): {
        "run.scenario.environment.runway_spec.half_width": 20.0},
    ("run.train_random.runway.half_width", "low"): {
        "run.train_random.runway.threshold_stripes": [0, 0]},
    # no states mined: only with the stage off
    ("run.incremental.anomalies", "low"): {"run.incremental.enabled": False},
    # the k-of-n rule is set whole or left to the checkpoint
    ("run.scenario.monitor.flags_needed", "low"): {"run.scenario.monitor.flag_window": 1},
    ("run.scenario.monitor.flags_needed", "high"): {"run.scenario.monitor.flag_window": 1000},
    ("run.scenario.monitor.flag_window", "low"): {"run.scenario.monitor.flags_needed": 1},
    ("run.scenario.monitor.flag_window", "high"): {"run.scenario.monitor.flags_needed": 1},
    ("run.dataset.height", "low"): {"run.detector.detector.height": SAME},
    ("run.dataset.height", "high"): {"run.detector.detector.height": SAME},
    ("run.dataset.width", "low"): {"run.detector.detector.width": SAME},
    ("run.dataset.width", "high"): {"run.detector.detector.width": SAME},
    ("run.detector.detector.height", "low"): {"run.dataset.height": SAME},
    ("run.detector.detector.height", "high"): {"run.dataset.height": SAME},
    ("run.detector.detector.width", "low"): {"run.dataset.width": SAME},
    ("run.detector.detector.width", "high"): {"run.dataset.width": SAME},
    ("run.dataset.labels.band", "high"): {"run.dataset.labels.max_band": 1000.0},
    ("run.dataset.labels.max_band", "low"): {"run.dataset.labels.band": 0.0},
    ("run.detector.validation_fraction", "low"): {"run.detector.target_recall": 0.0},
    ("run.monitor.within", "high"): {"run.monitor.duration": 600.0},
    # the pooling grid must fit in the encoder's last map (the frame halved per layer)
    ("run.monitor.height", "low"): {"run.monitor.pool": [1, 1]},
    ("run.monitor.width", "low"): {"run.monitor.pool": [1, 1]},
    ("run.monitor.pool", "high"): {"run.monitor.height": 512, "run.monitor.width": 512},
    ("run.monitor.calibrate", "low"): {"run.monitor.alpha": 0.5},
    # guarded runs come from the recorded starts of each held-out environment
    ("run.monitor.guarded_runs", "high"): {"run.monitor.held_out_runs": 100_000},
    # horizon and guard.online_seconds are at least one control period
    ("run.scenario.controller.period", "high"): {"run.horizon": 120.0,
                                                 "run.guard.online_seconds": 10.0},
}
#: Ends that a relation keeps from being reached at all: the value tested inside
#: instead, and what it needs. ``monitor.duration`` must exceed ``monitor.within`` (> 0),
#: and ``alpha`` must be at least 1 / (calibrate + 1) with calibrate <= 1000.
INSIDE_INSTEAD = {
    ("run.monitor.duration", "low"): (1e-3, {"run.monitor.within": 5e-4}),
    ("run.scenario.camera.far", "low"): (1e-3, {"run.scenario.camera.near": 5e-4}),
    ("run.monitor.alpha", "low"): (1 / 1001, {"run.monitor.calibrate": 1000}),
    ("run.horizon", "low"): (1e-3, {"run.scenario.controller.period": 1e-3}),
    ("run.guard.online_seconds", "low"): (1e-3, {"run.scenario.controller.period": 1e-3}),
}


#: The run file's schema with the default application's (the taxi's) environments.
SCHEMA = run_file_schema(load_application(TAXI_APPLICATION))


def _cases():
    """``(class, key path, field name, Bound)`` of every bounded field, once per class
    (at the first key where its class appears)."""
    out = []
    for cls, paths in _classes(SCHEMA, "run"):
        for name, bound in bounds(cls).items():
            out.append((cls, paths[0], name, bound))
    return out


CASES = _cases()


def _ends(bound: Bound):
    return [end for end in ("low", "high") if getattr(bound, end) is not None]


def _step(bound: Bound, x, towards: float):
    """The next number from ``x`` towards ``towards``: 1 for a whole number, the next
    float otherwise."""
    if bound.whole:
        return x + (1 if towards > x else -1)
    return math.nextafter(x, towards)


def _at(bound: Bound, end: str):
    """The value at ``end`` that must be accepted (just inside an open end)."""
    if end == "low":
        value = bound.low if not bound.low_open else _step(bound, bound.low, math.inf)
    else:
        value = bound.high if not bound.high_open else _step(bound, bound.high, -math.inf)
    return int(value) if bound.whole else float(value)


def _outside(bound: Bound, end: str):
    """The value just outside ``end`` that must be refused."""
    if end == "low":
        value = bound.low if bound.low_open else _step(bound, bound.low, -math.inf)
    else:
        value = bound.high if bound.high_open else _step(bound, bound.high, math.inf)
    return int(value) if bound.whole else float(value)


def _list_value(bound: Bound, end: str, edge, current):
    """A list holding ``edge`` at ``end`` and other values inside, ascending and
    different (a ``[low, high]`` range stays ordered, seeds stay distinct)."""
    least, most = bound.items or (0, None)
    n = len(current) if isinstance(current, list) and current else max(least, 2)
    n = min(max(n, least, 1), most if most is not None else n)
    if end == "low":
        values, x = [edge], _at(bound, "low")
        for _ in range(n - 1):
            x = _step(bound, x, math.inf)
            values.append(x)
        return values
    values, x = [edge], _at(bound, "high")
    for _ in range(n - 1):
        x = _step(bound, x, -math.inf)
        values.insert(0, x)
    return values


def _set(data, key_path: str, value):
    """Set ``run.a.b[].c`` in raw run-file data (mappings and first list items made as
    needed)."""
    parts = key_path.split(".")[1:]
    node = data
    for part in parts[:-1]:
        listed = part.endswith("[]")
        name = part[:-2] if listed else part
        if listed:
            items = node.get(name) or [{}]
            node[name] = items
            node = items[0]
        else:
            if not isinstance(node.get(name), dict):
                node[name] = {}
            node = node[name]
    node[parts[-1]] = value


def _dataclass_of(annotation):
    """``X`` of ``X``, ``Optional[X]`` or ``List[X]``."""
    if dc.is_dataclass(annotation):
        return annotation
    return next(a for a in typing.get_args(annotation) if dc.is_dataclass(a))


def _set_field(spec, key_path: str, value):
    """Set ``run.a.b[].c`` on a `RunSpec` (a null dataclass made, a list's first item
    made or used)."""
    parts = key_path.split(".")[1:]
    node, schema = spec, SCHEMA
    for part in parts[:-1]:
        listed = part.endswith("[]")
        name = part[:-2] if listed else part
        child = getattr(node, name)
        kind = schema = _dataclass_of(typing.get_type_hints(schema)[name])
        if listed:
            if not child:
                child.append(kind())
            child = child[0]
        elif child is None:
            child = kind()
            setattr(node, name, child)
        node = child
    setattr(node, parts[-1], value)


def _get_field(spec, key_path: str):
    """The value at ``run.a.b[].c`` (None where the path passes a null or empty list)."""
    node = spec
    for part in key_path.split(".")[1:]:
        node = getattr(node, part[:-2] if part.endswith("[]") else part)
        if part.endswith("[]"):
            node = node[0] if node else None
        if node is None:
            return None
    return node


BASE = load_run_spec(data=TINY)


def _spec(key, value, extra=()):
    spec = copy.deepcopy(BASE)
    _set_field(spec, key, value)
    for other, other_value in extra:
        _set_field(spec, other, value if other_value is SAME else other_value)
    return spec


def _run_file(key, value):
    data = yaml.safe_load(TINY)
    _set(data, key, value)
    return yaml.safe_dump(data, default_flow_style=None)


def _scenario_file(key, value):
    """The same edit in a scenario file (``run.scenario.`` keys only)."""
    data = {}                       # `_set` drops the first part of a key: the root
    _set(data, "scenario." + key[len("run.scenario."):], value)
    return yaml.safe_dump(data, default_flow_style=None)


def _names_the_key(message: str, cls, path: str, name: str) -> bool:
    """Whether a one-line error names the key: the field's name, after its parent's
    (``surface.roughness``, ``taxiway_lines[0].radius``) below the top level of a file."""
    if "\n" in message or not re.search(rf"(^|[\s.']){re.escape(name)}\b", message):
        return False
    if cls.__name__ in ("RunSpec", "Scenario"):
        return True
    parent = path.split(".")[-1]
    parent = parent[:-2] + "[0]" if parent.endswith("[]") else parent
    return f"{parent}.{name}" in message


def _value_cases():
    out = []
    for cls, path, name, bound in CASES:
        if not bound.has_range:
            continue
        for end in _ends(bound):
            out.append(pytest.param(cls, path, name, bound, end,
                                    id=f"{path}.{name}-{end}"))
    return out


def _item_cases():
    out = []
    for cls, path, name, bound in CASES:
        if bound.items is None:
            continue
        least, most = bound.items
        for count in ([least - 1] if least > 0 else []) + ([most + 1] if most is not None else []):
            out.append(pytest.param(cls, path, name, bound, count,
                                    id=f"{path}.{name}-{count}-items"))
    return out


def test_every_numeric_key_of_the_reference_sections_is_declared():
    """A float or int key with no bound is a choice, not an oversight: the ones that may
    be any number are listed here."""
    numeric = (int, float, Optional[int], Optional[float], List[int], List[float])
    unbounded = {f"{paths[0]}.{f.name}" for cls, paths in _classes(SCHEMA, "run")
                 for f in dc.fields(cls)
                 if typing.get_type_hints(cls)[f.name] in numeric and "bound" not in f.metadata}
    assert unbounded == set(), unbounded
    assert len(CASES) > 100


@pytest.mark.parametrize("cls, path, name, bound, end", _value_cases())
def test_a_value_just_outside_a_bound_is_refused_and_at_it_accepted(cls, path, name, bound,
                                                                      end):
    key = f"{path}.{name}"
    extra = tuple(COMPANIONS.get((key, end), {}).items())
    inside = _at(bound, end)
    instead = INSIDE_INSTEAD.get((key, end))
    if instead is not None:
        inside, more = instead
        extra = extra + tuple(more.items())
    outside = _outside(bound, end)
    if bound.each:
        current = _get_field(BASE, key)
        inside = _list_value(bound, end, inside, current)
        outside = _list_value(bound, end, outside, current)
    spec = _spec(key, inside, extra).validate()                 # the relations hold
    assert _get_field(spec, key) == inside
    with pytest.raises(ValueError) as refused:
        _spec(key, outside).validate()                          # the bound alone refuses
    assert _names_the_key(str(refused.value), cls, path, name), str(refused.value)


def _first_bounds():
    """The first bounded number of each class: loaded from YAML too."""
    out, seen = [], set()
    for cls, path, name, bound in CASES:
        if cls not in seen and bound.has_range and not bound.each:
            seen.add(cls)
            out.append(pytest.param(cls, path, name, bound, id=f"{path}.{name}"))
    return out


@pytest.mark.parametrize("cls, path, name, bound", _first_bounds())
def test_the_files_refuse_a_value_outside_with_a_one_line_error_naming_the_key(cls, path, name,
                                                                               bound):
    """The same through the YAML loaders: a run file, and a scenario file for the
    scenario's keys (a value at the bound loads)."""
    key = f"{path}.{name}"
    end = _ends(bound)[0]
    loaders = [(load_run_spec, _run_file)]
    if key.startswith("run.scenario."):
        loaders.append((load_scenario, _scenario_file))
    for load, text in loaders:
        if (key, end) not in COMPANIONS and (key, end) not in INSIDE_INSTEAD:
            load(data=text(key, _at(bound, end)))
        with pytest.raises(ScenarioError) as refused:
            load(data=text(key, _outside(bound, end)))
        message = str(refused.value)
        assert message.startswith("<yaml>: ") and _names_the_key(message, cls, path, name), \
            message


@pytest.mark.parametrize("cls, path, name, bound, count", _item_cases())
def test_a_list_with_too_few_or_too_many_items_is_refused(cls, path, name, bound, count):
    key = f"{path}.{name}"
    least, most = bound.items
    value = [{} for _ in range(count)]
    if bound.has_range:
        value = [_at(bound, "low")] * min(count, 1)
        while len(value) < count:
            value.append(_step(bound, value[-1], math.inf))
    with pytest.raises(ValueError) as refused:
        _spec(key, value).validate()
    assert _names_the_key(str(refused.value), cls, path, name), str(refused.value)


def test_check_bounds_names_the_key_and_reads_each_declaration():
    @dc.dataclass
    class Demo:
        share: float = dc.field(default=0.5, metadata={"bound": Bound(0.0, 1.0,
                                                                      high_open=True)})
        sizes: list = dc.field(default_factory=lambda: [3], metadata={
            "bound": Bound(3, 9, whole=True, each=True, items=(1, 2))})
        count: int = dc.field(default=1, metadata={"bound": Bound(1, whole=True, unit="runs")})

    assert check_bounds(Demo(), "demo.") is not None
    for changed, message in (({"share": 1.0}, "demo.share must be a finite number in [0, 1), got 1.0"),
                             ({"share": True}, "demo.share must be a finite number"),
                             ({"share": float("nan")}, "demo.share must be"),
                             ({"sizes": [3, 10]}, "demo.sizes[1] must be a whole number in [3, 9]"),
                             ({"sizes": [3.0]}, "demo.sizes[0] must be a whole number"),
                             ({"sizes": [3, 4, 5]}, "demo.sizes must list 1 to 2 items, got 3"),
                             ({"count": 0}, "demo.count must be a whole number >= 1 runs, got 0")):
        with pytest.raises(ValueError, match=re.escape(message)):
            check_bounds(dc.replace(Demo(), **changed), "demo.")
    texts = {name: b.text() for name, b in bounds(Demo).items()}
    assert texts == {"share": "[0, 1)", "sizes": "1 to 2 items, each in [3, 9]",
                     "count": ">= 1 runs"}


def test_the_reference_prints_each_declared_bound():
    from reachwatch.pipeline.reference import reference_markdown
    text = reference_markdown()
    for cls, path, name, bound in CASES:
        section = text.split(f"## {cls.__name__}\n", 1)[1].split("\n## ", 1)[0]
        row = next(line for line in section.splitlines() if line.startswith(f"| `{name}` |"))
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", row)]   # key, type, default, bounds
        assert cells[4] == bound.text().replace("|", "\\|"), row


def _bounded_flags():
    """``(command, action, key, Bound)`` of every flag that sets one run-file key with a
    declared bound (its default a `RunFileDefault`)."""
    import argparse

    from reachwatch.pipeline import cli
    from reachwatch.pipeline.commands import RunFileDefault, _declared_bound
    out = []
    for name, sub in next(a for a in cli.build_parser()._actions
                          if isinstance(a, argparse._SubParsersAction)).choices.items():
        for action in sub._actions:
            default = action.default
            if isinstance(default, RunFileDefault) and len(default.paths) == 1 \
                    and default.convert is None:
                bound = _declared_bound(default.paths[0])
                if bound is not None and bound.has_range:
                    out.append(pytest.param(name, action, default.paths[0], bound,
                                            id=f"{name} {action.option_strings[0]}"))
    return out


@pytest.mark.parametrize("command, action, key, bound", _bounded_flags())
def test_a_flag_that_sets_a_run_file_key_is_bounded_as_the_key(command, action, key, bound,
                                                                capsys):
    """Past the flag's own type check, the key's declaration refuses what a run file
    would refuse (exit 2, naming the flag and the key) and takes what it takes."""
    import argparse

    from reachwatch.pipeline import cli
    from reachwatch.pipeline.commands import check_run_file_flags
    parser = cli.build_parser()
    for end in _ends(bound):
        inside, outside = _at(bound, end), _outside(bound, end)
        if bound.each:
            inside, outside = [inside] * action.nargs, [outside] * action.nargs
        check_run_file_flags(parser, argparse.Namespace(command=command,
                                                        **{action.dest: inside}))
        with pytest.raises(SystemExit) as refused:
            check_run_file_flags(parser, argparse.Namespace(command=command,
                                                            **{action.dest: outside}))
        last = capsys.readouterr().err.strip().splitlines()[-1]
        assert refused.value.code == 2
        assert last.startswith(f"reachwatch {command}: error: argument {action.option_strings[0]}")
        assert key in last, last


def test_the_command_line_refuses_a_flag_outside_its_keys_bound_before_any_work(tmp_path,
                                                                                   capsys):
    from reachwatch.pipeline import cli
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as refused:
        cli.main(["evaluate", "--out", str(out), "--samples", "5"])
    assert refused.value.code == 2 and not out.exists()
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "reachwatch evaluate: error: argument --samples: dataset.samples must be a whole "
        "number in [10, 10000000], got 5")
    assert len(_bounded_flags()) >= 20
