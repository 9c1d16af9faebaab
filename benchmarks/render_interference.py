"""Why the guarded loop loses more than the detector's own time: a 200x360 render
right after other work on this CPU-only machine is slower than one right after
another render. Times the camera render (`StateRenderer`) after nothing, after 1 and
2 ms of pure-Python busy work, after one and two default-detector passes, and after
a 1 ms sleep, the cases interleaved; prints median and mean render times.

    python benchmarks/render_interference.py [--rounds 40]
"""

import argparse
import time

import numpy as np
import torch

from reachwatch.diagrams import StateRenderer, load_scenario
from reachwatch.systems import AnomalyDetector, DetectorConfig, build_detector


def busy(ms):
    start = time.perf_counter()
    while time.perf_counter() - start < ms / 1e3:
        pass


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=40)
    args = parser.parse_args()
    scenario = load_scenario(data="")
    renderer = StateRenderer(environment=scenario.environment, camera=scenario.camera)
    torch.manual_seed(0)
    detector = AnomalyDetector(model=build_detector(DetectorConfig()), config=DetectorConfig())
    frame = np.random.default_rng(0).integers(0, 256, (1, 200, 360, 4), dtype=np.uint8)
    before = {"nothing": lambda: None, "1 ms busy": lambda: busy(1.0),
              "2 ms busy": lambda: busy(2.0), "detector": lambda: detector.scores(frame),
              "detector x2": lambda: (detector.scores(frame), detector.scores(frame)),
              "1 ms sleep": lambda: time.sleep(1e-3)}
    renderer.render([0.0, 110.0, 0.0])
    times = {k: [] for k in before}
    for _ in range(args.rounds):
        for name, work in before.items():
            for i in range(5):
                work()
                start = time.perf_counter()
                renderer.render([0.1 * (i % 3), 110.0 + i, 0.0])
                times[name].append(time.perf_counter() - start)
    print(f"render 200x360 after ..., {args.rounds} rounds x 5 renders, "
          f"{torch.get_num_threads()} torch threads")
    print(f"{'after':<14} {'median ms':>10} {'mean ms':>8} {'vs nothing':>11}")
    base = np.median(times["nothing"])
    for name, t in times.items():
        print(f"{name:<14} {1e3 * np.median(t):10.2f} {1e3 * np.mean(t):8.2f} "
              f"{1e3 * (np.median(t) - base):+10.2f}")


if __name__ == "__main__":
    main()
