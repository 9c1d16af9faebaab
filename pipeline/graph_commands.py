"""``reachwatch graph``: the Graphviz graph of the loop a scenario or run file describes.

``--loop`` picks it: ``closed`` (the camera, the controller and the plant, as
``simulate`` and the sweeps run it), ``guarded`` (that loop watched by the monitor,
with the fallback switch between controller and plant, as the guard stage runs it) or
``world`` (the plant and camera alone, open loop). The default is the loop the file
describes: ``guarded`` when it names a detector checkpoint (``monitor.detector``), else
``closed``. A run file's loop is that of its ``application`` (the taxi by default),
built by the function a run's sweeps build it with, so the graph is the diagram that
is simulated."""

import argparse
import copy

from .commands import count
from .console import log
from .overlays import add_overlay_arguments

#: What ``--loop`` takes, and the file each is written to (in ``--out``).
LOOPS = {"closed": "closed_loop", "guarded": "guarded_loop", "world": "world"}


def add_parsers(sub):
    g = sub.add_parser("graph", help="export the graph of the loop a scenario or run file "
                       "describes: the closed loop, guarded when it names a detector "
                       "(.dot; .svg/.png with graphviz)")
    source = g.add_mutually_exclusive_group()
    source.add_argument("--scenario", help="scenario YAML, or a run file (read as one when "
                        "it has a run file's keys, e.g. grid or train); default: built-in "
                        "defaults")
    source.add_argument("--run", metavar="RUN_FILE", help="run file (as 'reachwatch run "
                        "--scenario' takes): its scenario, in its first held-out environment "
                        "(--env picks another)")
    add_overlay_arguments(g, "scenario or run")
    g.add_argument("--loop", choices=tuple(LOOPS), help="closed: camera, controller and "
                   "plant; guarded: with the monitor (the detector of monitor.detector) and "
                   "the fallback switch; world: plant and camera alone, no controller (runs "
                   "no controller code). Default: guarded when the file names a detector, "
                   "else closed")
    g.add_argument("--env", metavar="NAME", help="with a run file: the environment (as the "
                   "report names it, e.g. KSFO_21h_overcast)")
    g.add_argument("--out", required=True, help="output folder: LOOP.dot (closed_loop, "
                   "guarded_loop or world), and .svg/.png with graphviz")
    g.add_argument("--max-depth", type=count, default=2, help="Graphviz nesting depth "
                   "(default: %(default)s)")
    g.set_defaults(func=graph)


def graph(args):
    from reachwatch.diagrams import export_graph

    from .commands import output_folder
    scenario, application, where, key = loop_scenario(args)
    loop = args.loop or ("guarded" if scenario.monitor.detector else "closed")
    if loop == "guarded" and not scenario.monitor.detector:
        raise ValueError(f"{where}: {key} is not set; the guarded loop needs a detector "
                         f"checkpoint (train one with 'reachwatch evaluate'; --set {key}=PATH)")
    diagram = loop_diagram(scenario, loop, application)
    out = output_folder(args.out)
    for path in export_graph(diagram, out / LOOPS[loop], max_depth=args.max_depth):
        log.info(path)


def loop_diagram(scenario, loop: str, application: str = ""):
    """The Drake diagram of ``loop`` ("closed", "guarded" or "world") of ``scenario``
    in the application ``application`` (a run file's ``application``; "" = the taxi):
    the loop is the application's ``loop_diagram``, built as a run's sweeps build it
    (`reachwatch.reach.application.build_loop`)."""
    from reachwatch.diagrams.checkpoints import checkpoint_kind
    from reachwatch.reach.application import ApplicationRef, build_loop
    if loop == "world":
        if application:
            raise ValueError(f"--loop world draws the taxi's open-loop world; the "
                             f"application '{application}' has none (draw its closed "
                             f"loop: --loop closed)")
        from reachwatch.diagrams import make_world_diagram
        return make_world_diagram(scenario)
    if loop == "guarded":
        checkpoint_kind(scenario.monitor.detector)       # a wrong file: one line
    return build_loop(ApplicationRef(application), scenario, loop == "guarded")


def loop_scenario(args):
    """``(scenario, application, where, key)``: the `Scenario` the graph is built from
    (a run file's in its environment), the application it is a loop of, how errors
    name the file, and the key of its detector."""
    from .commands import scenario_from_args
    controller = args.loop != "world"       # building the controller imports its factory
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
    scenario = scenario_from_args(args, controller=controller)
    return (scenario, "", f"--scenario {path}" if path else "the built-in scenario",
            "monitor.detector")


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
