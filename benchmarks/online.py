"""Online rate: closed-loop control ticks per wall second of TaxiNet alone vs the
guarded pipeline (TaxiNet + anomaly detector + fallback switch), same run, same
200x360 camera. The detector has random weights unless --detector is given (timing
does not depend on the weights) and never triggers the fallback (threshold 1), so both
loops drive the same path.

    python benchmarks/online.py [--detector PATH] [--duration 8] [--runs 3]
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from reachwatch.diagrams import (load_scenario, make_closed_loop_diagram, make_guarded_diagram,
                                 save_checkpoint, simulate)
from reachwatch.systems import DetectorConfig, build_detector


def ticks_per_second(diagram, runs, duration):
    context = diagram.CreateDefaultContext()
    best = 0.0
    for k in range(runs):
        x0 = [0.5 * k, 110.0 + 10 * k, np.deg2rad(2.0 * k)]
        start = time.perf_counter()
        trajectory = simulate(diagram, initial_state=x0, duration=duration, half_width=1e9,
                              context=context)
        best = max(best, (len(trajectory.time) - 1) / (time.perf_counter() - start))
    return best


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--detector", help="a trained detector checkpoint")
    parser.add_argument("--duration", type=float, default=8.0)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    print(f"online benchmark: KMWH 9h clear, 200x360, best of {args.runs} runs of "
          f"{args.duration:g} s (paper: 33 Hz alone vs 25 Hz guarded)")
    print(f"{'detector':<34} {'alone ticks/s':>14} {'guarded ticks/s':>16} {'ratio':>6}")
    with tempfile.TemporaryDirectory() as folder:
        configs = [("given", args.detector)] if args.detector else []
        for name, config in [("small_cnn 96x160 (default)", DetectorConfig()),
                             ("efficientnet_b0 224x224 (paper)", DetectorConfig.paper())]:
            if args.detector:
                break
            torch.manual_seed(0)
            path = Path(folder) / f"{config.arch}.pt"
            save_checkpoint(path, kind="detector", model=build_detector(config),
                            model_config=config, preprocess_config=None,
                            metadata={"image_size": [200, 360]})
            configs.append((name, path))
        nominal = make_closed_loop_diagram(load_scenario(data=""))
        for name, path in configs:
            guarded = make_guarded_diagram(load_scenario(
                data=f"pipeline: {{detector: {path}, threshold: 1.0}}\n"))
            alone = guarded_rate = 0.0
            for _ in range(2):                 # interleaved, best of each: the VM is noisy
                alone = max(alone, ticks_per_second(nominal, args.runs, args.duration))
                guarded_rate = max(guarded_rate,
                                   ticks_per_second(guarded, args.runs, args.duration))
            print(f"{name:<34} {alone:14.1f} {guarded_rate:16.1f} {guarded_rate / alone:6.2f}")


if __name__ == "__main__":
    main()
