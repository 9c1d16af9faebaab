"""Several trainings of one monitor study, and the mean of their risks, read off their
outputs without rendering or training again. Each OUT is a finished
`benchmarks/monitor.py` study on the same recordings (the same family, split, runs
and cache) that differs only in how the monitors were trained (``--train-seed``,
``--lr-schedule``, ``--epochs``). For each variant it prints, per training and for the
tick-by-tick mean of the trainings' calibrated risks (not what ``monitor.ensemble``
computes, which averages the members' raw risks and calibrates the mean; a study with
``--ensemble K`` is one OUT here):

- how the risk ranks ticks, "fails within the study's horizon": AUROC pooled over a
  split's environments, at the worst environment and the median one;
- how it ranks whole runs (flag rule 1/1): a warnable failing run's largest risk at
  least the fallback's lead before it fails against a run that did not fail's largest
  risk (AUROC), and the fewest needless flags any threshold gives at a 10 % miss, the
  threshold set on those runs themselves;
- the system figures: the study's own flag-rule choice and conformal threshold on the
  calibration environments (`pipeline.monitor_study`), then the pooled miss and
  needless-flag rates on the held-out environments and on the named ones outside the
  family. ``--period``, ``--duration`` and ``--flag-rules`` must be the study's: each
  training's threshold must equal the one its study saved, and the runs that did not
  fail must last ``duration`` (both checked); the studies must share their horizon,
  lead, alpha and variants (checked).

    python benchmarks/monitor.py ... --train-seed 0 --out OUT0     # the studies first
    python benchmarks/monitor.py ... --train-seed 1 --out OUT1
    python benchmarks/monitor_seeds.py OUT0 OUT1 --variants "single frame"
"""

import argparse
import types

import numpy as np

from reachwatch.pipeline.monitor_sections import read_study_result, run_ranking
from reachwatch.pipeline.monitor_spec import DETECTOR_ROW
from reachwatch.pipeline.monitor_judge import fails_after
from reachwatch.pipeline.monitor_saved import (check_run_length, check_same_runs, open_saved_risks,
                                              saved_groups, study_script)
from reachwatch.pipeline.monitor_study import choose_flag_rule, judge_environments
from reachwatch.training.monitor_eval import decisive_scores, rate, tick_auroc

SPLITS = ("calibrate", "held_out", "also_held_out")


def _groups(saved, flat: dict):
    """Per split: the environments and each one's risks per run (`saved_groups`), from
    ``flat`` (the split's risks of every tick, concatenated). A study saved before the
    longer watch has no watched times: its failure times stand in (and `main` judges it
    on its recordings' duration)."""
    groups, risks = {}, {}
    for split in SPLITS:
        groups[split], risks[split] = saved_groups(saved, split, flat[split])
    return groups, risks


def _ranking(groups, risks, *, period, watch, within, lead):
    """Tick AUROC (pooled, worst and median environment; labelled over the ``watch`` s)
    run AUROC and the fewest needless flags at a 10 % miss (`run_ranking`, flag rule
    1/1) over ``groups``."""
    shape = dict(period=period, duration=watch, within=within)
    pooled = tick_auroc([r for runs in risks for r in runs],
                        np.concatenate([g["ticks"] for g in groups]),
                        np.concatenate([g["watched_failure_time"] for g in groups]), **shape)
    per_env = [a for a in (tick_auroc(runs, g["ticks"], g["watched_failure_time"], **shape)
                           for g, runs in zip(groups, risks)) if np.isfinite(a)]
    worst, median = (min(per_env), float(np.median(per_env))) if per_env else (np.nan, np.nan)
    ranked = run_ranking({"scores": {"runs": [
        decisive_scores(runs, g["ticks"], g["failure_time"], period=period, lead=lead,
                        fails_after=fails_after(g))
        for g, runs in zip(groups, risks)]}}, "runs")
    return pooled, worst, median, ranked["auroc"], ranked["needless"] or rate(0, 0)


def _pct(r) -> str:
    if not r["of"]:
        return "    - (0/0)"
    return f"{100 * r['count'] / r['of']:5.1f} ({r['count']}/{r['of']})"


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("outs", nargs="+", help="finished studies' --out folders")
    p.add_argument("--variants", nargs="+", help="variants to show (default: all)")
    p.add_argument("--period", type=float, default=0.05, help="the loop's control period (s)")
    p.add_argument("--duration", type=float, default=8.0, help="the study's run length (s)")
    p.add_argument("--flag-rules", nargs="+", default=["1/1"], metavar="K/N",
                   help="the study's --flag-rules (its default: 1/1)")
    args = p.parse_args()
    studies = [read_study_result(f"{out}/monitor.json") for out in args.outs]
    saved = [open_saved_risks(f"{out}/risks.npz") for out in args.outs]
    first = studies[0]
    lead, within = first["lead_s"], first["within_s"]
    for out, study in zip(args.outs[1:], studies[1:]):
        for key in ("lead_s", "within_s", "alpha"):
            if study[key] != first[key]:
                p.error(f"{out}: {key} {study[key]:g}, {args.outs[0]}: {first[key]:g}: "
                        f"the studies must differ only in how they trained")
        if list(study["variants"]) != list(first["variants"]):
            p.error(f"{out} trained other variants than {args.outs[0]}")
    try:
        check_run_length(saved[0], period=args.period, duration=args.duration)
        check_same_runs(dict(zip(args.outs, saved)), SPLITS)
    except ValueError as e:
        p.error(str(e))
    # a study saved before the longer watch is judged on its recordings alone
    watched = f"{SPLITS[0]}/watched_failure_time" in saved[0]
    # the study's threshold settings, as `choose_flag_rule` reads them from its spec
    given = {bool(row.get("given_failures")) for study in studies
             for name, row in study["variants"].items() if name != DETECTOR_ROW}
    if len(given) > 1:
        p.error("the studies fixed their thresholds differently (given_failures)")
    spec = types.SimpleNamespace(alpha=first["alpha"], duration=args.duration,
                                 within=within if watched else 0.0,
                                 flag_rules=[list(map(int, r.split("/")))
                                             for r in args.flag_rules],
                                 given_failures=given.pop() if given else False)
    watch = args.duration + spec.within
    shape = dict(period=args.period, watch=watch, within=within, lead=lead)
    for variant in args.variants or list(first["variants"]):
        print(f"\n{variant}: fails within {within:g} s; lead {lead:.2f} s; alpha {spec.alpha:g}")
        print(f"{'training':28s} {'split':14s} tick AUROC pooled/worst/median  run AUROC  "
              f"needless at 10 % miss  | rule, threshold: miss %, needless flags %")
        rows = [(out, {split: s[f"{variant}/{split}/risk"].astype(float) for split in SPLITS},
                 study["variants"][variant]["threshold"])
                for out, s, study in zip(args.outs, saved, studies)]
        if len(rows) > 1:
            rows.append(("mean of the risks", {split: np.mean([r[1][split] for r in rows], axis=0)
                                               for split in SPLITS}, None))
        for name, flat, saved_threshold in rows:
            groups, risks = _groups(saved[0], flat)
            rule, flags, chosen, _ = choose_flag_rule(spec, groups["calibrate"], risks,
                                                      period=args.period, lead=lead)
            if saved_threshold is not None and not np.isclose(chosen.threshold, saved_threshold):
                p.error(f"{name}: threshold {chosen.threshold:.4f} here, {saved_threshold:.4f} "
                        f"in its study: give the study's --period, --duration and --flag-rules")
            for split in SPLITS:
                if not groups[split]:
                    continue
                tick, worst, median, run_auc, needless = _ranking(groups[split], risks[split],
                                                                  **shape)
                _, pooled = judge_environments(
                    groups[split], risks[split], threshold=chosen.threshold,
                    period=args.period, lead=lead, watch=watch, flags=flags[split])
                print(f"{name:28s} {split:14s} {tick:.3f} / {worst:.3f} / {median:.3f}"
                      f"        {run_auc:.3f}      {_pct(needless)}  | {rule[0]}/{rule[1]}, "
                      f"{chosen.threshold:.3f}: {_pct(pooled['miss'])}, "
                      f"{_pct(pooled['needless'])}")


if __name__ == "__main__":
    study_script(main)
