"""``reachwatch guard`` (failure sets with and without the fallback) and the guarded
``reachwatch simulate --pipeline guarded``."""

import json
import time
from pathlib import Path

import numpy as np

from reachwatch.diagrams import (Scenario, initial_state_vector, load_scenario,
                                 make_closed_loop_diagram, make_guarded_diagram, simulate)
from reachwatch.diagrams.plots import plot_guarded_run
from reachwatch.diagrams.replay import meshcat_replay_html
from reachwatch.reach import ValueFunction
from reachwatch.taxi import dynamics_for, guarded_failures, paper_grid, sweep_guarded
from reachwatch.taxi.plots import plot_brt_slices
from reachwatch.systems import STRATEGIES
from reachwatch.systems.files import atomic_write_bytes, cache_root

from .commands import positive_float, positive_int
from .console import log
from .executors import open_executor


def add_parsers(sub):
    g = sub.add_parser("guard", help="failure sets (fraction of grid starts that leave the "
                       "runway within the horizon) under TaxiNet alone and under each "
                       "fallback strategy, from one sweep of the guarded diagram")
    g.add_argument("--scenario", required=True, help="scenario YAML with pipeline.detector")
    g.add_argument("--shape", type=positive_int, nargs=3, default=[41, 41, 41])
    g.add_argument("--horizon", type=positive_float, default=8.0, help="s")
    g.add_argument("--out", required=True)
    g.add_argument("--executor", default="local", help="local | inline | dask://HOST:PORT")
    g.add_argument("--cache", default=None)
    g.set_defaults(func=guard_command)


def failure_sets(scenario, grid, tables, horizon, strategies=STRATEGIES):
    """{"TaxiNet alone" | strategy: boolean failure per grid node (C order)} from the
    swept tables of the guarded diagram."""
    dynamics = dynamics_for(scenario)
    steering = tables["p_controller.steering_angle"]
    score = tables["anomaly_detector.score"]
    kw = dict(horizon=horizon, period=scenario.controller.period)
    out = {"TaxiNet alone": guarded_failures(grid, dynamics, steering, None, **kw)[0]}
    for strategy in strategies:
        out[strategy] = guarded_failures(
            grid, dynamics, steering, score, threshold=scenario.pipeline.threshold,
            strategy=strategy, brake_deceleration=scenario.pipeline.brake_deceleration, **kw)[0]
    return out


def plot_failure_sets(failures, grid, horizon, *, py, path, half_width, title):
    """One BRT-style slice panel per failure set (failing starts grey)."""
    sets = {k: ValueFunction(grid, np.where(v.reshape(grid.shape), -1.0, 1.0), horizon,
                             "rollouts") for k, v in failures.items()}
    return plot_brt_slices(sets, py=py, path=path, half_width=half_width, title=title)


def guard_command(args):
    scenario = load_scenario(args.scenario)
    grid = paper_grid(scenario.environment.half_width, tuple(args.shape))
    with open_executor(args.executor) as executor:
        tables = sweep_guarded(scenario, grid, cache_dir=args.cache or cache_root() / "sweeps",
                               executor=executor)
    started = time.time()
    failures = failure_sets(scenario, grid, tables, args.horizon)
    out = Path(args.out)
    name = scenario.environment.name
    volumes = {k: float(v.mean()) for k, v in failures.items()}
    log.info(f"{name}, grid {list(grid.shape)}, horizon {args.horizon:g} s, detector "
          f"{scenario.pipeline.detector} (threshold {scenario.pipeline.threshold}); "
          f"rollouts {time.time() - started:.1f} s")
    for k, v in volumes.items():
        log.info(f"  failure set ({k}): {100 * v:.2f}% of the grid")
    atomic_write_bytes(out / f"guard_{name}.json", json.dumps(volumes, indent=1).encode())
    plot_failure_sets(failures, grid, args.horizon, py=175.0, path=out / f"guard_{name}.png",
                      half_width=scenario.environment.half_width,
                      title=f"{name}: failing start states (grey)")
    log.info(f"wrote {out / f'guard_{name}.json'} and .png")


def simulate_guarded(scenario: Scenario, out: Path, *, meshcat_html=True):
    """Nominal and guarded runs from the scenario's start; Fig.-6 plot, trajectories
    (.npz) and a standalone Meshcat replay (.html) of the guarded run. The replay is
    recorded after both runs, by a Meshcat server that is closed once the HTML is
    written (`meshcat_replay_html`)."""
    x0 = initial_state_vector(scenario.initial_state)
    B = scenario.environment.half_width
    if not scenario.pipeline.detector:
        raise ValueError("pipeline.detector: the guarded pipeline needs a detector checkpoint")
    diagrams = make_closed_loop_diagram(scenario), make_guarded_diagram(scenario)  # inputs load
    nominal, guarded = (simulate(d, initial_state=x0, duration=scenario.duration, half_width=B)
                        for d in diagrams)
    name = f"{scenario.environment.name}_{scenario.pipeline.strategy}"
    paths = [plot_guarded_run(nominal, guarded, half_width=B, path=out / f"guarded_{name}.png",
                              title=f"{scenario.environment.name}: TaxiNet alone "
                                    f"{'fails' if nominal.failed else 'stays on'}; guarded "
                                    f"({scenario.pipeline.strategy}) "
                                    f"{'fails' if guarded.failed else 'stays on'}")]
    np.savez(out / f"guarded_{name}.npz", nominal_state=nominal.state, state=guarded.state,
             speed=guarded.speed, anomaly=guarded.anomaly, time=guarded.time)
    paths.append(out / f"guarded_{name}.npz")
    if meshcat_html:
        html = meshcat_replay_html(scenario, guarded.time, guarded.state)
        paths.append(atomic_write_bytes(out / f"guarded_{name}.html", html.encode()))
    return nominal, guarded, paths
