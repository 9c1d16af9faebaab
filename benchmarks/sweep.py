"""Grid states per second of the sweep (set state, evaluate the closed loop's steering
port: render + TaxiNet + P-controller) beside the raw camera-port render rate, same
run, same scene, same image size (200x360, the reference TaxiNet's). With
``--workers``, also the sweep on pools of spawned workers (1 and the default, one per
usable core), interleaved, as a ratio to the single worker, and whether every pool's
table is identical to the in-process one.

    python benchmarks/sweep.py [--shape 9 9 9] [--workers]
"""

import argparse
import tempfile
import time

import numpy as np

from reachwatch.diagrams import StateRenderer, load_scenario
from reachwatch.reach import InlineExecutor, default_executor, stop_executor
from reachwatch.reach.sweep import usable_cores
from reachwatch.taxi import paper_grid, sweep_closed_loop


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shape", type=int, nargs=3, default=[9, 9, 9])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--workers", action="store_true",
                        help="also compare pools of 1 and of the default number of workers")
    parser.add_argument("--environment", default="runway: KMWH, hour: 9.0, sky: clear",
                        help="the environment block, YAML flow style without braces")
    args = parser.parse_args()
    scenario = load_scenario(data=f"environment: {{{args.environment}}}\n")
    grid = paper_grid(scenario.environment.half_width, tuple(args.shape))
    renderer = StateRenderer(environment=scenario.environment, camera=scenario.camera)
    states = grid.states()
    renderer.render(states[0])
    render_fps = sweep_rate = 0.0
    with tempfile.TemporaryDirectory() as cache:
        sweep_closed_loop(scenario, paper_grid(10.0, (2, 2, 2)), cache_dir=cache,
                          executor=InlineExecutor(), progress=False)        # warm-up build
        for round_ in range(args.rounds):   # interleaved, best of each: the VM is noisy
            start = time.perf_counter()
            for x in states:
                renderer.render(x)
            render_fps = max(render_fps, len(states) / (time.perf_counter() - start))
            start = time.perf_counter()
            sweep_closed_loop(scenario, grid, cache_dir=f"{cache}/{round_}",
                              executor=InlineExecutor(), progress=False)
            sweep_rate = max(sweep_rate, grid.size / (time.perf_counter() - start))
        start = time.perf_counter()
        sweep_closed_loop(scenario, grid, cache_dir=f"{cache}/0", executor=InlineExecutor(),
                          progress=False)
        cached_s = time.perf_counter() - start
    print(f"sweep benchmark: {args.environment}, 200x360, grid {args.shape} ({grid.size} "
          f"states), in-process executor, best of {args.rounds} interleaved rounds")
    print(f"sweep {sweep_rate:.1f} states/s, raw render {render_fps:.1f} frames/s, "
          f"ratio {sweep_rate / render_fps:.2f}; repeated (cached) sweep {cached_s:.2f} s")
    if args.workers:
        compare_workers(scenario, grid, args.rounds)


def compare_workers(scenario, grid, rounds):
    """Pools of 1 and of ``usable_cores()`` workers, interleaved rounds, best of each;
    chunks small enough that every worker gets several."""
    counts = sorted({1, usable_cores()})
    chunk = max(1, grid.size // (4 * counts[-1]))
    pools = {n: default_executor(n) for n in counts}
    rates, same = {n: 0.0 for n in counts}, {n: True for n in counts}
    try:
        with tempfile.TemporaryDirectory() as cache:
            reference = sweep_closed_loop(scenario, grid, cache_dir=f"{cache}/inline",
                                          executor=InlineExecutor(), progress=False)
            for n, pool in pools.items():             # warm-up: spawn, import, build
                sweep_closed_loop(scenario, paper_grid(10.0, (2, 2, 2)), cache_dir=f"{cache}/w{n}",
                                  executor=pool, progress=False, chunk_size=1)
            for round_ in range(rounds):
                for n, pool in pools.items():
                    start = time.perf_counter()
                    table = sweep_closed_loop(scenario, grid, cache_dir=f"{cache}/{n}_{round_}",
                                              executor=pool, progress=False, chunk_size=chunk)
                    rates[n] = max(rates[n], grid.size / (time.perf_counter() - start))
                    same[n] &= all(np.array_equal(table[p], reference[p]) for p in reference.tables)
    finally:
        for pool in pools.values():
            stop_executor(pool)
    print(f"worker pools ({usable_cores()} usable cores, chunks of {chunk} states, best of "
          f"{rounds} interleaved rounds):")
    for n in counts:
        print(f"  {n} worker{'s' if n > 1 else ' '}  {rates[n]:6.1f} states/s  ratio "
              f"{rates[n] / rates[1]:.2f}  table identical to in-process: {same[n]}")


if __name__ == "__main__":
    main()
