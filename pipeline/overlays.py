"""Overlays: changes to a run or scenario file given on the command line, applied to
the file's data before it is checked, so an overlaid value meets every check a value
in the file meets (and a run's key, and its ``run.yaml``, are those of the file it makes).

- ``--set KEY=VALUE``: ``KEY`` is a dotted path into the file's mappings, with list
  items by index (``guard.check_starts``, ``train.0.hour`` or ``train[0].hour``);
  ``VALUE`` is read as YAML (``5``, ``1.0e-4``, ``true``, ``[5, 3, 5]``, ``{runway:
  KSFO, hour: 17.0, sky: clear}``, text). It replaces what is there; missing mappings on
  the way are made.
- ``--scenario-text YAML``: a YAML mapping merged into the file, as Drake's
  ``--scenario_text`` is: mappings are merged key by key, anything else (numbers,
  text, lists) replaced.

Overlays apply in the order given. A key that is not a field of the file's schema is
an error naming the overlay and the field's path."""

import argparse
import dataclasses as dc
import re
import typing

#: One dot-separated piece of a --set key: a name (or a list index), then ``[i]`` indices.
_PIECE = re.compile(r"([^.\[\]\s=]*)((?:\[\d+\])*)")


def _clip(text, limit=120) -> str:
    text = str(text)
    return text if len(text) <= limit else text[:limit - 3] + "..."


@dc.dataclass(frozen=True)
class Overlay:
    """One overlay as given: ``kind`` "set" (``text`` is ``KEY=VALUE``) or "text" (a
    YAML mapping); ``flag``: the option it came from."""
    kind: str
    text: str
    flag: str

    @property
    def label(self) -> str:
        return f"{self.flag} {_clip(self.text)}" if self.kind == "set" else self.flag


def key_parts(key: str):
    """``"train[0].hour"`` (or ``"train.0.hour"``) -> ``["train", 0, "hour"]``; a
    ValueError for a key that is not of that form."""
    parts = []
    for piece in key.split("."):
        match = _PIECE.fullmatch(piece)
        if not match or not piece:
            raise ValueError(f"'{_clip(key)}' is not a dotted key (e.g. guard.check_starts "
                             f"or train[0].hour)")
        name, indices = match.groups()
        if name:
            parts.append(int(name) if name.isdigit() else name)
        parts += [int(i) for i in re.findall(r"\d+", indices)]
    if not parts or isinstance(parts[0], int):
        raise ValueError(f"'{_clip(key)}' is not a dotted key (e.g. guard.check_starts "
                         f"or train[0].hour)")
    return parts


def set_argument(text: str) -> Overlay:
    """argparse type of ``--set``: ``KEY=VALUE`` with a well-formed key."""
    key, sep, _ = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"'{_clip(text)}' is not KEY=VALUE (e.g. "
                                         f"grid=[5,3,5])")
    try:
        key_parts(key.strip())
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return Overlay("set", text, "--set")


def text_argument(flag: str):
    def parse(text: str) -> Overlay:
        return Overlay("text", text, flag)
    parse.__name__ = "YAML text"
    return parse


#: ``--set``'s example in the help of a command reading a scenario file, a run file, or
#: either.
SET_EXAMPLES = {"scenario": "controller.speed=3.0", "run": "grid=[5,3,5]",
                "scenario or run": "controller.speed=3.0 (in a run file: "
                                   "scenario.controller.speed=3.0)"}


def add_overlay_arguments(parser, what="scenario"):
    """``--set`` and ``--scenario-text`` (spelt ``--scenario_text`` too, as Drake's
    tools do; for a run file, ``what`` "run" or "scenario or run", also ``--run-text``),
    all into ``args.overlays`` in the order given; an overlay's errors name the flag
    it was given as."""
    run = "run" in what.split()
    parser.add_argument("--set", dest="overlays", action="append", type=set_argument,
                        metavar="KEY=VALUE",
                        help=f"change one field of the {what} file, e.g. --set "
                             f"{SET_EXAMPLES[what]} (dotted keys, list items by index, VALUE "
                             f"read as YAML; repeatable; checked as the file is)")
    example = ("{guard: {check_starts: 0}}" if what == "run" else "{controller: {speed: 3.0}}")
    parser.add_argument("--scenario-text", "--scenario_text", dest="overlays",
                        action="append", type=text_argument("--scenario-text"),
                        metavar="YAML",
                        help=f"a YAML mapping merged into the {what} file (mappings key by "
                             f"key, other values replaced), e.g. '{example}'; repeatable")
    if run:
        parser.add_argument("--run-text", "--run_text", dest="overlays", action="append",
                            type=text_argument("--run-text"), metavar="YAML",
                            help="the same as --scenario-text, for a run file")


class Overlays:
    """The overlays of one command, as `reachwatch.diagrams.load_scenario`'s ``edit``."""

    def __init__(self, overlays):
        self.overlays = list(overlays or [])

    def __bool__(self):
        return bool(self.overlays)

    @property
    def where(self) -> str:
        return _clip("with " + " ".join(o.label for o in self.overlays), 300)

    def apply(self, raw, schema, root):
        """``raw`` with the overlays applied in order. ``schema``: the data's schema, or
        a function of the data so far returning it (an overlay that names another
        application gives the overlays after it that application's schema)."""
        schema_of = (lambda _: schema) if isinstance(schema, type) else schema
        for overlay in self.overlays:
            if overlay.kind == "set":
                raw = _apply_set(raw, overlay, schema_of(raw), root)
            else:
                raw = _apply_text(raw, overlay, schema_of, root)
        return raw


def _read(text: str, label: str):
    from reachwatch.diagrams.scenario import read_yaml
    return read_yaml(text, label, drake=False)


def _unwrap(schema):
    """``Optional[T]`` -> ``T``; anything else as it is."""
    if typing.get_origin(schema) is typing.Union:
        args = [a for a in typing.get_args(schema) if a is not type(None)]
        return args[0] if len(args) == 1 else schema
    return schema


def _type_name(schema) -> str:
    return getattr(schema, "__name__", str(schema).replace("typing.", ""))


def _step(schema, part, path: str, label: str):
    """The schema of ``part`` inside ``schema`` (at ``path``), or a ValueError."""
    from reachwatch.diagrams.scenario import ScenarioError
    schema = _unwrap(schema)
    origin = typing.get_origin(schema)
    if dc.is_dataclass(schema):
        hints = typing.get_type_hints(schema)
        if part not in hints or part not in {f.name for f in dc.fields(schema)}:
            raise ScenarioError(f"{label}: {path}.{_clip(part, 60)}: unknown field of "
                                f"{schema.__name__}; known fields: "
                                f"{', '.join(f.name for f in dc.fields(schema))}")
        return hints[part]
    if origin is dict:
        return typing.get_args(schema)[1]
    if origin is list:
        if not isinstance(part, int):
            raise ScenarioError(f"{label}: {path} is a list; '{_clip(part, 60)}' is not an "
                                f"index (write {path}[0] or {path}.0)")
        return typing.get_args(schema)[0]
    raise ScenarioError(f"{label}: {path} is a {_type_name(schema)}, not a mapping or a "
                        f"list; it has no '{_clip(part, 60)}'")


def _path(root: str, parts) -> str:
    return root + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in parts)


def _apply_set(raw, overlay: Overlay, schema, root):
    from reachwatch.diagrams.scenario import ScenarioError
    key, _, value = overlay.text.partition("=")
    parts = key_parts(key.strip())
    label = overlay.label
    value = _read(value, label)
    node, node_schema = raw, schema
    for i, part in enumerate(parts):
        path = _path(root, parts[:i])
        node_schema = _step(node_schema, part, path, label)
        last = i == len(parts) - 1
        if isinstance(part, int):
            if not isinstance(node, list) or part >= len(node):
                size = len(node) if isinstance(node, list) else 0
                raise ScenarioError(f"{label}: {path} has {size} item"
                                    f"{'' if size == 1 else 's'} in the file; no index {part}")
        elif not isinstance(node, dict):        # e.g. a list item that is not a mapping
            raise ScenarioError(f"{label}: {path} is not a mapping in the file")
        if last:
            node[part] = value
        else:
            if isinstance(part, str) and not isinstance(node.get(part), (dict, list)):
                node[part] = {}                 # missing (or null): made
            node = node[part]
    return raw


def _apply_text(raw, overlay: Overlay, schema_of, root):
    """``raw`` with the text overlay merged in, checked against ``schema_of`` the data
    with the overlay's own top-level keys (a text naming another application is checked
    against that application's schema)."""
    from reachwatch.diagrams.scenario import ScenarioError
    data = _read(overlay.text, overlay.label)
    if data is None:
        return raw
    if not isinstance(data, dict):
        raise ScenarioError(f"{overlay.label}: expected a YAML mapping such as "
                            f"'{{horizon: 4.0}}', got {type(data).__name__}")
    schema = schema_of({**raw, **data} if isinstance(raw, dict) else data)
    return _merge(raw, data, schema, root, overlay.label)


def _merge(base, data, schema, path, label):
    """``data`` merged into ``base`` (mappings key by key, anything else replaced),
    every key of a dataclass's mapping checked to be one of its fields."""
    schema = _unwrap(schema)
    if not isinstance(data, dict):
        return data
    if not (dc.is_dataclass(schema) or typing.get_origin(schema) is dict):
        return data                 # a mapping where none goes: the schema check says so
    merged = dict(base) if isinstance(base, dict) else {}
    for key, value in data.items():
        child = _step(schema, key, path, label)
        merged[key] = _merge(merged.get(key), value, child, f"{path}.{_clip(key, 60)}", label)
    return merged
