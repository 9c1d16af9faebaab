"""The taxi closed loop (any controller on the taxi plant) as a sweepable system: its
probes, factories and sweeps."""

import copy
import functools
from pathlib import Path

from reachwatch.diagrams import (CONTROL_PORT, DETECTOR, ESTIMATE_PORT, PLANT, REFERENCE_TAXINET,
                                 make_closed_loop_diagram, make_controller,
                                 make_guarded_diagram)
from reachwatch.diagrams.controller import has_estimate
from reachwatch.diagrams.scenario import Scenario
from reachwatch.reach import Grid, Probe, SweepTable, sweep, sweep_key
from reachwatch.reach.application import sweep_scenario
from reachwatch.reach.refine import refine_adaptively
from reachwatch.reach.robust import control_bounds

def taxi_probe(scenario, *, guarded=False) -> Probe:
    """What a taxi sweep reads: the steering, the controller's estimate when it declares
    one, and (``guarded``) the detector's score."""
    extra = (ESTIMATE_PORT,) if has_estimate(make_controller(scenario.controller)) else ()
    return Probe(plant=PLANT, control_port=CONTROL_PORT,
                 extra_ports=extra + ((f"{DETECTOR}.score",) if guarded else ()))


def _absolute_factory(spec: str) -> str:
    target, sep, name = spec.rpartition(":")
    return f"{Path(target).resolve()}:{name}" if sep and target.endswith(".py") else spec


def resolved(scenario):
    """A copy of ``scenario`` whose file paths (checkpoints, a controller factory's
    file) are absolute; TaxiNet's empty checkpoint becomes the shipped one."""
    scenario = copy.deepcopy(scenario)
    controller = scenario.controller
    controller.factory = _absolute_factory(controller.factory)
    if controller.checkpoint or not controller.factory:
        controller.checkpoint = str(Path(controller.checkpoint or REFERENCE_TAXINET).resolve())
    if scenario.monitor.detector:
        scenario.monitor.detector = str(Path(scenario.monitor.detector).resolve())
    return scenario


def _sweep_scenario(scenario, guarded=False) -> Scenario:
    """`reach.application.sweep_scenario` of ``scenario`` with its checkpoint paths
    absolute and its runway written out in full, so a changed catalog entry changes the
    fingerprint."""
    scenario = sweep_scenario(resolved(scenario), guarded)
    scenario.environment.runway_spec = scenario.environment.spec()
    return scenario


def _factory(scenario, guarded=False):
    make = make_guarded_diagram if guarded else make_closed_loop_diagram
    return functools.partial(make, _sweep_scenario(scenario, guarded))


def _name(scenario, guarded=False):
    return scenario.environment.name + ("_guarded" if guarded else "")


def _label(scenario, grid, what=""):
    return f"{what}{scenario.environment.name} {'x'.join(map(str, grid.shape))}"


def taxi_sweep_key(scenario, grid: Grid, *, guarded=False) -> str:
    """The cache folder of ``scenario``'s (guarded) sweep over ``grid``: the environment
    name, the grid shape and the content fingerprint of what the table depends on."""
    return sweep_key(_factory(scenario, guarded), grid, taxi_probe(scenario, guarded=guarded),
                     name=_name(scenario, guarded))


def sweep_closed_loop(scenario, grid: Grid, *, cache_dir, executor=None, chunk_size=1024,
                      progress=True) -> SweepTable:
    """Steering (rad) and the controller's estimate (if any) at every node of ``grid``."""
    return sweep(_factory(scenario), grid, probe=taxi_probe(scenario), name=_name(scenario),
                 cache_dir=cache_dir, executor=executor, chunk_size=chunk_size,
                 progress=progress, label=_label(scenario, grid))


def sweep_guarded(scenario, grid: Grid, *, cache_dir, executor=None, chunk_size=1024,
                  progress=True) -> SweepTable:
    """Steering, estimate and detector score at every node (one render per node)."""
    return sweep(_factory(scenario, True), grid, probe=taxi_probe(scenario, guarded=True),
                 name=_name(scenario, True), cache_dir=cache_dir,
                 executor=executor, chunk_size=chunk_size, progress=progress,
                 label=_label(scenario, grid, "guarded "))


def refine_closed_loop(scenario, table: SweepTable, *, solve, levels: int, band: float,
                       variation: float = None, cache_dir, executor=None, progress=True):
    """`reach.refine.refine_adaptively` of ``scenario``'s swept ``table`` (from
    `sweep_closed_loop`): ``levels`` times, render the new nodes of the cells where the
    BRT's boundary passes within ``band`` m or the steering varies by more than
    ``variation`` rad, and solve again with ``solve(table)``."""
    return refine_adaptively(_factory(scenario), table, probe=taxi_probe(scenario), solve=solve,
                             levels=levels, band=band, variation=variation,
                             cache_dir=cache_dir, executor=executor, progress=progress,
                             label=scenario.environment.name)


def steering_bounds(table: SweepTable, min_spread_deg, *, neighbourhood: int = 3):
    """`reach.robust.control_bounds` of the steering of a swept ``table``."""
    return control_bounds(table, CONTROL_PORT, min_spread_deg, neighbourhood=neighbourhood)
