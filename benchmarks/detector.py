"""Anomaly-detector inference on the CPU from 200x360 RGBA camera frames, the OpenCV
area resize included: batch-1 latency of the model as trained and of the copy the
`AnomalyDetector` system runs (BatchNorm folded, channels-last, RGBA resized without a
numpy copy), and batch-32 throughput, for the default (small CNN, 96x160), the small
CNN with a stride-2 stem, the small CNN at 48x80 and the paper's configuration
(EfficientNet-B0, 224x224).

    python benchmarks/detector.py [--repeats 50]
"""

import argparse
import time

import numpy as np
import torch

from reachwatch.systems import (AnomalyDetector, DetectorConfig, build_detector,
                                detector_input, resize_for_detector)


def best_time(fn, repeats):
    fn()                                                   # warm-up
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


@torch.no_grad()
def as_trained(model, config, frames_rgba):
    """The pre-system path: numpy drops alpha, the trained (unfolded) model."""
    x = torch.from_numpy(resize_for_detector(np.ascontiguousarray(frames_rgba[..., :3]), config))
    return torch.softmax(model(detector_input(x, config)), dim=1)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=50)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (32, 200, 360, 4), dtype=np.uint8)
    print(f"detector benchmark: CPU, {torch.get_num_threads()} torch threads, best of "
          f"{args.repeats}, 200x360 RGBA frames in")
    print(f"{'configuration':<34} {'as trained ms':>14} {'system ms':>10} {'speed-up':>9} "
          f"{'batch-32 images/s':>18} {'batch / one':>12}")
    for name, config in [("default: small_cnn 96x160", DetectorConfig()),
                         ("small_cnn 96x160 stem_stride 2", DetectorConfig(stem_stride=2)),
                         ("small_cnn 48x80", DetectorConfig(height=48, width=80)),
                         ("paper: efficientnet_b0 224x224", DetectorConfig.paper())]:
        torch.manual_seed(0)
        model = build_detector(config).eval()
        system = AnomalyDetector(model=model, config=config)
        trained = best_time(lambda: as_trained(model, config, frames[:1]), args.repeats)
        latency = best_time(lambda: system.scores(frames[:1]), args.repeats)
        batch = best_time(lambda: system.scores(frames), max(3, args.repeats // 10))
        # batch / one: images a second in a batch of 32 against one at a time, both here
        print(f"{name:<34} {1e3 * trained:14.2f} {1e3 * latency:10.2f} "
              f"{trained / latency:8.2f}x {32 / batch:18.1f} {latency * 32 / batch:11.2f}x")


if __name__ == "__main__":
    main()
