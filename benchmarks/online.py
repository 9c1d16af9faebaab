"""Online rate: closed-loop control ticks per wall second of TaxiNet alone vs the
guarded pipeline (TaxiNet + anomaly detector + fallback switch), same run, same
200x360 camera. The detector has random weights unless --detector is given (timing
does not depend on the weights) and never triggers the fallback (threshold 1), so both
loops drive the same path.

    python benchmarks/online.py [--detector PATH] [--duration 4] [--rounds 5]
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
    parser.add_argument("--duration", type=float, default=4.0)
    parser.add_argument("--runs", type=int, default=1, help="runs per timing (best kept)")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (median ratio)")
    parser.add_argument("--torch-threads", type=int, default=0,
                        help="torch.set_num_threads for the run (0: torch's default)")
    args = parser.parse_args()
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    print(f"online benchmark: KMWH 9h clear, 200x360, {args.rounds} interleaved rounds of "
          f"{args.duration:g} s runs; rates are the best round, the ratio the median of "
          f"per-round ratios, {torch.get_num_threads()} torch threads (paper: 33 Hz alone "
          f"vs 25 Hz guarded)")
    print(f"{'detector':<34} {'alone ticks/s':>14} {'guarded ticks/s':>16} {'ratio':>6}")
    with tempfile.TemporaryDirectory() as folder:
        configs = [("given", args.detector)] if args.detector else []
        for name, config in [("small_cnn 96x160 (default)", DetectorConfig()),
                             ("small_cnn 48x80", DetectorConfig(height=48, width=80)),
                             ("efficientnet_b0 224x224 (paper)", DetectorConfig.paper())]:
            if args.detector:
                break
            torch.manual_seed(0)
            path = Path(folder) / f"{config.arch}_{config.height}x{config.width}.pt"
            save_checkpoint(path, kind="detector", model=build_detector(config),
                            model_config=config, preprocess_config=None,
                            metadata={"image_size": [200, 360]})
            configs.append((name, path))
        nominal = make_closed_loop_diagram(load_scenario(data=""))
        guarded = {name: make_guarded_diagram(load_scenario(
            data=f"pipeline: {{detector: {path}, threshold: 1.0}}\n")) for name, path in configs}
        # The VM's speed drifts by ~30 % over minutes, so every round times TaxiNet alone
        # and each guarded loop back to back, and the ratio is the median over rounds.
        alone, rates = [], {name: [] for name in guarded}
        for _ in range(args.rounds):
            alone.append(ticks_per_second(nominal, args.runs, args.duration))
            for name, diagram in guarded.items():
                rates[name].append(ticks_per_second(diagram, args.runs, args.duration))
        for name, r in rates.items():
            ratio = float(np.median(np.asarray(r) / np.asarray(alone)))
            print(f"{name:<34} {max(alone):14.1f} {max(r):16.1f} {ratio:6.2f}")


if __name__ == "__main__":
    main()
