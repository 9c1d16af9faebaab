"""``reachwatch guard``: failure sets with and without the fallback."""

import json
import time
from pathlib import Path

from reachwatch.diagrams import load_scenario
from reachwatch.systems.files import atomic_write_bytes, cache_root
from reachwatch.taxi import failure_sets, paper_grid, sweep_guarded
from reachwatch.taxi.plots import plot_failure_sets

from .commands import positive_float, positive_int
from .console import log
from .executors import open_executor


def add_parsers(sub):
    g = sub.add_parser("guard", help="failure sets (fraction of grid starts that leave the "
                       "runway within the horizon) under the controller alone and under each "
                       "fallback strategy, from one sweep of the guarded diagram")
    g.add_argument("--scenario", required=True, help="scenario YAML with pipeline.detector")
    g.add_argument("--shape", type=positive_int, nargs=3, default=[41, 41, 41])
    g.add_argument("--horizon", type=positive_float, default=8.0, help="s")
    g.add_argument("--out", required=True)
    g.add_argument("--executor", default="local", help="local | inline | dask://HOST:PORT")
    g.add_argument("--cache", default=None)
    g.set_defaults(func=guard_command)


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
          f"{scenario.monitor.detector} (threshold {scenario.monitor.threshold}); "
          f"rollouts {time.time() - started:.1f} s")
    for k, v in volumes.items():
        log.info(f"  failure set ({k}): {100 * v:.2f}% of the grid")
    atomic_write_bytes(out / f"guard_{name}.json", json.dumps(volumes, indent=1).encode())
    plot_failure_sets(failures, grid, args.horizon, py=175.0, path=out / f"guard_{name}.png",
                      half_width=scenario.environment.half_width,
                      title=f"{name}: failing start states (grey)")
    log.info(f"wrote {out / f'guard_{name}.json'} and .png")
