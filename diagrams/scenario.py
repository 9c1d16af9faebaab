"""`Scenario`: what to build and run, loaded from YAML with `pydrake.common.yaml`.

Drake's loader reports an unknown field without saying where, and silently turns
``200.0`` into an int; `load_scenario` checks the raw YAML against the dataclass
schema first, so every error names the field's full path.
"""

import dataclasses as dc
import math
import os
import re
import typing
from pathlib import Path
from typing import Dict, List

import yaml
from pydrake.common.yaml import yaml_dump_typed, yaml_load_data, yaml_load_typed

from reachwatch.systems import CameraConfig, Environment
from reachwatch.systems.bounds import MAX_INT, bounded, check_bounds, seed_field
from reachwatch.systems.checks import clip, is_file, short

from .monitor_config import MAX_FLAG_WINDOW, STORED_STEERING, MonitorConfig  # noqa: F401
from .schemas import ApplicationEnvironment, slot_field, typed_schema, untyped

#: Bounds on a scenario's numbers (a value past them is a mistake, or would hang a run).
MAX_DURATION = 3600.0       # s of simulated time
MAX_PERIOD = 10.0           # s between control updates
MAX_SPEED = 100.0           # m/s
MAX_POSITION = 10000.0      # m (or deg) of a start state's coordinates
#: The largest scenario or run file read (bytes), and the most YAML nodes its aliases
#: may expand to (a small file of nested aliases otherwise expands without bound).
MAX_FILE_BYTES = 1 << 20
MAX_NODES = 100_000


@dc.dataclass
class InitialState:
    """Start state in the units configs speak: px m, py m, theta deg."""
    px: float = bounded(0.0, -MAX_POSITION, MAX_POSITION, unit="m")
    py: float = bounded(110.0, -MAX_POSITION, MAX_POSITION, unit="m")
    theta_deg: float = bounded(0.0, -MAX_POSITION, MAX_POSITION, unit="deg")


@dc.dataclass
class ControllerConfig:
    """The controller under test and how it is run. ``factory``: the function that
    builds it (``"package.module:function"`` or ``"path/to/file.py:function"``, given
    this config; empty = TaxiNet + P-controller, see `reachwatch.diagrams.controller`);
    ``parameters``: numbers for that function; ``data_files``: files it reads (a table
    of gains, a second network), keyed by their content as ``checkpoint`` is, which the
    factory finds in ``config.data_files``. ``checkpoint`` empty = the shipped
    reference TaxiNet; gains in deg per m and deg per deg (TaxiNet's P-controller and
    the privileged oracle); ``period`` s (the steering is held that long); ``speed`` m/s.
    A factory is code: the commands that build the controller (simulate, sweep, brt,
    evaluate, guard, run, and graph to draw the loop) import and run it, so run only
    scenario files you trust; loading a file, ``render`` and ``graph --loop world``
    check its form alone and run none of it."""
    factory: str = ""
    parameters: Dict[str, float] = dc.field(default_factory=dict)
    data_files: List[str] = dc.field(default_factory=list)
    checkpoint: str = ""
    px_gain: float = bounded(-0.74, -1000.0, 1000.0, unit="deg/m")
    theta_gain: float = bounded(-0.44, -1000.0, 1000.0, unit="deg/deg")
    period: float = bounded(0.05, 0.0, MAX_PERIOD, low_open=True, unit="s")
    speed: float = bounded(5.0, 0.0, MAX_SPEED, unit="m/s")

    def __fingerprint__(self):
        """What a sweep of this controller depends on: every field, plus the code of a
        user factory (an edited controller never reuses a stale table). A factory file
        is keyed by its name and function, its folder's code by content: a moved or
        cloned project reuses its caches, as a moved checkpoint does."""
        from .user_code import factory_code_hash
        fields = {f.name: getattr(self, f.name) for f in dc.fields(self)}
        target, _, function = self.factory.rpartition(":")
        if target.endswith(".py"):
            fields["factory"] = f"{os.path.basename(target)}:{function}"
        return {**fields, "factory_code": factory_code_hash(self.factory)}

    def validate(self):
        if self.factory:        # its form only: the factory is imported when it is built
            from .user_code import _split
            target, _ = _split(self.factory)
            if target.endswith(".py") and not is_file(target):
                raise ValueError(f"controller.factory: file not found: {clip(target, 200)}")
        if self.parameters and not self.factory:
            raise ValueError(f"controller.parameters: only a controller.factory reads them, "
                             f"and none is given (the default TaxiNet takes none): set "
                             f"controller.factory, or remove "
                             f"{short(', '.join(map(str, self.parameters)))}")
        if self.data_files and not self.factory:
            raise ValueError("controller.data_files: only a controller.factory reads them, "
                             "and none is given")
        for i, path in enumerate(self.data_files):
            if not is_file(path):
                raise ValueError(f"controller.data_files[{i}]: file not found: {clip(path, 200)}")
        for name, value in self.parameters.items():
            if not math.isfinite(value):
                raise ValueError(f"controller.parameters.{short(name)} must be finite, got {value}")
        check_bounds(self, "controller.")
        if self.checkpoint and not is_file(self.checkpoint):
            raise ValueError(f"controller.checkpoint: file not found: {clip(self.checkpoint, 200)}")
        return self


def _taxi_default(slot, role):
    """A scenario file's default environment: the taxi's `Environment()`."""
    return Environment


@dc.dataclass
class Scenario:
    """One run: environment, camera, start state, controller, duration (s), seed.

    ``initial_state``, ``duration`` and ``seed`` are a single run's (``reachwatch
    simulate``); sweeps and batches of real-loop runs set their own starts and
    durations and build the loop with these three at their defaults. No loop of the
    library reads ``seed``."""
    environment: ApplicationEnvironment = slot_field("scenario", default_factory=Environment)
    camera: CameraConfig = dc.field(default_factory=CameraConfig)
    initial_state: InitialState = dc.field(default_factory=InitialState)
    controller: ControllerConfig = dc.field(default_factory=ControllerConfig)
    monitor: MonitorConfig = dc.field(default_factory=MonitorConfig)
    duration: float = bounded(10.0, 0.0, MAX_DURATION, low_open=True, unit="s")
    seed: int = seed_field()
    shadows: bool = False

    #: The fields of a single run alone (``reachwatch simulate``), unread by sweeps and
    #: batches of real-loop runs.
    SINGLE_RUN_FIELDS = ("initial_state", "duration", "seed")

    def single_run_settings(self) -> List[str]:
        """The names of `SINGLE_RUN_FIELDS` set to other than their defaults (a run
        file's stages do not read them: worth a word to whoever set them)."""
        defaults = type(self)()
        return [name for name in self.SINGLE_RUN_FIELDS
                if getattr(self, name) != getattr(defaults, name)]

    @classmethod
    def schema_for(cls, raw) -> type:
        """The schema a scenario file is loaded with: its environment is the taxi's
        (`Environment`); a run file's ``scenario`` takes its application's."""
        return typed_schema(cls, ((ApplicationEnvironment, Environment),), _taxi_default)

    def validate(self):
        """Raise ValueError naming the first bad field; return self."""
        self.environment.validate()
        self.camera.validate()
        self.controller.validate()
        self.monitor.validate()
        check_bounds(self)
        check_bounds(self.initial_state, "initial_state.")
        return self


class ScenarioError(ValueError):
    """A scenario file that does not match the schema; the message names the field."""


def _type_name(t):
    return getattr(t, "__name__", str(t))


#: A number written as text that PyYAML reads as a string (``1e-4``: YAML 1.1 floats
#: need a dot), accepted for a float field.
_FLOAT_TEXT = re.compile(r"[-+]?(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?")


def _key_text(key) -> str:
    """A mapping key as a field path writes it (cut short)."""
    return key if isinstance(key, str) and len(key) <= 60 else short(key)


def _is_seed(key) -> bool:
    return key in ("seed", "seeds") or str(key).endswith("_seed")


def _check(value, schema, path, later=None, converted=None):
    """Compare raw YAML data with a type from the schema; raise ScenarioError. Returns
    the value, a number written as text (``1e-4``) in a float field turned into a float
    (noted in ``converted``). Non-finite floats and negative seeds are noted in
    ``later`` as ``(path, message)``: the schema's own checks run first and say more."""
    later = [] if later is None else later
    converted = [] if converted is None else converted
    origin = typing.get_origin(schema)
    if origin is typing.Union:                      # Optional[T]
        args = [a for a in typing.get_args(schema) if a is not type(None)]
        if value is None:
            return value
        return _check(value, args[0], path, later, converted)
    if dc.is_dataclass(schema):
        if not isinstance(value, dict):
            raise ScenarioError(f"{path}: expected a mapping of {schema.__name__} fields, "
                                f"got {type(value).__name__} {short(value)}")
        fields = {f.name: f for f in dc.fields(schema)}
        hints = typing.get_type_hints(schema)
        for key, item in list(value.items()):
            if key not in fields:
                raise ScenarioError(f"{path}.{_key_text(key)}: unknown field of {schema.__name__}; "
                                    f"known fields: {', '.join(fields)}")
            checked = _check(item, hints[key], f"{path}.{key}", later, converted)
            if checked is not item:
                value[key] = checked
            if _is_seed(key):
                for seed in (checked if isinstance(checked, list) else [checked]):
                    if isinstance(seed, int) and seed < 0:
                        later.append((f"{path}.{key}", f"must be a seed, a whole number in "
                                                       f"[0, {MAX_INT}], got {seed}"))
        return value
    if origin in (dict, Dict):
        if not isinstance(value, dict):
            raise ScenarioError(f"{path}: expected a mapping, got {type(value).__name__} "
                                f"{short(value)}")
        key_type, item_type = typing.get_args(schema)
        for key, item in list(value.items()):
            _check(key, key_type, f"{path} key", later, converted)
            checked = _check(item, item_type, f"{path}.{key}", later, converted)
            if checked is not item:
                value[key] = checked
        return value
    if origin in (list, List):
        if not isinstance(value, list):
            raise ScenarioError(f"{path}: expected a list, got {type(value).__name__} "
                                f"{short(value)}")
        (item_type,) = typing.get_args(schema)
        for i, item in enumerate(value):
            checked = _check(item, item_type, f"{path}[{i}]", later, converted)
            if checked is not item:
                value[i] = checked
        return value
    if schema is float and isinstance(value, str) and _FLOAT_TEXT.fullmatch(value.strip()):
        value = float(value)
        converted.append(path)
    ok = {bool: lambda v: isinstance(v, bool),
          int: lambda v: isinstance(v, int) and not isinstance(v, bool),
          float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
          str: lambda v: isinstance(v, str)}.get(schema, lambda v: True)
    if not ok(value):
        raise ScenarioError(f"{path}: expected {_type_name(schema)}, got "
                            f"{type(value).__name__} {short(value)}")
    if schema in (int, float) and isinstance(value, int) and abs(value) > MAX_INT:
        raise ScenarioError(f"{path}: {short(value)} is out of range; numbers here are at "
                            f"most {MAX_INT} in size")
    if schema is float and not math.isfinite(value):
        later.append((path, f"must be a finite number, got {value}"))
    return value


def _expanded_nodes(root, budget: int) -> int:
    """How many nodes the YAML node graph ``root`` stands for with every alias written
    out; a ScenarioError past ``budget`` or for an alias inside its own anchor."""
    sizes, open_nodes = {}, set()

    def size(node):
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in open_nodes:
            raise ScenarioError("a YAML alias refers to a node that contains it")
        open_nodes.add(key)
        if isinstance(node, yaml.SequenceNode):
            children = node.value
        elif isinstance(node, yaml.MappingNode):
            children = [part for pair in node.value for part in pair]
        else:
            children = []
        total = 1
        for child in children:
            total += size(child)
            if total > budget:
                raise ScenarioError(f"the YAML holds more than {budget} values (each alias, "
                                    f"*name, counted as the values it stands for); a "
                                    f"scenario or run file needs far fewer")
        open_nodes.discard(key)
        sizes[key] = total
        return total

    return size(root)


class _UniqueKeyLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """PyYAML's safe loader (its C parser where PyYAML has one: a 1 MiB file is parsed
    in about a second rather than ten), refusing a key written twice in one mapping
    (PyYAML and Drake's loader silently keep the last one), and a document that holds
    more than `MAX_NODES` values with its aliases written out (a few hundred bytes of
    nested aliases would otherwise stand for billions)."""

    def get_single_node(self):
        node = super().get_single_node()
        if node is not None:
            _expanded_nodes(node, MAX_NODES)
        return node

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if key in seen:
                raise ScenarioError(f"line {key_node.start_mark.line + 1}: key {short(key)} is "
                                    f"written twice in one mapping (first on line {seen[key]})")
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep)


def read_text_file(filename, what="scenario file") -> str:
    """The UTF-8 text of ``filename``; ScenarioError naming it when it is missing, not
    a regular file, larger than `MAX_FILE_BYTES`, binary or empty."""
    path = Path(filename)
    if os.path.isdir(path):             # (False, not an error, for a name too long)
        raise ScenarioError(clip(f"{filename} is a folder, not a {what}", 300))
    if not is_file(path):
        raise ScenarioError(clip(f"{what} not found: {filename}", 300))
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ScenarioError(f"{filename}: {size} bytes; a {what} is at most "
                            f"{MAX_FILE_BYTES} bytes")
    raw = path.read_bytes()
    if b"\0" in raw:
        raise ScenarioError(f"{filename}: not a text YAML file (it holds NUL bytes)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ScenarioError(f"{filename}: not a UTF-8 text YAML file ({e.reason} at byte "
                            f"{e.start})") from None
    if not any(line.strip() and not line.lstrip().startswith("#") for line in text.splitlines()):
        raise ScenarioError(f"{filename} is empty; write '{{}}' for all defaults")
    return text


def read_yaml(data: str, where: str, *, drake=True):
    """The data of the YAML text ``data`` (at most `MAX_FILE_BYTES`; a key written twice,
    or aliases expanding past `MAX_NODES` values, is an error); a ScenarioError starting
    with ``where`` otherwise. ``drake``: also parse it with Drake's loader (which the
    typed load uses)."""
    if len(data) > MAX_FILE_BYTES:
        raise ScenarioError(f"{where}: {len(data)} characters; a scenario is at most "
                            f"{MAX_FILE_BYTES}")
    try:
        raw = yaml.load(data, Loader=_UniqueKeyLoader) if data.strip() else None
        if raw and drake:
            yaml_load_data(data)
    except ScenarioError as e:
        raise ScenarioError(clip(f"{where}: {e}")) from None
    except ValueError as e:  # an integer of thousands of digits (Python's own limit)
        if "integer string conversion" not in str(e):
            raise ScenarioError(clip(f"{where}: not valid YAML: {e}")) from None
        raise ScenarioError(clip(f"{where}: a number of thousands of digits; numbers here "
                                 f"are at most {MAX_INT} in size")) from None
    except Exception as e:  # PyYAML's or Drake's parser error
        text = " ".join(str(e).replace('in "<unicode string>", line', "at line").split())
        raise ScenarioError(clip(f"{where}: not valid YAML: {text}")) from None
    return raw


def load_scenario(filename=None, *, data=None, schema=Scenario, root="scenario", edit=None):
    """Load and validate a scenario (``schema`` instance) from a YAML file or string
    (an empty string means all defaults; an empty file is an error); errors name fields
    as ``root.field.subfield``, and a key written twice is an error. Every float must
    be finite, every seed >= 0; a float written as text that PyYAML takes for a string
    (``1e-4``) is read as the number. ``edit``: None, or an object whose ``apply(raw,
    schema, root)`` returns the raw data changed (e.g. command-line overlays) and whose
    ``where`` says how errors name it; it runs before every check, so the changed
    values are checked as the file's are (``apply``'s ``schema`` is a function of the
    data so far returning its schema). A ``schema`` with a ``schema_for(raw)``
    class method (a generic schema with application slots, `schemas`) is loaded as the
    schema that returns for the data, and handed back as ``schema`` instances
    (`schemas.untyped`)."""
    where = (str(filename) if filename is not None else "<yaml>" if data.strip()
             else "the built-in defaults")
    if filename is not None:
        data = read_text_file(filename)
    raw = read_yaml(data, where)
    raw = {} if raw is None else raw
    later, converted = [], []
    try:
        schema_of = schema.schema_for if hasattr(schema, "schema_for") else lambda _: schema
        if edit is not None:                # its own errors name their overlay
            raw = edit.apply(raw, schema_of, root)
            where = f"{where} {edit.where}"
        typed = schema_of(raw)
        raw = _check(raw, typed, root, later, converted)
        if converted or edit is not None:   # Drake's loader reads the text again: give
            data = yaml.safe_dump(raw, default_flow_style=None)     # it the numbers
        scenario = untyped(yaml_load_typed(schema=typed, data=data) if raw else typed())
        scenario.validate()
    except (ScenarioError, ValueError) as e:     # ScenarioError is a ValueError
        hint = ("this looks like a run file (it has train: or scenario:), which `reachwatch "
                "run --scenario` reads; " if root == "scenario" and isinstance(raw, dict)
                and {"train", "scenario"} & set(raw) else
                "this looks like a scenario file (it has environment:, camera:, "
                "initial_state: or controller:), which a run file holds under scenario:; "
                if root == "run" and isinstance(raw, dict) and "scenario" not in raw and
                {"environment", "camera", "initial_state", "controller"} & set(raw) else "")
        raise ScenarioError(clip(f"{where}: {hint}{e}")) from None
    except (ArithmeticError, TypeError):        # a non-finite number the checks missed
        if not later:
            raise
    if later:
        path, message = later[0]
        raise ScenarioError(clip(f"{where}: {path} {message}"))
    return scenario


def dump_scenario(scenario, schema=None) -> str:
    """YAML text of ``scenario`` (round-trips through `load_scenario`); ``schema``: the
    schema to write it as (default: its class's ``schema_for``, or its class)."""
    if schema is None:
        kind = type(scenario)
        schema = (kind.schema_for({f.name: getattr(scenario, f.name) for f in dc.fields(kind)})
                  if hasattr(kind, "schema_for") else kind)
    return yaml_dump_typed(scenario, schema=schema)
