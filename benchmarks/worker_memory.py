"""The resident memory of one process that runs the loop alone in many environments in
turn, as a worker running a study's chunks does: each environment's loop holds a
renderer, and a worker thread keeps only its `KEPT_DIAGRAMS` most recently used
(`reachwatch.reach.thread_kept`), so the memory should level off after that many.

    python benchmarks/worker_memory.py [--environments 10] [--duration 1]

One start per environment (seeded), inline, a fresh cache; prints the process's
resident memory (VmRSS) after each environment.
"""

import argparse
import dataclasses as dc
import tempfile

from reachwatch.diagrams import load_scenario
from reachwatch.reach.application import load_application
from reachwatch.taxi.application import TAXI_APPLICATION
from reachwatch.reach.thread_kept import KEPT_DIAGRAMS
from reachwatch.systems import RandomEnvironments


def resident_mb() -> float:
    """This process's resident memory (MB), from /proc (Linux)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return float("nan")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--environments", type=int, default=10)
    p.add_argument("--duration", type=float, default=1.0, help="each run's length (s)")
    p.add_argument("--seed", type=int, default=5, help="the random family's seed")
    args = p.parse_args()
    application, scenario = load_application(TAXI_APPLICATION), load_scenario(data="")
    environments = RandomEnvironments(seed=args.seed, count=args.environments).environments()
    print(f"kept per thread: {KEPT_DIAGRAMS}; before any loop: {resident_mb():.0f} MB")
    with tempfile.TemporaryDirectory() as cache:
        for i, environment in enumerate(environments):
            here = dc.replace(scenario, environment=environment)
            box = application.grid(here, (3,) * len(application.axes))
            starts = application.starts(here, (box.lo, box.hi), 1, i)
            application.missions(here, starts, duration=args.duration, cache_dir=cache,
                                 progress=False)
            print(f"{i + 1:3d} {environment.name:28s} {resident_mb():7.0f} MB", flush=True)


if __name__ == "__main__":
    main()
