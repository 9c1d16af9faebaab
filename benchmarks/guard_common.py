"""What the guard benchmarks share: their common command-line options and the guarded
scenario, grid and cache those options name."""

import argparse
from pathlib import Path

from reachwatch.diagrams import load_scenario
from reachwatch.pipeline.executor_option import add_executor_argument
from reachwatch.systems.files import cache_root
from reachwatch.taxi import paper_grid, resolved


def guard_parser(doc: str, *, fallbacks: str, starts: int, seed: int,
                 noise_seeds: int) -> argparse.ArgumentParser:
    """The options every guard benchmark takes, with its own defaults for ``--fallbacks``,
    ``--starts``, ``--seed`` and ``--noise-seeds``; add yours to the parser it returns."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--scenario", required=True, help="scenario file with a monitor")
    p.add_argument("--shape", type=int, nargs=3, default=[21, 11, 21])
    p.add_argument("--fallbacks", default=fallbacks, help="comma-separated fallback names")
    p.add_argument("--starts", type=int, default=starts)
    p.add_argument("--seed", type=int, default=seed)
    p.add_argument("--calibration-starts", type=int, default=20)
    p.add_argument("--calibration-seed", type=int, default=4000)
    p.add_argument("--noise-seeds", type=int, default=noise_seeds)
    p.add_argument("--mission-limit", type=float, default=3.0)
    p.add_argument("--cache", default=None, help="sweep and rollout cache (default: the user cache)")
    add_executor_argument(p)
    return p


def guarded_setup(p: argparse.ArgumentParser, args):
    """``(scenario, grid, cache, fallbacks)`` from the parsed options; a clear
    ``p.error`` for a scenario without a detector or counts below 1."""
    scenario = resolved(load_scenario(args.scenario))
    if not scenario.monitor.detector:
        p.error(f"{args.scenario} has no monitor.detector: nothing to guard with")
    scenario.monitor = scenario.monitor.with_checkpoint_defaults()   # the threshold it shows
    if min(args.starts, args.calibration_starts, args.noise_seeds) < 1:
        p.error("--starts, --calibration-starts and --noise-seeds must be >= 1")
    grid = paper_grid(scenario.environment.half_width, tuple(args.shape))
    cache = cache_root() if args.cache is None else Path(args.cache)
    return scenario, grid, cache, [f for f in args.fallbacks.split(",") if f]
