"""``reachwatch graph``: the Graphviz graph of the loop a scenario or run file describes.

``--loop`` picks it: ``closed`` (the camera, the controller and the plant, as
``simulate`` and the sweeps run it), ``guarded`` (that loop watched by the monitor,
with the fallback switch between controller and plant, as the guard stage runs it) or
``world`` (the plant and camera alone, open loop). The default is the loop the file
describes: ``guarded`` when it names a detector checkpoint (``monitor.detector``), else
``closed``. A run file's loop is that of its ``application`` (the taxi by default),
built by the function a run's sweeps build it with, so the graph is the diagram that
is simulated."""

from .commands import add_loop_source_arguments, check_detector, count, loop_scenario
from .console import log

#: What ``--loop`` takes, and the file each is written to (in ``--out``).
LOOPS = {"closed": "closed_loop", "guarded": "guarded_loop", "world": "world"}


def add_parsers(sub):
    g = sub.add_parser("graph", help="export the graph of the loop a scenario or run file "
                       "describes: the closed loop, guarded when it names a detector "
                       "(.dot; .svg/.png with graphviz)")
    add_loop_source_arguments(g)
    g.add_argument("--loop", choices=tuple(LOOPS), help="closed: camera, controller and "
                   "plant; guarded: with the monitor (the detector of monitor.detector) and "
                   "the fallback switch; world: plant and camera alone, no controller (runs "
                   "no controller code). Default: guarded when the file names a detector, "
                   "else closed")
    g.add_argument("--out", required=True, help="output folder: LOOP.dot (closed_loop, "
                   "guarded_loop or world), and .svg/.png with graphviz")
    g.add_argument("--max-depth", type=count, default=2, help="Graphviz nesting depth "
                   "(default: %(default)s)")
    g.set_defaults(func=graph)


def graph(args):
    from reachwatch.diagrams import export_graph

    from .commands import output_folder
    # building the controller imports its factory; the world has none
    scenario, application, where, key = loop_scenario(args, controller=args.loop != "world")
    loop = args.loop or ("guarded" if scenario.monitor.detector else "closed")
    if loop == "guarded":
        check_detector(scenario, where, key)
    diagram = loop_diagram(scenario, loop, application)
    out = output_folder(args.out)
    for path in export_graph(diagram, out / LOOPS[loop], max_depth=args.max_depth):
        log.info(path)


def loop_diagram(scenario, loop: str, application: str = None):
    """The Drake diagram of ``loop`` ("closed", "guarded" or "world") of ``scenario``
    in the application ``application`` (a run file's ``application``; None: the
    default, `DEFAULT_APPLICATION`): the loop is the application's ``loop_diagram``,
    built as a run's sweeps build it (`reachwatch.reach.application.build_loop`);
    "world" is the default's (the taxi's) alone."""
    from reachwatch.reach.application import ApplicationRef, build_loop, load_application
    from .slot_defaults import DEFAULT_APPLICATION, is_default_application
    application = application or DEFAULT_APPLICATION
    if loop == "world":
        if not is_default_application(load_application(application)):
            raise ValueError(f"--loop world draws the taxi's open-loop world; the "
                             f"application '{application}' has none (draw its closed "
                             f"loop: --loop closed)")
        from reachwatch.diagrams import make_world_diagram
        return make_world_diagram(scenario)
    return build_loop(ApplicationRef(application), scenario, loop == "guarded")
