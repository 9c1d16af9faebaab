"""Implementations of the ``reachwatch`` subcommands (argparse namespaces in, files out)."""

import argparse
import math
from pathlib import Path


from reachwatch.diagrams import (Scenario, StateRenderer, export_graph, write_png,
                                 initial_state_vector, load_scenario, make_world_diagram)
from reachwatch.diagrams.contact_sheet import contact_sheet

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
grid_nodes = number_type(int, 0, True, "a whole number of grid nodes in [1, 401]", most=401)
horizon_seconds = number_type(float, 0.0, True, "a finite number > 0 of at most 120 s", most=120.0)
mission_multiple = number_type(float, 1.0, False, "a multiple of the horizon in [1, 100]", most=100.0)


def scenario_from_args(args) -> Scenario:
    """The ``--scenario`` file, or the built-in defaults when none is given."""
    return load_scenario(args.scenario) if args.scenario else Scenario().validate()


def render(args):
    scenario = scenario_from_args(args)
    out = Path(args.out)
    state = initial_state_vector(scenario.initial_state)
    if args.contact_sheet:
        sheet = contact_sheet(state=state, camera=scenario.camera,
                              progress=lambda it: bar(it, desc="contact sheet"))
        log.info(write_png(out / "contact_sheet.png", sheet))
        return
    image = StateRenderer(environment=scenario.environment, camera=scenario.camera,
                          shadows=scenario.shadows).render(state)
    log.info(write_png(out / f"{scenario.environment.name}.png", image))


def graph(args):
    scenario = scenario_from_args(args)
    diagram = make_world_diagram(scenario)
    for path in export_graph(diagram, Path(args.out) / "world", max_depth=args.max_depth):
        log.info(path)
