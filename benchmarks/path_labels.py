"""Trajectory labels against the real loop: how many frames a label costs, and whether
the labels read along longer runs are what the loop does when started at those states.

From ``--starts`` seeded uniform on-runway starts of the paper's box, the real Drake
loop (rendering every tick) runs ``horizon + --extend`` s (`taxi.fidelity.real_paths`);
every ``--stride``-th tick within the first ``--extend`` s is a labelled state. Then
``--checks`` of those states (the starts themselves left out, drawn with ``--seed + 1``)
are run again from scratch for the horizon (`taxi.fidelity.real_outcomes`), and their
labels are scored against what the loop did: agreement, false-safe (labelled safe,
the loop failed) and false-unsafe, with 95 % Wilson intervals. The cost is given as
frames per label beside the ``rollout`` source's (one run per label: the check runs'
own frames per run).

Real runs are cached by content under ``--cache`` (a re-run is free, a killed one
resumes).

    python benchmarks/path_labels.py [--run-file scenarios/demo.yaml]
        [--environment KSFO:21:overcast] [--starts 60] [--extend 8] [--stride 8]
        [--checks 200] [--seed 5000] [--cache DIR]
"""

import argparse
import copy
import time
from pathlib import Path

import numpy as np

from fidelity import interval       # benchmarks/fidelity.py
from reachwatch.pipeline.evaluate_commands import parse_environment
from reachwatch.pipeline.spec import load_run_spec
from reachwatch.reach import compare_verdicts
from reachwatch.systems.files import cache_root
from reachwatch.taxi import on_runway_starts, paper_grid
from reachwatch.taxi.fidelity import real_outcomes, real_paths


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run-file", default="scenarios/demo.yaml", help="camera, controller, horizon")
    p.add_argument("--environment", default="KSFO:21:overcast")
    p.add_argument("--starts", type=int, default=60, help="uniform starts whose runs are labelled")
    p.add_argument("--extend", type=float, default=8.0, help="s each run lasts past the horizon")
    p.add_argument("--stride", type=int, default=8, help="ticks between labelled states")
    p.add_argument("--checks", type=int, default=200, help="labelled states run again from scratch")
    p.add_argument("--seed", type=int, default=5000)
    p.add_argument("--cache", default=None, help="rollout cache (default: the user cache)")
    args = p.parse_args()
    spec = load_run_spec(args.run_file)
    cache = (cache_root() if args.cache is None else Path(args.cache)) / "outcomes"
    env = parse_environment(args.environment)
    scenario = copy.deepcopy(spec.scenario)
    scenario.environment = env
    grid = paper_grid(env.half_width, (3, 3, 3))
    starts = on_runway_starts(grid, args.starts, args.seed, half_width=env.half_width)
    started = time.time()
    paths = real_paths(scenario, starts, grid=grid, horizon=spec.horizon, extend=args.extend,
                       stride=args.stride, cache_dir=cache)
    path_seconds = time.time() - started
    labels, states = paths["path_label"], paths["path_state"]
    known = labels >= 0
    frames = int(np.sum(paths["ticks"]))
    print(f"{env.name}: {args.starts} starts x {spec.horizon:g} + {args.extend:g} s, every "
          f"{args.stride} ticks: {int(known.sum())} labels ({int(known[:, 1:].sum())} beyond the "
          f"starts; {int(np.sum(labels == 1))} anomalous) from {frames} frames, "
          f"{frames / known.sum():.1f} frames per label; {path_seconds:.0f} s")
    rows, cols = np.nonzero(known[:, 1:])
    rng = np.random.default_rng(args.seed + 1)
    pick = rng.choice(len(rows), size=min(args.checks, len(rows)), replace=False)
    check_states = states[rows[pick], cols[pick] + 1]
    check_labels = labels[rows[pick], cols[pick] + 1] == 1
    started = time.time()
    real = real_outcomes(scenario, check_states, grid=grid, duration=spec.horizon,
                         cache_dir=cache)
    fidelity = compare_verdicts(check_labels, real.failed, real["left_box"])
    per_run = float(np.mean(real["ticks"]))
    print(f"{len(pick)} labelled states run again from scratch ({time.time() - started:.0f} s): "
          f"{fidelity.real_failures} failed; labels agree {interval(fidelity, 'agree')} %, "
          f"false-safe {interval(fidelity, 'false_safe')} %, "
          f"false-unsafe {interval(fidelity, 'false_unsafe')} %")
    print(f"frames per label: trajectory {frames / known.sum():.1f}, rollout {per_run:.1f} "
          f"(the check runs' mean); {per_run / (frames / known.sum()):.1f} x fewer")


if __name__ == "__main__":
    main()
