"""Anomaly-detector inference on the CPU: latency per image at batch 1 and throughput
at batch 32, for the default (small CNN, 96x160), the small CNN at 48x80 and the paper's
configuration (EfficientNet-B0, 224x224), from 200x360 camera frames (the system's
OpenCV area resize included).

    python benchmarks/detector.py [--repeats 20]
"""

import argparse
import time

import numpy as np
import torch

from reachwatch.systems import DetectorConfig, build_detector, detector_input, resize_for_detector


@torch.no_grad()
def timed(model, config, frames, repeats):
    def scores():
        x = torch.from_numpy(resize_for_detector(frames, config))
        return torch.softmax(model(detector_input(x, config)), dim=1)
    scores()                                               # warm-up
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        scores()
        best = min(best, time.perf_counter() - start)
    return best


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (32, 200, 360, 3), dtype=np.uint8)
    print(f"detector benchmark: CPU, {torch.get_num_threads()} torch threads, best of "
          f"{args.repeats}")
    print(f"{'configuration':<34} {'batch-1 latency ms':>19} {'batch-32 images/s':>18}")
    for name, config in [("default: small_cnn 96x160", DetectorConfig()),
                         ("small_cnn 48x80", DetectorConfig(height=48, width=80)),
                         ("paper: efficientnet_b0 224x224", DetectorConfig.paper())]:
        torch.manual_seed(0)
        model = build_detector(config).eval()
        latency = timed(model, config, frames[:1], args.repeats)
        batch = timed(model, config, frames, max(3, args.repeats // 4))
        print(f"{name:<34} {1e3 * latency:19.2f} {32 / batch:18.1f}")


if __name__ == "__main__":
    main()
