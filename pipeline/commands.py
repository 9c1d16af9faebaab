"""Implementations of the ``reachwatch`` subcommands (argparse namespaces in, files out).

The command line builds its parser from these modules without drake or torch (so that
``--help`` is quick): each ``*_commands`` module imports only the standard library and
this package's light modules at the top, and its heavy imports inside the functions
that run a command."""

import argparse
import copy
import math
import os
from pathlib import Path

from .console import bar, log


def number_type(kind, least, strict, what, most=math.inf, most_strict=False):
    """An argparse type: a ``kind`` number >= ``least`` (> when ``strict``) and <= ``most``
    (< when ``most_strict``), refused with "'TEXT' is not ``what``" otherwise."""
    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not {what}") from None
        if (not math.isfinite(value) or value < least or (strict and value == least)
                or value > most or (most_strict and value == most)):
            raise argparse.ArgumentTypeError(f"'{text}' is not {what}")
        return value
    parse.__name__ = what
    return parse


#: argparse types that reject bad numbers at parse time, before any work is done.
positive_int = number_type(int, 0, True, "a whole number >= 1")
count = number_type(int, 0, False, "a whole number >= 0")
positive_float = number_type(float, 0.0, True, "a finite number > 0")
non_negative_float = number_type(float, 0.0, False, "a finite number >= 0")
open_share = number_type(float, 0.0, True, "a share in (0, 1)", most=1.0, most_strict=True)
#: Seeds, grid sizes, horizons and mission limits, bounded as a run file bounds them.
seed_number = number_type(int, 0, False, "a seed (a whole number in [0, 2147483647])", most=2 ** 31 - 1)
grid_nodes = number_type(int, 3, False, "a whole number of grid nodes in [3, 401]", most=401)
horizon_seconds = number_type(float, 0.0, True, "a finite number > 0 of at most 120 s", most=120.0)
#: the solved box's bounds, as the run file's ``solved_theta_deg`` and ``solved_py_max``
solved_theta = number_type(float, 28.0, False, "a number of degrees in [28, 180]", most=180.0)
solved_py = number_type(float, 250.0, False, "a finite number of metres >= 250",
                        most=10_000.0)
mission_multiple = number_type(float, 1.0, False, "a multiple of the horizon in [1, 100]", most=100.0)
#: A state's component (``simulate --start``): any finite number.
finite = number_type(float, -math.inf, False, "a finite number")


class RunFileDefault:
    """A flag's default that is the run file's: the value of ``path`` (e.g.
    ``"guard.check_starts"``; several paths: a list of their values) in a run file of
    defaults, passed through ``convert``. Read from the schema's dataclass defaults when
    the command runs (`fill_run_file_defaults`), so that the parser imports no schema
    and the two cannot drift apart; ``--help`` names the field."""

    def __init__(self, path, convert=None):
        self.paths = (path,) if isinstance(path, str) else tuple(path)
        self.convert = convert

    def __str__(self):          # --help imports no schema (nor Drake, nor torch)
        return f"as {' and '.join(self.paths)} in a run file's defaults"

    __repr__ = __str__

    def value(self):
        from .overlays import key_parts
        from .spec import RunSpec
        values = []
        for path in self.paths:
            node = RunSpec()
            for part in key_parts(path):
                node = node[part] if isinstance(part, int) else getattr(node, part)
            values.append(copy.deepcopy(node))
        value = values[0] if len(values) == 1 else values
        return self.convert(value) if self.convert else value


def _declared_bound(path: str):
    """The `Bound` declared for the run-file key ``path`` (``guard.check_starts``), or
    None."""
    import dataclasses as dc
    import typing

    from reachwatch.systems.bounds import bound_of

    from reachwatch.reach.application import load_application

    from .slot_defaults import DEFAULT_APPLICATION
    from .spec import run_file_schema
    # the default application's environments
    schema, field = run_file_schema(load_application(DEFAULT_APPLICATION)), None
    for part in path.split("."):
        fields = {f.name: f for f in dc.fields(schema)} if dc.is_dataclass(schema) else {}
        if part not in fields:
            return None
        field = fields[part]
        hint = typing.get_type_hints(schema)[part]
        schema = next((a for a in (hint, *typing.get_args(hint)) if dc.is_dataclass(a)), hint)
    return bound_of(field)


def _invoked_actions(parser, args):
    """The actions of the (sub)command ``args`` invoked, with the parser that owns each."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = action.choices.get(getattr(args, action.dest, None))
            if chosen is not None:
                yield from _invoked_actions(chosen, args)
        else:
            yield parser, action


def check_run_file_flags(parser, args):
    """Refuse a given flag that sets a run-file key (its default a `RunFileDefault` of
    one key) with a value outside that key's declared bound, as the run file would:
    ``parser.error`` naming the flag and the key (exit 2), before any work."""
    for owner, action in _invoked_actions(parser, args):
        default = action.default
        value = getattr(args, action.dest, default)
        if not isinstance(default, RunFileDefault) or isinstance(value, RunFileDefault) \
                or len(default.paths) != 1 or default.convert is not None or value is None:
            continue
        bound = _declared_bound(default.paths[0])
        if bound is not None:
            try:
                bound.check(default.paths[0], value)
            except ValueError as e:
                owner.error(f"argument {'/'.join(action.option_strings)}: {e}")


def fill_run_file_defaults(args):
    """Replace every `RunFileDefault` left in ``args`` (a flag not given) by its value."""
    for name, value in vars(args).items():
        if isinstance(value, RunFileDefault):
            setattr(args, name, value.value())
    return args


def scenario_from_args(args, schema=None, root="scenario", *, controller=False):
    """The ``--scenario`` file (``schema``: a `Scenario` by default), or the built-in
    defaults when none is given, with the command's overlays (``--set``,
    ``--scenario-text``) applied before it is checked. Loading it runs no code of a
    ``controller.factory``; ``controller``: the command builds the controller, so
    import its factory now (a broken one fails before any work)."""
    from reachwatch.diagrams import Scenario, load_scenario, resolve_factory

    from .overlays import Overlays
    schema = schema or Scenario
    overlays = Overlays(getattr(args, "overlays", None))
    if not args.scenario and not overlays:
        loaded = schema().validate()
    else:
        loaded = load_scenario(args.scenario, data=None if args.scenario else "",
                               schema=schema, root=root, edit=overlays or None)
    if controller:
        resolve_factory((loaded if isinstance(loaded, Scenario) else loaded.scenario)
                        .controller.factory)
    return loaded


def check_detector(scenario, where, key="monitor.detector") -> None:
    """Raise a ValueError when ``scenario`` names no detector checkpoint for the guarded
    loop (at ``key`` of the file ``where`` names), or a file that is not one; cheap, so
    commands call it before their work."""
    from reachwatch.diagrams.checkpoints import checkpoint_kind
    if not scenario.monitor.detector:
        raise ValueError(f"{where}: {key} is not set; the guarded loop needs a detector "
                         f"checkpoint (train one with 'reachwatch evaluate'; --set {key}=PATH)")
    checkpoint_kind(scenario.monitor.detector)


def scenario_words(path) -> str:
    """How errors name a ``--scenario`` file ``path`` (None: the built-in defaults)."""
    return f"--scenario {path}" if path else "the built-in scenario"


def output_folder(path) -> Path:
    """``path`` as a folder the command can write to, made now so that a file standing
    where it goes, or a folder it may not write in, fails before any work (the command
    line reports the `OSError` and exits 2)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    if not os.access(path, os.W_OK | os.X_OK):
        raise PermissionError(13, "Permission denied", str(path))
    return path


def output_file(path) -> Path:
    """``path`` as a file the command can write at its end: not a folder, in a folder
    that is made now and can be written (`output_folder`)."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(21, "Is a directory", str(path))
    output_folder(path.parent)
    return path


def render(args):
    from reachwatch.diagrams import StateRenderer, initial_state_vector, write_png
    from reachwatch.diagrams.contact_sheet import contact_sheet
    scenario = scenario_from_args(args)
    out = output_folder(args.out)
    state = initial_state_vector(scenario.initial_state)
    if args.contact_sheet:
        sheet = contact_sheet(state=state, camera=scenario.camera,
                              progress=lambda it: bar(it, desc="contact sheet"))
        log.info(write_png(out / "contact_sheet.png", sheet))
        return
    image = StateRenderer(environment=scenario.environment, camera=scenario.camera,
                          shadows=scenario.shadows).render(state)
    log.info(write_png(out / f"{scenario.environment.name}.png", image))


def add_loop_source_arguments(parser):
    """``--scenario`` (a scenario or a run file) or ``--run`` (a run file), their
    overlays, and ``--env`` (a run file's environment): the loop of a command that
    reads it with `loop_scenario`."""
    from .overlays import add_overlay_arguments
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--scenario", help="scenario YAML, or a run file (read as one when "
                        "it has a run file's keys, e.g. grid or train); default: built-in "
                        "defaults")
    source.add_argument("--run", metavar="RUN_FILE", help="run file (as 'reachwatch run "
                        "--scenario' takes): its application's loop and scenario, in its "
                        "first held-out environment (--env picks another)")
    add_overlay_arguments(parser, "scenario or run")
    parser.add_argument("--env", metavar="NAME", help="with a run file: the environment (as "
                        "the report names it, e.g. KSFO_21h_overcast)")


def loop_scenario(args, *, controller: bool = True):
    """``(scenario, application, where, key)`` of a command that takes ``--scenario`` (a
    scenario or a run file) or ``--run`` (a run file) with ``--env``: the `Scenario` of
    the loop (a run file's in its environment), the application it is a loop of (its
    spec; a scenario's: `DEFAULT_APPLICATION`), how errors name the file, and the key of
    its detector.
    ``controller``: the command builds the controller, so import its factory now."""
    path = args.run or args.scenario
    if args.run or (args.scenario and is_run_file(args.scenario)):
        from .spec import RunSpec
        spec = scenario_from_args(argparse.Namespace(scenario=path, overlays=args.overlays),
                                  schema=RunSpec, root="run", controller=controller)
        return (run_scenario(spec, args.env, path), spec.application, f"run file {path}",
                "scenario.monitor.detector")
    if args.env:
        raise ValueError("--env picks one of a run file's environments; a scenario names its "
                         "own (set it with --set environment.runway=KSFO, or give a run file "
                         "with --run)")
    from .slot_defaults import DEFAULT_APPLICATION
    scenario = scenario_from_args(args, controller=controller)
    return scenario, DEFAULT_APPLICATION, scenario_words(path), "monitor.detector"


def run_scenario(spec, env_name, path):
    """The run file ``spec``'s scenario in the environment named ``env_name`` (None: its
    first held-out one, whose loops the report draws), as its stages build it."""
    envs = spec.all_environments()
    if env_name is None:
        env = (spec.held_out_environments() or envs)[0]
    else:
        named = [e for e in envs if e.name == env_name]
        if not named:
            from reachwatch.systems.checks import clip
            raise ValueError(clip(f"--env {env_name}: the run file {path} has no such "
                                  f"environment; its environments: "
                                  f"{', '.join(e.name for e in envs)}", 400))
        env = named[0]
    scenario = copy.deepcopy(spec.scenario)
    scenario.environment = env
    return scenario


def is_run_file(path) -> bool:
    """Whether the YAML file ``path`` is a run file: a mapping with a key only a run file
    has (``name``, ``scenario``, ``train``, ``grid``, ...). A file that cannot be read is
    not: loading it as a scenario says why."""
    import dataclasses as dc

    from reachwatch.diagrams import Scenario
    from reachwatch.diagrams.scenario import ScenarioError, read_text_file, read_yaml

    from .spec import RunSpec
    try:
        raw = read_yaml(read_text_file(path), str(path), drake=False)
    except ScenarioError:
        return False
    run_only = {f.name for f in dc.fields(RunSpec)} - {f.name for f in dc.fields(Scenario)}
    return isinstance(raw, dict) and any(k in run_only for k in raw)
