"""Simulated control ticks per wall second of the TaxiNet closed loop (Drake
Simulator, one render + TaxiNet + P-controller per 0.05 s tick), beside the raw
camera-port render rate measured in the same run.

At 64x128 the loop uses a TaxiNet with random weights (timing does not depend on the
weights; the shipped checkpoint is for 200x360).

This is one long run at a time on torch's default threads; `benchmarks/lockstep.py` times
the real-loop runs as `reachwatch.taxi.fidelity` makes them (several runs in lockstep,
one torch thread) against the render rate.

    python benchmarks/closed_loop.py [--duration 8] [--runs 3]
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from reachwatch.diagrams import (REFERENCE_TAXINET, StateRenderer, load_scenario,
                                 make_closed_loop_diagram, save_checkpoint, simulate)
from reachwatch.systems import PreprocessConfig, TaxiNetConfig, build_taxinet


def checkpoint_for(height, width, folder):
    """The shipped TaxiNet at 200x360, else a seeded random one (timing does not depend
    on the weights)."""
    if (height, width) == (200, 360):
        return REFERENCE_TAXINET
    torch.manual_seed(0)
    path = Path(folder) / f"random_{height}x{width}.pt"
    save_checkpoint(path, kind="taxinet", model=build_taxinet(TaxiNetConfig(), PreprocessConfig()),
                    model_config=TaxiNetConfig(), preprocess_config=PreprocessConfig(),
                    metadata={"image_size": [height, width]})
    return path


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=8.0)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"closed-loop benchmark: KMWH 9h clear, {args.runs} runs of {args.duration:g} s "
          f"from the centreline region, best run")
    print(f"{'HxW':>8} {'ticks/s':>9} {'render fps':>11} {'ticks/render':>13} {'x real time':>12}")
    with tempfile.TemporaryDirectory() as folder:
        for height, width in [(64, 128), (200, 360)]:
            scenario = load_scenario(data=(
                f"camera: {{width: {width}, height: {height}}}\n"
                f"controller: {{checkpoint: {checkpoint_for(height, width, folder)}}}\n"))
            diagram = make_closed_loop_diagram(scenario)
            context = diagram.CreateDefaultContext()
            best = 0.0
            for _ in range(args.runs):
                x0 = [rng.uniform(-2, 2), rng.uniform(100, 150), np.deg2rad(rng.uniform(-5, 5))]
                start = time.perf_counter()
                trajectory = simulate(diagram, initial_state=x0, duration=args.duration,
                                      period=scenario.controller.period,
                                      context=context)
                best = max(best, (len(trajectory.time) - 1) / (time.perf_counter() - start))
            renderer = StateRenderer(environment=scenario.environment, camera=scenario.camera)
            states = np.column_stack([rng.uniform(-11, 11, 200), rng.uniform(100, 250, 200),
                                      np.deg2rad(rng.uniform(-28, 28, 200))])
            renderer.render(states[0])
            start = time.perf_counter()
            for x in states:
                renderer.render(x)
            fps = len(states) / (time.perf_counter() - start)
            ticks_per_s = best
            print(f"{height}x{width:<4} {ticks_per_s:9.1f} {fps:11.1f} {ticks_per_s / fps:13.2f} "
                  f"{ticks_per_s * 0.05:12.1f}")


if __name__ == "__main__":
    main()
