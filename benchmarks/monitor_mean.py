"""The mean of several finished monitors' risks, judged without rendering or training
again: is an ensemble worth building before it is built?

Each monitor is a variant of a finished study (``STUDY:VARIANT``, or ``STUDY`` for
every variant of it); the studies must have recorded the same runs (the same family,
splits, run counts and cache: only their training differs; checked, and the run
length against ``--period`` and ``--duration``). The mean is taken over the monitors'
calibrated risks at every tick (as ``benchmarks/monitor_seeds.py`` takes it; the
library's ``monitor.ensemble`` averages raw risks and calibrates the mean), then
judged as one monitor under the 1-of-1 rule: its calibration and held-out
environments' scores redrawn ``--draws`` times into calibration and new environments
as ``benchmarks/monitor_bound.py`` does (E[miss], pooled miss, needless flags at the
conformal threshold), and the worst and median held-out environment's AUROC of
"fails within ``within`` s" on the study's own split, over the environments where at
least ``--min-failing`` runs fail (one by default: with a run or two failing, an
environment's AUROC rests on their last ticks alone). Each monitor alone gets the same
rows. Each
study's Platt scaling was fitted on its own calibration environments, some of which a
draw judges as new: the weights the members get in the mean saw them (slightly
optimistic; the ranking of one monitor alone does not depend on it).

    python benchmarks/monitor_mean.py R40 R40_s1                 # every variant of both
    python benchmarks/monitor_mean.py "R40:single frame" "R40_s1:single frame"
"""

import argparse
import types
from pathlib import Path

import numpy as np

from monitor_bound import alpha_value, draw_figures, environment_scores
from reachwatch.pipeline.monitor_judge import watch_s
from reachwatch.pipeline.monitor_sections import read_study_result
from reachwatch.pipeline.monitor_spec import DETECTOR_ROW
from reachwatch.pipeline.monitor_saved import (check_run_length, check_same_runs, open_saved_risks,
                                              saved_risks, study_script)
from reachwatch.training.monitor_eval import tick_auroc

SPLITS = ("calibrate", "held_out")


def monitors(names) -> list:
    """``[(label, folder, variant)]`` for ``STUDY:VARIANT`` or ``STUDY`` (every variant
    but the detector's row)."""
    out = []
    for name in names:
        folder, _, variant = name.partition(":")
        result = read_study_result(Path(folder) / "monitor.json")
        variants = [variant] if variant else [v for v in result["variants"]
                                               if v != DETECTOR_ROW]
        for v in variants:
            if v not in result["variants"]:
                raise SystemExit(f"{folder} has no variant {v!r}: {list(result['variants'])}")
            out.append((f"{Path(folder).name}: {v}", Path(folder), v))
    return out


def mean_groups(chosen, saved: dict) -> dict:
    """``{split: [(risks per run, ticks, failure, fails_after) per environment]}`` of the
    mean of ``chosen`` monitors' calibrated risks, from the open ``risks.npz`` files
    ``saved`` (by folder)."""
    per = [{s: saved_risks(saved[folder], variant, s) for s in SPLITS}
           for _, folder, variant in chosen]
    out = {}
    for s in SPLITS:
        groups = []
        for e, (_, ticks, failure, after) in enumerate(per[0][s]):
            runs = [np.mean([m[s][e][0][i] for m in per], axis=0) for i in range(len(ticks))]
            groups.append((runs, ticks, failure, after))
        out[s] = groups
    return out


def judged(groups: dict, saved_file, *, alpha, lead, period, watch, within, draws, seed,
           min_failing: int = 1):
    """The figures of one monitor's ``groups`` (`mean_groups`): the redrawn splits'
    (`draw_figures`), and the worst and median held-out AUROC over the environments
    with at least ``min_failing`` runs failing within the watch."""
    envs = environment_scores([g for s in SPLITS for g in groups[s]], period=period, lead=lead)
    calibrate = len(groups["calibrate"])
    f = draw_figures(envs, calibrate, alpha, draws=draws, seed=seed)["every"]
    watched = saved_file["held_out/watched_failure_time" if "held_out/watched_failure_time"
                         in saved_file.files else "held_out/failure_time"]
    env = saved_file["held_out/environment"]
    aurocs = [tick_auroc(risks, ticks, watched[env == e], period=period, duration=watch,
                         within=within)
              for e, (risks, ticks, _, _) in enumerate(groups["held_out"])
              if np.sum(np.isfinite(watched[env == e])) >= min_failing]
    aurocs = [a for a in aurocs if np.isfinite(a)]
    return f, *((min(aurocs), float(np.median(aurocs))) if aurocs else (np.nan, np.nan))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("monitors", nargs="+", metavar="STUDY[:VARIANT]")
    p.add_argument("--draws", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--period", type=float, default=0.05, help="the control period (s)")
    p.add_argument("--duration", type=float, default=8.0, help="the studies' run length (s)")
    p.add_argument("--alone", action="store_true", help="also judge each monitor alone")
    p.add_argument("--min-failing", type=int, default=1,
                   help="the AUROC columns over held-out environments where at least this "
                        "many runs fail")
    p.add_argument("--alpha", type=alpha_value, default=None,
                   help="fix each draw's threshold at this alpha (default: the studies')")
    args = p.parse_args()
    chosen = monitors(args.monitors)
    folders = list(dict.fromkeys(folder for _, folder, _ in chosen))
    results = {f: read_study_result(f / "monitor.json") for f in folders}
    first = results[folders[0]]
    for f in folders[1:]:
        for key in ("alpha", "lead_s", "within_s"):
            if results[f][key] != first[key]:
                p.error(f"{f}: {key} {results[f][key]}, {folders[0]}: {first[key]}")
    saved = {f: open_saved_risks(f / "risks.npz") for f in folders}
    try:
        check_same_runs(saved, SPLITS)
        for f in folders:
            check_run_length(saved[f], period=args.period, duration=args.duration)
    except ValueError as e:
        p.error(str(e))
    within = first["within_s"]
    spec = types.SimpleNamespace(duration=args.duration, within=within)
    alpha = first["alpha"] if args.alpha is None else args.alpha
    shape = dict(alpha=alpha, lead=first["lead_s"], period=args.period,
                 watch=watch_s(spec), within=within, draws=args.draws, seed=args.seed,
                 min_failing=args.min_failing)
    rows = [(f"mean of {len(chosen)}", chosen)] if len(chosen) > 1 else []
    if args.alone or len(chosen) == 1:
        rows += [(label, [m]) for m in chosen for label in [m[0]]]
    print(f"{args.draws} draws; alpha {alpha:g}, lead {first['lead_s']:.2f} s, "
          f"1-of-1 rule; percent")
    where = ("" if args.min_failing <= 1 else
             f", environments with {args.min_failing}+ failing runs")
    print(f"| monitor | E[miss] | pooled miss | pooled miss p90 | needless flags | "
          f"needless p10-p90 | held-out AUROC, fails within {within:g} s: worst, "
          f"median{where} |")
    print("|---|---|---|---|---|---|---|")
    for label, members in rows:
        f, worst, median = judged(mean_groups(members, saved), saved[folders[0]], **shape)
        print(f"| {label} | {100 * f['E[miss]']:.1f} | {100 * f['pooled']:.1f} | "
              f"{100 * f['pooled p90']:.1f} | "
              f"{100 * f['needless']:.1f} | {100 * f['needless p10']:.1f}-"
              f"{100 * f['needless p90']:.1f} | {worst:.3f}, {median:.3f} |", flush=True)
    if len(chosen) > 1:
        print("mean of: " + "; ".join(label for label, _, _ in chosen))


if __name__ == "__main__":
    study_script(main)
