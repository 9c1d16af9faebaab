"""Do the guard's table rollouts say what the real loop does? For one guarded scenario
(an environment, a detector and its threshold): the tables of the guarded sweep
rolled out from seeded on-runway starts, with the detector's score interpolated
between nodes and with the fitted noise of its variation between nodes
(`reach.score_noise`), beside the real Drake loops (rendering every tick) from the
same starts, each fallback with 95 % Wilson intervals.

The noise is fitted on separate calibration runs of the controller alone (their own
seed), never on the starts it is checked on; the tables are rolled out with it under
``--noise-seeds`` seeds (the calibration seed and the ones after it). This is the
guard stage's real-loop check (`guard_check`) with more noise seeds. Real runs and sweeps are cached by
content under ``--cache`` (a re-run is free, a killed one resumes).

    python benchmarks/guard_fidelity.py --scenario S.yaml [--shape 21 11 21]
        [--fallbacks brake] [--starts 200] [--seed 2000] [--calibration-starts 20]
        [--calibration-seed 4000] [--noise-seeds 5] [--mission-limit 3] [--cache DIR]

``S.yaml`` is a scenario file with ``monitor: {detector: ..., threshold: ...}``.
"""

import time

import numpy as np

from guard_common import guard_parser, guarded_setup
from reachwatch.pipeline.executors import open_executor
from reachwatch.pipeline.online_stages import guard_check
from reachwatch.reach.liveness import percent
from reachwatch.taxi import sweep_guarded


def row(name, figures):
    same = figures.get("same_distance_failure_set")
    cut = figures.get("same_distance_failure_cut")
    return (f"{name:34s} alone fails {percent(figures['alone_failure_set']):22s} guarded fails "
            f"(same distance) {percent(same) if same else '-':22s} cut "
            f"{100 * cut if cut is not None else float('nan'):4.0f} %  ended stopped "
            f"{percent(figures['ended_stopped']):22s} needless stops "
            f"{percent(figures['needless_stops']):22s} flagged ticks "
            f"{100 * figures['flagged_ticks']:3.0f} %{saves(figures)}")


def saves(figures):
    """Of the starts the controller alone fails within the horizon, how many the fallback
    keeps on the runway within it, and how many of those still move at its end (the
    rest are saved by standing still; a moving save may still fail later)."""
    saved, moving = figures.get("saved"), figures.get("saved_moving")
    if not saved:
        return ""
    return (f"  saved within the horizon {saved['count']}/{saved['of']}, still moving "
            f"{moving['count']}")


def main():
    p = guard_parser(__doc__, fallbacks="brake", starts=200, seed=2000, noise_seeds=5)
    args = p.parse_args()
    scenario, grid, cache, fallbacks = guarded_setup(p, args)
    horizon = float(scenario.duration)
    started = time.perf_counter()
    with open_executor(args.executor) as executor:
        tables = sweep_guarded(scenario, grid, cache_dir=cache / "sweeps", executor=executor)
        check = guard_check(scenario, grid, tables, fallbacks, starts=args.starts, seed=args.seed,
                            horizon=horizon, mission_limit=args.mission_limit,
                            cache_dir=cache / "outcomes", executor=executor,
                            noise_starts=args.calibration_starts,
                            noise_seed=args.calibration_seed, noise_seeds=args.noise_seeds)
    print(f"guard fidelity: {scenario.environment.name}, detector threshold "
          f"{scenario.monitor.threshold:.3g}, grid {args.shape}, {args.starts} starts (seed "
          f"{args.seed}), horizon {horizon:g} s, same distance up to {args.mission_limit:g} x "
          f"the horizon ({time.perf_counter() - started:.0f} s)")
    noise = check["score_noise"]
    if "error" in noise:
        raise SystemExit(f"the score-noise fit failed: {noise['error']}")
    print(f"score noise fitted on {noise['runs']} calibration runs of the controller alone (seed "
          f"{args.calibration_seed}, {noise['ticks']} ticks): mean {noise['mean']:+.3f} and sigma "
          f"{noise['sigma']:.3f} (logit), correlation length {noise['length']:.2f} m")
    for f in fallbacks:
        record = check["fallbacks"][f]
        figures = record.get("table_with_noise_by_seed", [record["table_with_noise"]])
        print(f"\n{f}:")
        print(row("tables, interpolated score", record["table"]))
        for k, fig in enumerate(figures):
            print(row(f"tables + score noise, seed {args.calibration_seed + k}", fig))
        mean = {k: np.mean([fig[k]["rate"] for fig in figures])
                for k in ("same_distance_failure_set", "ended_stopped", "needless_stops")}
        print(f"{'tables + score noise, mean':34s} guarded fails (same distance) "
              f"{100 * mean['same_distance_failure_set']:.1f} %, ended stopped "
              f"{100 * mean['ended_stopped']:.1f} %, needless stops "
              f"{100 * mean['needless_stops']:.1f} %")
        print(row("real loop", record["real"]))


if __name__ == "__main__":
    main()
