"""What of a `reachwatch run` stays on the driver: per stage, the wall seconds spent in
chunked work that an executor hands to workers (sweep, real-loop and dataset chunks,
every call of `reach.chunks.run_chunks`) and the rest, which runs in the driver
whatever the cluster's size (the HJB solves, training, evaluation, the guard's table
rollouts, figures and the report).

    python benchmarks/driver_share.py [--scenario scenarios/demo.yaml] [--out DIR]

It runs the whole pipeline of the run file inline (one process, nothing cached: a
fresh ``$REACHWATCH_CACHE`` and run directory under ``--out``), timing every
`run_chunks` call and every stage; a stage's chunked seconds are the union of the
`run_chunks` intervals inside it (the calls of environments run together overlap).
Inline, a chunk's time is what a worker would spend on it, so the driver's share of a
study on a cluster of N workers is at least driver / (driver + chunked / N). Inline,
the driver's cache writes inside a `run_chunks` call count as chunked, and what a stage
builds before its chunks (a renderer, networks, which each worker builds again on a
cluster) counts as the driver's."""

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _union(intervals):
    """Total length of the union of ``(start, end)`` intervals."""
    total, end = 0.0, float("-inf")
    for a, b in sorted(intervals):
        if b <= end:
            continue
        total += b - max(a, end)
        end = b
    return total


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default=str(ROOT / "scenarios" / "demo.yaml"))
    parser.add_argument("--out", default=None, help="where the run and its cache go "
                                                     "(default: a temporary folder)")
    args = parser.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix="driver_share_"))
    out.mkdir(parents=True, exist_ok=True)
    os.environ["REACHWATCH_CACHE"] = str(out / "cache")     # nothing cached before

    import importlib
    from reachwatch.pipeline import cli
    from reachwatch.pipeline.stages import Run
    # the modules that call run_chunks (the package re-exports a function named sweep)
    callers = [importlib.import_module(f"reachwatch.{name}") for name in
               ("reach.outcomes", "reach.sweep", "training.dataset")]

    chunked, stages, lock = [], [], threading.Lock()

    def timed(fn):
        def run_chunks(*a, **k):
            started = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                with lock:
                    chunked.append((started, time.perf_counter()))
        return run_chunks

    for module in callers:
        module.run_chunks = timed(module.run_chunks)
    stage = Run.stage

    def timed_stage(self, name, key, fn):
        started = time.perf_counter()
        try:
            return stage(self, name, key, fn)
        finally:
            stages.append((name, started, time.perf_counter()))
    Run.stage = timed_stage

    started = time.perf_counter()
    code = cli.main(["-q", "run", "--scenario", args.scenario, "--out", str(out / "run"),
                     "--executor", "inline"])
    wall = time.perf_counter() - started
    if code != 0:
        print(f"the run failed (exit {code})", file=sys.stderr)
        return code
    print(f"run file {args.scenario}, inline, nothing cached; wall {wall:.0f} s")
    print(f"{'stage':<36} {'seconds':>8} {'chunked':>8} {'driver':>8} {'driver %':>9}")
    totals = [0.0, 0.0]
    for name, a, b in stages:
        inside = _union([(max(s, a), min(e, b)) for s, e in chunked if e > a and s < b])
        totals[0] += b - a
        totals[1] += inside
        print(f"{name:<36} {b - a:8.1f} {inside:8.1f} {b - a - inside:8.1f} "
              f"{100 * (b - a - inside) / max(b - a, 1e-9):8.1f}")
    driver = totals[0] - totals[1]
    print(f"{'all stages':<36} {totals[0]:8.1f} {totals[1]:8.1f} {driver:8.1f} "
          f"{100 * driver / totals[0]:8.1f}")
    print(f"outside the stages (loading, checks): {wall - totals[0]:.1f} s")
    for n in (2, 8, 32):
        share = driver / (driver + totals[1] / n)
        print(f"on {n} workers the driver's part is at least {100 * share:.0f} % of the "
              f"stages' wall")
    return 0


if __name__ == "__main__":
    sys.exit(main())
