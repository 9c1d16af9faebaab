"""Online rate: closed-loop control ticks per wall second of TaxiNet alone vs the
guarded loop (TaxiNet + a monitor + fallback switch), same run, same 200x360 camera.
The monitors are single-image anomaly detectors and monitors over the image history
(`HistoryMonitor`, 48x80 frames, as the monitor study trains them, and an ensemble of
them: ``monitor.ensemble``); they have random
weights unless --detector is given (timing does not depend on the weights) and never
trigger the fallback (threshold 1), so both loops drive the same path.

The VM's speed moves by ~10 % within a second, so the two loops run side by side from
the same start, advanced in alternating 0.5 s blocks (`reachwatch.diagrams.paired_rates`),
and the ratio is the median over rounds of guarded ticks/s over alone ticks/s. The
first row times TaxiNet alone against a second copy of itself: the method's noise floor
(its ratio should read 1.00; on this VM it reads 0.97-1.05).

    python benchmarks/online.py [--detector PATH] [--monitors all|detector|history]
                                [--duration 4] [--rounds 15] [--ensemble 5]
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from reachwatch.diagrams import (load_scenario, make_closed_loop_diagram, make_guarded_diagram,
                                 paired_rates, save_checkpoint)
from reachwatch.systems import (MAX_MEMBERS, DetectorConfig, HistoryMonitorConfig,
                                HistoryRiskEnsemble, HistoryRiskModel, build_detector)
from reachwatch.taxi.application import NEAR_CENTRELINE


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--detector", help="a trained detector or history-monitor checkpoint")
    parser.add_argument("--monitors", choices=("all", "detector", "history"), default="all",
                        help="which untrained monitors to time (without --detector)")
    parser.add_argument("--duration", type=float, default=4.0, help="seconds simulated per round")
    parser.add_argument("--rounds", type=int, default=15, help="rounds (median ratio)")
    parser.add_argument("--ensemble", type=int, default=5,
                        help="members of the ensemble row (monitor.ensemble)")
    parser.add_argument("--torch-threads", type=int, default=0,
                        help="torch.set_num_threads for the run (0: torch's default); a "
                             "history monitor runs its network on one thread whatever this says")
    args = parser.parse_args()
    if not 2 <= args.ensemble <= MAX_MEMBERS:
        parser.error(f"--ensemble takes 2 to {MAX_MEMBERS} members, got {args.ensemble}")
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    print(f"online benchmark: KMWH 9h clear, 200x360, {args.rounds} rounds of "
          f"{args.duration:g} s, both loops side by side in alternating 0.5 s blocks; "
          f"medians over rounds; {torch.get_num_threads()} torch threads, 1 in a history "
          f"monitor (paper: 33 Hz alone vs 25 Hz guarded)")
    print(f"{'detector':<38} {'alone /s':>10} {'guarded /s':>12} {'+ms/tick':>9} {'ratio':>6} "
          f"{'range':>9}")
    with tempfile.TemporaryDirectory() as folder:
        configs = [("given", args.detector)] if args.detector else []
        for name, config in [] if args.monitors == "history" else [("small_cnn 96x160 (default)", DetectorConfig()),
                             ("small_cnn 96x160 stem_stride 2", DetectorConfig(stem_stride=2)),
                             ("small_cnn 48x80", DetectorConfig(height=48, width=80)),
                             ("efficientnet_b0 224x224 (paper)", DetectorConfig.paper())]:
            if args.detector:
                break
            torch.manual_seed(0)
            path = Path(folder) / (f"{config.arch}_{config.height}x{config.width}_"
                                   f"{config.stem_stride}.pt")
            save_checkpoint(path, kind="detector", model=build_detector(config),
                            model_config=config, preprocess_config=None,
                            metadata={"image_size": [200, 360], "threshold": 0.5})
            configs.append((name, path))
        one = HistoryMonitorConfig(frames=1)
        for name, config, members in [] if args.detector or args.monitors == "detector" else [
                ("history: single frame, 48x80", one, 1),
                (f"history: ensemble of {args.ensemble} single frames", one, args.ensemble),
                ("history: stacked 8 frames, 48x80", HistoryMonitorConfig(frames=8, stride=4), 1),
                ("history: GRU 16 + signals, 48x80", HistoryMonitorConfig(
                    frames=16, temporal="gru", signals=3), 1)]:
            torch.manual_seed(0)
            path = Path(folder) / f"history_{config.temporal}_{config.frames}_{members}.pt"
            models = [HistoryRiskModel(config).eval() for _ in range(members)]
            model = models[0] if members == 1 else HistoryRiskEnsemble.of(models)
            save_checkpoint(path, kind="history_monitor", model=model,
                            model_config=config, preprocess_config=None,
                            metadata={"calibration": [1.0, 0.0], "threshold": 0.5})
            configs.append((name, path))
        nominal = make_closed_loop_diagram(load_scenario(data=""))
        # First row: TaxiNet alone against a second copy of itself, the method's noise floor.
        candidates = [("TaxiNet alone again (noise floor)", None)] + configs
        for name, path in candidates:
            guarded = make_closed_loop_diagram(load_scenario(data="")) if path is None else \
                make_guarded_diagram(load_scenario(
                    data=f"monitor: {{detector: {path}, threshold: 1.0}}\n"))
            alone, guard = paired_rates(nominal, guarded, rounds=args.rounds,
                                        duration=args.duration, period=0.05,
                                        starts=NEAR_CENTRELINE)
            ratio = guard / alone
            extra_ms = float(np.median(1e3 / guard - 1e3 / alone))
            print(f"{name:<38} {np.median(alone):10.1f} {np.median(guard):12.1f} "
                  f"{extra_ms:9.2f} {np.median(ratio):6.2f} {ratio.min():5.2f}-{ratio.max():.2f}")


if __name__ == "__main__":
    main()
