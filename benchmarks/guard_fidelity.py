"""Do the guard's table rollouts say what the real loop does? For one guarded scenario
(an environment, a detector and its threshold): the tables of the guarded sweep
rolled out from seeded on-runway starts, with the detector's score interpolated
between nodes and with the fitted noise of its variation between nodes
(`reach.score_noise`), beside the real Drake loops (rendering every tick) from the
same starts, each fallback with 95 % Wilson intervals.

The noise is fitted on separate calibration runs of the controller alone (their own
seed), never on the starts it is checked on. Real runs and sweeps are cached by
content under ``--cache`` (a re-run is free, a killed one resumes).

    python benchmarks/guard_fidelity.py --scenario S.yaml [--shape 21 11 21]
        [--fallbacks brake] [--starts 200] [--seed 2000] [--calibration-starts 20]
        [--calibration-seed 4000] [--noise-seeds 5] [--mission-limit 3] [--cache DIR]

``S.yaml`` is a scenario file with ``monitor: {detector: ..., threshold: ...}``.
"""

import argparse
import time
from pathlib import Path

import numpy as np

from reachwatch.diagrams import load_scenario
from reachwatch.pipeline.executors import open_executor
from reachwatch.reach.liveness import liveness_figures, percent
from reachwatch.systems.files import cache_root
from reachwatch.taxi import (UNGUARDED, fallback_rollouts, on_runway_starts, paper_grid,
                             real_missions, resolved, sweep_guarded)
from reachwatch.taxi.fidelity import real_score_noise
from reachwatch.taxi.guarded import SCORE_PORT


def row(name, figures):
    same = figures.get("same_distance_failure_set")
    cut = figures.get("same_distance_failure_cut")
    return (f"{name:34s} alone fails {percent(figures['alone_failure_set']):22s} guarded fails "
            f"(same distance) {percent(same) if same else '-':22s} cut "
            f"{100 * cut if cut is not None else float('nan'):4.0f} %  ended stopped "
            f"{percent(figures['ended_stopped']):22s} needless stops "
            f"{percent(figures['needless_stops']):22s} flagged ticks "
            f"{100 * figures['flagged_ticks']:3.0f} %")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", required=True, help="scenario file with a monitor")
    p.add_argument("--shape", type=int, nargs=3, default=[21, 11, 21])
    p.add_argument("--fallbacks", default="brake", help="comma-separated fallback names")
    p.add_argument("--starts", type=int, default=200)
    p.add_argument("--seed", type=int, default=2000)
    p.add_argument("--calibration-starts", type=int, default=20)
    p.add_argument("--calibration-seed", type=int, default=4000)
    p.add_argument("--noise-seeds", type=int, default=5)
    p.add_argument("--mission-limit", type=float, default=3.0)
    p.add_argument("--cache", default=None, help="sweep and rollout cache (default: the user cache)")
    p.add_argument("--executor", default="local")
    args = p.parse_args()
    scenario = resolved(load_scenario(args.scenario))
    if not scenario.monitor.detector:
        p.error(f"{args.scenario} has no monitor.detector: nothing to guard with")
    fallbacks = [f for f in args.fallbacks.split(",") if f]
    cache = cache_root() if args.cache is None else Path(args.cache)
    B, horizon = scenario.environment.half_width, float(scenario.duration)
    grid = paper_grid(B, tuple(args.shape))
    starts = on_runway_starts(grid, args.starts, args.seed, half_width=B)
    calibration = on_runway_starts(grid, args.calibration_starts, args.calibration_seed,
                                   half_width=B)
    started = time.perf_counter()
    with open_executor(args.executor) as executor:
        tables = sweep_guarded(scenario, grid, cache_dir=cache / "sweeps", executor=executor)
        noise, fit = real_score_noise(scenario, grid, tables[SCORE_PORT], calibration,
                                      duration=horizon, cache_dir=cache / "outcomes",
                                      executor=executor)
        real = {f: real_missions(scenario, starts, fallback=None if f == UNGUARDED else f,
                                 duration=horizon, mission_limit=args.mission_limit,
                                 cache_dir=cache / "outcomes", executor=executor)
                for f in [UNGUARDED, *fallbacks]}
    print(f"guard fidelity: {scenario.environment.name}, detector threshold "
          f"{scenario.monitor.threshold:.3g}, grid {args.shape}, {args.starts} starts (seed "
          f"{args.seed}), horizon {horizon:g} s, same distance up to {args.mission_limit:g} x "
          f"the horizon ({time.perf_counter() - started:.0f} s)")
    print(f"score noise fitted on {fit['runs']} calibration runs of the controller alone (seed "
          f"{args.calibration_seed}, {fit['ticks']} ticks): mean {noise.mean:+.3f} and sigma "
          f"{noise.sigma:.3f} (logit), correlation length {noise.length:.2f} m")
    plain = fallback_rollouts(scenario, grid, tables, horizon, fallbacks, starts=starts,
                              mission_limit=args.mission_limit)
    noisy = [fallback_rollouts(scenario, grid, tables, horizon, fallbacks, starts=starts,
                               mission_limit=args.mission_limit, score_noise=noise, seed=seed,
                               alone=plain[UNGUARDED])
             for seed in range(args.noise_seeds)]
    for f in fallbacks:
        print(f"\n{f}:")
        print(row("tables, interpolated score", liveness_figures(plain[UNGUARDED], plain[f])))
        figures = [liveness_figures(plain[UNGUARDED], n[f]) for n in noisy]
        for seed, fig in enumerate(figures):
            print(row(f"tables + score noise, seed {seed}", fig))
        mean = {k: np.mean([fig[k]["rate"] for fig in figures])
                for k in ("same_distance_failure_set", "ended_stopped", "needless_stops")}
        print(f"{'tables + score noise, mean':34s} guarded fails (same distance) "
              f"{100 * mean['same_distance_failure_set']:.1f} %, ended stopped "
              f"{100 * mean['ended_stopped']:.1f} %, needless stops "
              f"{100 * mean['needless_stops']:.1f} %")
        print(row("real loop", liveness_figures(real[UNGUARDED], real[f])))


if __name__ == "__main__":
    main()
