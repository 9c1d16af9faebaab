"""Flag rules read off a finished monitor study without rendering again: for each
variant and each k-of-n rule (flag when at least ``k`` of the last ``n`` ticks reached
the threshold, the guard's `FlagFilter`; offline
`reachwatch.training.monitor_eval.k_of_n_risks`), the conformal
threshold fixed on the study's calibration environments at each ``alpha``, and what it
gives on the held-out environments (pooled miss rate and needless-flag rate, Wilson 95 %
intervals) and on the named environments outside the family. The rule marked kept is
chosen on the calibration environments alone (fewest needless flags among the rules
whose threshold exists), as the study with ``keep: choose`` chooses (its default keeps
a monitor fixed in advance); the held-out figures are printed beside it, never used to
choose.

With ``--rank-within-environment`` each risk is first replaced by its rank among the
risks of the same environment's other runs (the share of their ticks below it; no
label is read, leave-one-run-out): a label-free normalisation of each environment's
shift, as a user could fit it from unlabelled runs in a new environment. The
conformal threshold is then fixed on the ranks of the calibration environments, which
stay exchangeable with the held-out ones (each environment's ranks use only its own
unlabelled runs).

    python benchmarks/monitor.py ... --out /tmp/reachwatch-monitor    # the study first
    python benchmarks/monitor_rules.py /tmp/reachwatch-monitor --rules 1/1 2/2 2/3 3/3
    python benchmarks/monitor_rules.py /tmp/reachwatch-monitor --rank-within-environment
"""

import argparse
from pathlib import Path

import numpy as np

from reachwatch.pipeline.monitor_sections import read_study_result
from reachwatch.pipeline.monitor_spec import DETECTOR_ROW
from reachwatch.pipeline.monitor_saved import open_saved_risks, saved_risks, study_script
from reachwatch.training.conformal import conformal_threshold, warning_scores
from reachwatch.training.monitor_eval import (flag_outcomes, k_of_n_risks, run_times,
                                              system_figures)


def _ranked(group):
    """``group`` with each run's risks replaced by their ranks among the ticks of the
    environment's other runs (leave-one-run-out; no label read)."""
    risks, ticks, failure, after = group
    every = np.sort(np.concatenate(risks)) if risks else np.zeros(0)
    ranks = []
    for risk in risks:      # ticks at or below, in every run less in this one
        below = (np.searchsorted(every, risk, side="right")
                 - np.searchsorted(np.sort(risk), risk, side="right"))
        ranks.append(below / max(len(every) - len(risk), 1))
    return ranks, ticks, failure, after


def _figures(groups, threshold, *, period, lead):
    pooled = {"failed": [], "warnable": [], "warned": [], "flagged": [], "failing_after": []}
    for risks, ticks, failure, after in groups:
        out = flag_outcomes(risks, ticks, failure, period=period, threshold=threshold, lead=lead,
                            fails_after=after)
        for k in pooled:
            pooled[k].append(out[k])
    return system_figures({k: np.concatenate(v) if v else np.zeros(0, bool)
                           for k, v in pooled.items()})


def _text(rate):
    if not rate["of"]:
        return "-"
    return (f"{100 * rate['rate']:.1f} [{100 * rate['lo']:.1f}, {100 * rate['hi']:.1f}] "
            f"({rate['count']}/{rate['of']})")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("study", help="the study's output folder (monitor.json, risks.npz)")
    p.add_argument("--rules", nargs="+", default=["1/1", "2/2", "2/3", "3/3", "3/5"],
                   metavar="K/N", help="k-of-n flag rules")
    p.add_argument("--alphas", type=float, nargs="+", default=[0.1, 0.2])
    p.add_argument("--period", type=float, default=0.05, help="the control period (s)")
    p.add_argument("--rank-within-environment", action="store_true",
                   help="replace each risk by its rank among the risks of the same "
                        "environment's other runs (label-free) before the threshold")
    args = p.parse_args()
    folder = Path(args.study)
    result = read_study_result(folder / "monitor.json")
    lead = result["lead_s"]
    rows, chosen = [], {}
    with open_saved_risks(folder / "risks.npz") as saved:
        splits = [s for s in ("calibrate", "held_out", "also_held_out")
                  if f"{s}/ticks" in saved.files]
        for variant in result["variants"]:
            data = {s: saved_risks(saved, variant, s) for s in splits}
            if args.rank_within_environment:
                data = {s: [_ranked(g) for g in groups] for s, groups in data.items()}
            for rule in args.rules:
                k, n = (int(v) for v in rule.split("/"))
                held = {s: [(k_of_n_risks(r, k, n), t, f, a) for r, t, f, a in g]
                        for s, g in data.items()}
                scores = [warning_scores(r, run_times(t, args.period), f, lead=lead)
                          for r, t, f, _ in held["calibrate"]]
                for alpha in args.alphas:
                    try:
                        tau = conformal_threshold(scores, alpha).threshold
                    except ValueError:
                        continue
                    figures = {s: _figures(g, tau, period=args.period, lead=lead)
                               for s, g in held.items()}
                    row = (variant, rule, alpha, tau, figures)
                    rows.append(row)
                    needless = figures["calibrate"]["needless"]["rate"]
                    if variant == DETECTOR_ROW:     # judged beside, never kept
                        continue
                    if alpha not in chosen or needless < chosen[alpha][4]["calibrate"][
                            "needless"]["rate"]:
                        chosen[alpha] = row
    print(f"lead {lead:.2f} s; thresholds fixed on the calibration environments"
          + ("; risks ranked within each environment (label-free)"
             if args.rank_within_environment else ""))
    print("| variant | flag rule (k/n) | alpha | threshold | calibration miss % | calibration "
          "needless % | held-out miss % [95 % CI] | held-out needless % [95 % CI] | outside "
          "the family: miss % | needless % |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for variant, rule, alpha, tau, f in rows:
        mark = " (kept)" if chosen.get(alpha) == (variant, rule, alpha, tau, f) else ""
        outside = f.get("also_held_out", {"miss": {"of": 0}, "needless": {"of": 0}})
        print(f"| {variant}{mark} | {rule} | {alpha:g} | {tau:.3f} | "
              f"{100 * f['calibrate']['miss']['rate']:.1f} | "
              f"{100 * f['calibrate']['needless']['rate']:.1f} | {_text(f['held_out']['miss'])} | "
              f"{_text(f['held_out']['needless'])} | {_text(outside['miss'])} | "
              f"{_text(outside['needless'])} |")


if __name__ == "__main__":
    study_script(main)
