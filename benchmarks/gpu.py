"""The CUDA paths beside the CPU in the same run: the BRT solve and a detector's
training, each on ``cpu`` and on ``cuda``, with their times and how far the two agree.

- **BRT.** `solve_brt` (semi-Lagrangian, the default) on the taxi's dynamics at
  ``--shape`` with the synthetic control table of ``benchmarks/hjb.py``: solve seconds
  on each device (the second of two solves, the first warms up), the largest
  difference of V(x, 0) and the share of nodes whose BRT membership (V <= 0) agrees.
- **Detector.** `train_detector` on ``--samples`` synthetic images (a bright bar whose
  side sets the label, in noise) for ``--epochs`` epochs: seconds on each device, each
  model's validation AUROC, and the CUDA-trained checkpoint loaded and scored on the
  CPU against its scores on the GPU (a checkpoint trained on a GPU serves a CPU-only
  loop).

Where torch sees no CUDA device it says so in one line and exits 0: the project never
needs one.

    python benchmarks/gpu.py [--shape 101 101 101] [--samples 4096] [--epochs 3]
                             [--device cuda]
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from reachwatch.diagrams import load_detector
from reachwatch.reach import solve_brt
from reachwatch.systems import DetectorConfig
from reachwatch.taxi import TaxiDynamics, paper_grid
from reachwatch.training.dataset import LabelledData
from reachwatch.training.detector_train import (DetectorTrainConfig, detector_scores,
                                                train_detector)

from hjb import B, HORIZON, synthetic_table


def timed_solve(grid, table, device):
    """V(x, 0) on ``device`` and the seconds of the second of two solves."""
    for _ in range(2):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        started = time.perf_counter()
        vf = solve_brt(grid, TaxiDynamics(half_width=B), table, horizon=HORIZON, device=device)
        values = np.asarray(vf.values, dtype=float)
        seconds = time.perf_counter() - started
    return values, seconds


def synthetic_data(samples: int, height: int, width: int, seed: int) -> LabelledData:
    """Noise images with a bright vertical bar; label 1 when it is in the right half."""
    rng = np.random.default_rng(seed)
    images = rng.integers(0, 90, (samples, height, width, 3), dtype=np.uint8)
    column = rng.integers(0, width - 4, samples)
    for i, c in enumerate(column):
        images[i, :, c:c + 4] = 230
    values = np.where(column + 2 >= width // 2, -1.0, 1.0)
    return LabelledData.from_arrays(images=images, states=np.zeros((samples, 3)),
                                    values=values, environment="synthetic",
                                    camera_size=(200, 360))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shape", type=int, nargs=3, default=[101, 101, 101])
    parser.add_argument("--samples", type=int, default=4096)
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--device", default="cuda",
                        help="the device set beside the CPU (cpu: a dry run of the script)")
    args = parser.parse_args()
    other = args.device
    if other.startswith("cuda") and not torch.cuda.is_available():
        print("gpu benchmark: torch sees no CUDA device here; nothing to compare")
        return
    name = torch.cuda.get_device_name(0) if other.startswith("cuda") else other
    print(f"gpu benchmark: {name}, torch {torch.__version__}, {torch.get_num_threads()} CPU "
          f"threads")

    grid = paper_grid(B, tuple(args.shape))
    table = synthetic_table(grid)
    values, seconds = {}, {}
    for device in ("cpu", other):
        values[device], seconds[device] = timed_solve(grid, table, device)
    gap = np.abs(values["cpu"] - values[other])
    agree = np.mean((values["cpu"] <= 0) == (values[other] <= 0))
    print(f"BRT {args.shape} ({grid.size:,} nodes, {HORIZON:g} s): cpu {seconds['cpu']:.2f} s, "
          f"{other} {seconds[other]:.2f} s ({seconds['cpu'] / seconds[other]:.1f}x); "
          f"max |V_cpu - V_{other}| {gap.max():.2e} (|V| up to "
          f"{np.abs(values['cpu']).max():.1f}); BRT membership agrees at "
          f"{100 * agree:.4f} % of nodes")

    detector = DetectorConfig(height=48, width=80, channels=[16, 32, 32])
    data = [synthetic_data(args.samples, detector.height, detector.width, seed=0)]
    with tempfile.TemporaryDirectory() as folder:
        rows = {}
        for device in dict.fromkeys(("cpu", other)):
            config = DetectorTrainConfig(detector=detector, epochs=args.epochs, batch_size=64,
                                         device=device)
            path = Path(folder) / f"{device}.pt"
            rows[device] = train_detector(data, config, path)
            print(f"detector on {device}: {rows[device]['train_seconds']:.1f} s for "
                  f"{args.epochs} epochs of {args.samples} images; validation AUROC "
                  f"{rows[device]['validation']['auroc']:.4f}, final loss "
                  f"{rows[device]['train_losses'][-1]:.4f}")
        model, config, _ = load_detector(Path(folder) / f"{other}.pt")
        on_other = detector_scores(model, config, data[0].images[:512], device=other)
        model, config, _ = load_detector(Path(folder) / f"{other}.pt")
        on_cpu = detector_scores(model, config, data[0].images[:512], device="cpu")
        print(f"the {other}-trained detector scored on the CPU: max score difference "
              f"{np.abs(on_other - on_cpu).max():.2e} over 512 images; cpu/{other} training "
              f"time {rows['cpu']['train_seconds'] / max(rows[other]['train_seconds'], 1e-9):.1f}x")


if __name__ == "__main__":
    main()
