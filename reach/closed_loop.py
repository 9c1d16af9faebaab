"""The TaxiNet closed loop as a sweepable system: its factory, cache key, dynamics."""

import copy
import dataclasses as dc
import functools
import hashlib
import json
from pathlib import Path

import numpy as np

from reachwatch.diagrams import (DETECTOR, REFERENCE_TAXINET, file_hash,
                                 make_closed_loop_diagram, make_guarded_diagram, simulate)

from .dynamics import TaxiDynamics
from .grid import Grid
from .sweep import Probe, SweepTable, sweep

SWEEP_FORMAT = 1


def resolved(scenario):
    """A copy of ``scenario`` whose controller checkpoint is an absolute path."""
    scenario = copy.deepcopy(scenario)
    scenario.controller.checkpoint = str(Path(scenario.controller.checkpoint
                                              or REFERENCE_TAXINET).resolve())
    if scenario.pipeline.detector:
        scenario.pipeline.detector = str(Path(scenario.pipeline.detector).resolve())
    return scenario


def sweep_key(scenario, grid: Grid, probe: Probe = Probe()) -> str:
    """Cache key: environment, grid, controller checkpoint hash, image size, gains, ports."""
    scenario = resolved(scenario)
    env = dc.asdict(scenario.environment)
    env["runway_spec"] = dc.asdict(scenario.environment.spec())
    parts = {"format": SWEEP_FORMAT, "environment": env, "grid": grid.key(),
             "checkpoint": file_hash(scenario.controller.checkpoint),
             "image": [scenario.camera.height, scenario.camera.width],
             "camera": dc.asdict(scenario.camera), "shadows": scenario.shadows,
             "gains": [scenario.controller.px_gain, scenario.controller.theta_gain],
             "probe": dc.asdict(probe)}
    if any(port.startswith(DETECTOR + ".") for port in probe.ports):
        parts["detector"] = file_hash(scenario.pipeline.detector)
    digest = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:20]
    return f"{scenario.environment.name}_{'x'.join(map(str, grid.shape))}_{digest}"


def _label(scenario, grid, what=""):
    return f"{what}{scenario.environment.name} {'x'.join(map(str, grid.shape))}"


def sweep_closed_loop(scenario, grid: Grid, *, cache_dir, executor=None, chunk_size=1024,
                      progress=True) -> SweepTable:
    """Steering (rad) and TaxiNet estimate at every node of ``grid``."""
    scenario = resolved(scenario)
    return sweep(functools.partial(make_closed_loop_diagram, scenario), grid,
                 key=sweep_key(scenario, grid), cache_dir=cache_dir, executor=executor,
                 chunk_size=chunk_size, progress=progress, label=_label(scenario, grid))


#: What the guarded sweep reads: steering, TaxiNet estimate and detector score.
GUARDED_PROBE = Probe(extra_ports=("taxinet.estimate", f"{DETECTOR}.score"))


def sweep_guarded(scenario, grid: Grid, *, cache_dir, executor=None, chunk_size=1024,
                  progress=True) -> SweepTable:
    """Steering, estimate and detector score at every node (one render per node)."""
    scenario = resolved(scenario)
    return sweep(functools.partial(make_guarded_diagram, scenario), grid,
                 key=sweep_key(scenario, grid, GUARDED_PROBE), cache_dir=cache_dir,
                 probe=GUARDED_PROBE, executor=executor, chunk_size=chunk_size,
                 progress=progress, label=_label(scenario, grid, "guarded "))


def taxi_dynamics(scenario) -> TaxiDynamics:
    return TaxiDynamics(half_width=scenario.environment.half_width,
                        speed=scenario.controller.speed)


def drake_agreement(scenario, value_function, starts, *, duration=None, progress=None):
    """Runs the real Drake closed loop (rendering in the loop) from each start and
    compares "left the runway" with the BRT verdict ``V(x0) <= 0``. Returns
    ``(agreement, failed, predicted)``."""
    scenario = resolved(scenario)
    B = scenario.environment.half_width
    diagram = make_closed_loop_diagram(scenario)
    context = diagram.CreateDefaultContext()
    duration = duration or value_function.horizon
    predicted = value_function.in_brt(starts)
    failed = []
    for x in (progress(starts) if progress else starts):
        failed.append(abs(x[0]) >= B or simulate(diagram, initial_state=x, duration=duration,
                                                  half_width=B, context=context).failed)
    failed = np.array(failed)
    return float(np.mean(failed == predicted)), failed, predicted
