"""``reachwatch guard``: failure sets with and without the fallback."""

import json
import time
from pathlib import Path

from reachwatch.diagrams import load_scenario
from reachwatch.systems.files import atomic_write_bytes, cache_root
from reachwatch.reach.liveness import liveness_figures, percent
from reachwatch.systems import fallback_parts
from reachwatch.taxi import UNGUARDED, fallback_rollouts, paper_grid, sweep_guarded
from reachwatch.taxi.guarded import tradeoff_curves, tradeoff_row
from reachwatch.taxi.plots import plot_failure_sets, plot_tradeoff

from .commands import positive_float, positive_int
from .console import log
from .executors import open_executor


def add_parsers(sub):
    g = sub.add_parser("guard", help="failure sets (fraction of grid starts that leave the "
                       "runway within the horizon) under the controller alone and under each "
                       "fallback, with their liveness (starts ended stopped, needless stops, "
                       "distance travelled, ticks flagged) and the trade-off as the detector "
                       "threshold sweeps, from one sweep of the guarded diagram")
    g.add_argument("--scenario", required=True, help="scenario YAML with pipeline.detector")
    g.add_argument("--shape", type=positive_int, nargs=3, default=[41, 41, 41])
    g.add_argument("--horizon", type=positive_float, default=8.0, help="s")
    g.add_argument("--fallbacks", nargs="+", type=_fallback,
                   default=["slow_down", "brake", "slow_down+dead_reckoning", "slow_down+oracle"],
                   help="speed strategy, optionally '+' the steering while flagged "
                        "(dead_reckoning; oracle is privileged, a reference only)")
    g.add_argument("--tradeoff-points", type=positive_int, default=9,
                   help="detector thresholds on the trade-off curve")
    g.add_argument("--out", required=True)
    g.add_argument("--executor", default="local", help="local | inline | dask://HOST:PORT")
    g.add_argument("--cache", default=None)
    g.set_defaults(func=guard_command)


def _fallback(text):
    fallback_parts(text)        # a clear error for a misspelt name
    return text


def guard_command(args):
    scenario = load_scenario(args.scenario)
    grid = paper_grid(scenario.environment.half_width, tuple(args.shape))
    with open_executor(args.executor) as executor:
        tables = sweep_guarded(scenario, grid, cache_dir=args.cache or cache_root() / "sweeps",
                               executor=executor)
    started = time.time()
    runs = fallback_rollouts(scenario, grid, tables, args.horizon, args.fallbacks)
    out = Path(args.out)
    name = scenario.environment.name
    volumes = {k: float(v.failed.mean()) for k, v in runs.items()}
    liveness = {f: liveness_figures(runs[UNGUARDED], runs[f]) for f in args.fallbacks}
    curves = tradeoff_curves(scenario, grid, tables, args.horizon, args.fallbacks,
                             args.tradeoff_points)
    log.info(f"{name}, grid {list(grid.shape)}, horizon {args.horizon:g} s, detector "
             f"{scenario.monitor.detector} (threshold {scenario.monitor.threshold}); "
             f"rollouts {time.time() - started:.1f} s")
    log.info(f"  controller alone: failure set {100 * volumes[UNGUARDED]:.2f}% of the grid")
    for f, v in liveness.items():
        log.info(f"  {f}: failure set {percent(v['failure_set'])}, ended stopped "
                 f"{percent(v['ended_stopped'])}, needless stops {percent(v['needless_stops'])}, "
                 f"distance {v['distance_ratio']:.2f} x alone, ticks flagged "
                 f"{100 * v['flagged_ticks']:.1f}%")
    atomic_write_bytes(out / f"guard_{name}.json", json.dumps(
        {"volumes": volumes, "liveness": liveness, "tradeoff": curves}, indent=1).encode())
    plot_failure_sets({k: v.failed for k, v in runs.items()}, grid, args.horizon, py=175.0,
                      path=out / f"guard_{name}.png", half_width=scenario.environment.half_width,
                      title=f"{name}: failing start states (grey)")
    plot_tradeoff(curves, alone=volumes[UNGUARDED], path=out / f"tradeoff_{name}.png",
                  operating={f: tradeoff_row(v) for f, v in liveness.items()},
                  title=f"{name}: failures against liveness as the threshold sweeps")
    log.info(f"wrote {out / f'guard_{name}.json'}, guard_{name}.png and tradeoff_{name}.png")
