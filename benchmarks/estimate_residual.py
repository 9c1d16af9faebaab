"""Does the taxi controller's own estimate say a failure is coming? Per environment,
the AUROC of "fails within ``--within`` s" over the ticks of a monitor study's recorded
runs (the same labels as the monitor's figures, `tick_auroc`) for scores a monitor
could compute online from the signals alone, without the image:

- ``residual``: how far the controller's estimated cross-track error lands from where
  its previous estimate, carried one tick by the taxi's kinematics with the steering
  it commanded, put it (`propagate_estimate`): an estimate that jumps about, as a
  confused estimator's might;
- ``residual, 1 s``: its mean over the last second;
- ``|estimate|``: the estimated cross-track error's size;
- ``|steering|, 1 s``: the mean size of the steering over the last second.

Reads the recorded runs a study cached (``CACHE/runs/loop_recordings_*``, or
``record_runs_*`` before 2026-12-07: one folder an environment and run count) and renders nothing.

    python benchmarks/estimate_residual.py --cache /path/to/study/cache
"""

import argparse
from pathlib import Path

import numpy as np

from reachwatch.reach.chunk_files import is_chunk_file, read_chunk_file
from reachwatch.systems.dead_reckoning import propagate_estimate
from reachwatch.training.monitor_eval import tick_auroc


def trailing_mean(values: np.ndarray, ticks: int) -> np.ndarray:
    """Each tick's mean of ``values`` over the last ``ticks`` ticks (fewer at the start)."""
    sums = np.cumsum(np.r_[0.0, values])
    end = np.arange(1, len(values) + 1)
    start = np.maximum(end - ticks, 0)
    return (sums[end] - sums[start]) / (end - start)


def scores(signals: np.ndarray, *, speed: float, period: float) -> dict:
    """The online scores of one run's signals ``(T, 3)``: estimated cross-track error
    (m), estimated heading (deg), steering (rad), one row a tick."""
    estimate, steering = signals[:, :2], signals[:, 2]
    carried = propagate_estimate(estimate[:-1], steering[:-1], speed, period)
    residual = np.r_[0.0, np.abs(estimate[1:, 0] - carried[:, 0])]
    second = max(1, round(1.0 / period))
    return {"residual": residual, "residual, 1 s": trailing_mean(residual, second),
            "|estimate|": np.abs(estimate[:, 0]),
            "|steering|, 1 s": trailing_mean(np.abs(steering), second)}


def environment_aurocs(folder: Path, *, speed: float, period: float, duration: float,
                       within: float) -> dict:
    """Each score's tick AUROC over the runs recorded in ``folder`` (NaN with one class)."""
    per_score, ticks, failure = {}, [], []
    for chunk in sorted(p for p in folder.iterdir() if is_chunk_file(p.name)):
        z = read_chunk_file(chunk, ("signals", "ticks", "failure_time"))
        for signals, n, t in zip(z["signals"], z["ticks"], z["failure_time"]):
            if n < 2:
                continue
            for name, values in scores(signals[:n], speed=speed, period=period).items():
                per_score.setdefault(name, []).append(values)
            ticks.append(int(n))
            failure.append(float(t))
    return {name: tick_auroc(values, np.array(ticks), np.array(failure), period=period,
                             duration=duration, within=within)
            for name, values in per_score.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cache", type=Path, required=True,
                        help="a monitor study's cache (its runs/loop_recordings_* folders, or "
                        "record_runs_* of a study before 2026-12-07)")
    parser.add_argument("--speed", type=float, default=5.0, help="taxi speed, m/s")
    parser.add_argument("--period", type=float, default=0.05, help="control period, s")
    parser.add_argument("--duration", type=float, default=8.0, help="recorded run length, s")
    parser.add_argument("--within", type=float, default=4.0)
    args = parser.parse_args()
    # the runs of this version, else those a study cached before 2026-12-07 (not both:
    # a cache used before and after holds each environment under both names)
    folders = (sorted((args.cache / "runs").glob("loop_recordings_*"))
               or sorted((args.cache / "runs").glob("record_runs_*")))
    if not folders:
        parser.error(f"--cache: no recorded runs under {args.cache / 'runs'}")
    rows = []
    for folder in folders:
        aurocs = environment_aurocs(folder, speed=args.speed, period=args.period,
                                    duration=args.duration, within=args.within)
        rows.append((folder, aurocs))
    print(f"{len(rows)} environments' recorded runs, AUROC of 'fails within {args.within:g} s'")
    print("| score | environments | worst | median |")
    print("|---|---|---|---|")
    for name in rows[0][1]:
        values = np.array([a[name] for _, a in rows])
        values = values[np.isfinite(values)]
        print(f"| {name} | {len(values)} | {values.min():.3f} | {np.median(values):.3f} |")


if __name__ == "__main__":
    main()
