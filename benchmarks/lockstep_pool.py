"""Real-loop runs per wall second on a local pool of workers (one per core by default),
each worker thread advancing its chunk's runs one at a time or N at a time in lockstep
(`reach.loop_runs.loop_rollouts`'s ``lockstep``, on the taxi's loop): whether lockstep pays where
it is used, on a machine whose cores the pool's workers fill. The sizes take turns
within each round (a shared VM's speed drifts); each ratio is to lockstep 1 in the same
round, the median over the rounds after a warm-up round (diagram builds); every size's
runs are compared with lockstep 1's.

    python benchmarks/lockstep_pool.py [--workers 2] [--starts 32] [--duration 1]
                                       [--sizes 1 4] [--rounds 4]
"""

import argparse
import functools
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from reachwatch.diagrams import load_scenario
from reachwatch.reach import default_executor, stop_executor
from reachwatch.reach.application import ApplicationRef
from reachwatch.taxi.application import TAXI_APPLICATION
from reachwatch.reach.loop_runs import loop_rollouts
from reachwatch.reach.outcomes import run_outcomes
from reachwatch.taxi import on_runway_starts, paper_grid


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=int, default=0, help="pool workers (0: one per core)")
    parser.add_argument("--starts", type=int, default=32, help="runs per size and round")
    parser.add_argument("--duration", type=float, default=1.0, help="seconds per run")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 4],
                        help="runs a worker thread advances together (the first: the reference)")
    parser.add_argument("--rounds", type=int, default=4, help="timed rounds, after a warm-up")
    args = parser.parse_args()
    scenario = load_scenario(data="environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    B = scenario.environment.half_width
    grid = paper_grid(B, (9, 5, 9))
    starts = on_runway_starts(grid, args.starts, 0, half_width=B)
    pool = default_executor(args.workers or None)
    rates = {n: [] for n in args.sizes}
    fields, same = {}, {n: True for n in args.sizes}
    try:
        with tempfile.TemporaryDirectory(prefix="lockstep_pool_") as folder:
            for round_ in range(args.rounds + 1):
                turn = round_ % len(args.sizes)
                for n in args.sizes[turn:] + args.sizes[:turn]:
                    rollout = functools.partial(loop_rollouts, ApplicationRef(TAXI_APPLICATION),
                                                scenario, args.duration, grid, lockstep=n)
                    t = time.perf_counter()
                    out = run_outcomes(rollout, starts, cache_dir=Path(folder) / f"{round_}_{n}",
                                       executor=pool, progress=False, chunk_size=8)
                    rates[n].append(len(starts) / (time.perf_counter() - t))
                    got = {k: np.asarray(v) for k, v in out.fields.items()}
                    first = fields.setdefault(args.sizes[0], got) if n == args.sizes[0] else \
                        fields.get(args.sizes[0])
                    if first is not None:
                        same[n] &= all(np.array_equal(got[k], first[k], equal_nan=True)
                                       for k in first)
    finally:
        stop_executor(pool)
    workers = args.workers or pool._max_workers
    print(f"lockstep in a pool: KMWH 9h clear, 200x360; {workers} workers on {os.cpu_count()} "
          f"CPUs; {args.starts} starts x {args.duration:g} s in chunks of 8; medians of "
          f"{args.rounds} interleaved rounds after a warm-up round")
    print(f"{'lockstep':>8} {'runs/s':>7} {'warm-up':>8} {'x lockstep ' + str(args.sizes[0]):>14} "
          f"{'range':>11}  identical")
    reference = np.array(rates[args.sizes[0]][1:])
    for n in args.sizes:
        timed = np.array(rates[n][1:])
        ratio = timed / reference
        print(f"{n:>8} {np.median(timed):7.2f} {rates[n][0]:8.2f} {np.median(ratio):14.2f} "
              f"{ratio.min():5.2f}-{ratio.max():5.2f}  {same[n]}")
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
