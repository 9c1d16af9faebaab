"""The TaxiNet closed loop as a sweepable system: its probes, factories and sweeps."""

import copy
import functools
from pathlib import Path

from reachwatch.diagrams import (CONTROL_PORT, DETECTOR, ESTIMATE_PORT, PLANT, REFERENCE_TAXINET,
                                 make_closed_loop_diagram, make_guarded_diagram)
from reachwatch.diagrams.scenario import InitialState, PipelineConfig, Scenario
from reachwatch.reach import Grid, Probe, SweepTable, sweep, sweep_key

#: What a taxi sweep reads: the steering and TaxiNet's estimate.
TAXI_PROBE = Probe(plant=PLANT, control_port=CONTROL_PORT, extra_ports=(ESTIMATE_PORT,))
#: What the guarded sweep reads: steering, TaxiNet estimate and detector score.
GUARDED_PROBE = Probe(plant=PLANT, control_port=CONTROL_PORT,
                      extra_ports=(ESTIMATE_PORT, f"{DETECTOR}.score"))


def resolved(scenario):
    """A copy of ``scenario`` whose controller checkpoint is an absolute path."""
    scenario = copy.deepcopy(scenario)
    scenario.controller.checkpoint = str(Path(scenario.controller.checkpoint
                                              or REFERENCE_TAXINET).resolve())
    if scenario.pipeline.detector:
        scenario.pipeline.detector = str(Path(scenario.pipeline.detector).resolve())
    return scenario


def _sweep_scenario(scenario, guarded=False) -> Scenario:
    """What a swept table depends on, and nothing else: the start state, duration,
    seed and fallback settings are reset (a sweep sets the state and reads ports that
    do not depend on them), the runway is written out in full so a changed catalog
    entry changes the fingerprint, and the checkpoint paths are absolute."""
    scenario = resolved(scenario)
    defaults = Scenario()
    scenario.initial_state, scenario.duration, scenario.seed = (
        InitialState(), defaults.duration, defaults.seed)
    scenario.environment.runway_spec = scenario.environment.spec()
    scenario.pipeline = PipelineConfig(detector=scenario.pipeline.detector if guarded else "")
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
    return sweep_key(_factory(scenario, guarded), grid, GUARDED_PROBE if guarded else TAXI_PROBE,
                     name=_name(scenario, guarded))


def sweep_closed_loop(scenario, grid: Grid, *, cache_dir, executor=None, chunk_size=1024,
                      progress=True) -> SweepTable:
    """Steering (rad) and TaxiNet estimate at every node of ``grid``."""
    return sweep(_factory(scenario), grid, probe=TAXI_PROBE, name=_name(scenario),
                 cache_dir=cache_dir, executor=executor, chunk_size=chunk_size,
                 progress=progress, label=_label(scenario, grid))


def sweep_guarded(scenario, grid: Grid, *, cache_dir, executor=None, chunk_size=1024,
                  progress=True) -> SweepTable:
    """Steering, estimate and detector score at every node (one render per node)."""
    return sweep(_factory(scenario, True), grid, probe=GUARDED_PROBE,
                 name=_name(scenario, True), cache_dir=cache_dir,
                 executor=executor, chunk_size=chunk_size, progress=progress,
                 label=_label(scenario, grid, "guarded "))
