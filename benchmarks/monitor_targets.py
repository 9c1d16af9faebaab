"""The monitor study's figures against the targets the monitor is judged by, read from
a finished study (``OUT/monitor/monitor.json``): no render, no training.

    python benchmarks/monitor_targets.py out/monitor/monitor/monitor.json

Prints one markdown table: each target, the kept monitor's figure (and the
single-image detector's and the oracle's where the target compares with them), with
Wilson 95 % intervals, and whether it is met. The conformal bound gets two rows: the
one held-out group as the target states it, and over redrawn splits of the family's
calibration and held-out environments (`benchmarks/monitor_bound.py`), which is what
the bound speaks of: a valid bound reads above alpha on one group of 8 environments
a fifth to a third of the time. The online tick rate is not in a study:
`benchmarks/online.py` measures it.
"""

import argparse
import math
from pathlib import Path

import numpy as np

from monitor_bound import draw_figures, family_environments
from reachwatch.pipeline.monitor_guarded import ORACLE
from reachwatch.pipeline.monitor_sections import (bounded_miss_rates, rate_text,
                                                  read_study_result, same_needless)
from reachwatch.pipeline.monitor_saved import study_script
from reachwatch.pipeline.monitor_spec import DETECTOR_ROW

#: The targets' numbers: prevented >= 0.85 of the oracle's; needless stops <= 10 % (upper
#: bound <= 13 %); miss rate <= 10 % (upper bound <= 13 %); ECE <= 0.05; worst AUROC of
#: "fails within 4 s" 5 points over the detector's; +10 points over the detector.
OF_ORACLE, RATE, UPPER, ECE, AUROC_POINTS, DETECTOR_POINTS = 0.85, 0.10, 0.13, 0.05, 5.0, 10.0

#: Redrawn splits of the family's calibration and held-out environments behind the
#: bound's row over draws (`monitor_bound.draw_figures`).
REDRAWS = 1000

#: The study's groups of held-out environments: the family's, and those outside it.
GROUPS = {"held_out": ("family", "guarded"), "also_held_out": ("nights", "guarded_also_held_out")}


def _worst_auroc(row, group):
    values = [e["auroc_4s"] for e in row[group]["environments"] if np.isfinite(e["auroc_4s"])]
    return min(values) if values else float("nan")


def _verdict(ok) -> str:
    return "-" if ok is None else ("met" if ok else "not met")


def target_rows(result: dict) -> list:
    """``[target, group, measured, verdict]`` rows for the kept monitor of ``result``."""
    kept = result["kept"]
    row = result["variants"][kept]
    detector = result["variants"].get(DETECTOR_ROW)
    rows = []
    for group, (name, guarded_key) in GROUPS.items():
        if not row[group]["environments"]:
            continue
        guarded = result.get(guarded_key) or {}
        mine, oracle = guarded.get(kept), guarded.get(ORACLE)
        if mine and oracle and oracle["prevented"]:
            share = mine["prevented"] / oracle["prevented"]
            rows.append(["prevented >= 0.85 of the oracle's", name,
                         f"{mine['prevented']} of the oracle's {oracle['prevented']} ({share:.2f}); "
                         f"{rate_text(mine['prevented_rate'])} of failures, the oracle "
                         f"{rate_text(oracle['prevented_rate'])}",
                         _verdict(share >= OF_ORACLE)])
        if mine:
            needless = mine["needless_rate"]
            rows.append(["needless stops <= 10 % (upper bound <= 13 %)", name,
                         rate_text(needless),
                         _verdict(needless["rate"] <= RATE and needless["hi"] <= UPPER
                                  if needless["of"] else None)])
        theirs = guarded.get(DETECTOR_ROW)
        if mine and theirs:
            points = 100 * (mine["prevented_rate"]["rate"] - theirs["prevented_rate"]["rate"])
            rows.append(["+10 points over the detector (guarded, each at its threshold)", name,
                         f"prevented {rate_text(mine['prevented_rate'])} with needless "
                         f"{rate_text(mine['needless_rate'])}; the detector "
                         f"{rate_text(theirs['prevented_rate'])} with "
                         f"{rate_text(theirs['needless_rate'])} ({points:+.1f} points)",
                         "-"])
        for variant, warned, needless, d_warned, points in same_needless(result, group):
            if variant == kept:
                rows.append(["+10 points over the detector at the same needless flags "
                             "(offline)", name,
                             f"warned {rate_text(warned)} against {rate_text(d_warned)} at "
                             f"needless {rate_text(needless)} ({points:+.1f} points)",
                             _verdict(points >= DETECTOR_POINTS if math.isfinite(points)
                                      else None)])
        miss = row[group]["pooled"]["miss"]
        rows.append(["miss rate <= 10 % (upper bound <= 13 %)", name, rate_text(miss),
                     _verdict(miss["rate"] <= RATE and miss["hi"] <= UPPER
                              if miss["of"] else None)])
        if group == "held_out":
            observed = bounded_miss_rates(row[group]["environments"])
            if observed:
                every, failing, with_failures, count = observed
                # what the threshold bounds: the mean with an environment where no run
                # fails counting 0, or (fixed `given_failures`) over those where runs fail
                bounded = failing if row.get("given_failures") else every
                rows.append(["the conformal bound (alpha) on the mean miss rate", name,
                             f"{100 * every:.1f} % over {count} environments (0 where none "
                             f"fails), {100 * failing:.1f} % over the {with_failures} with "
                             f"failures ({'the latter' if row.get('given_failures') else 'the former'}"
                             f" bounded); alpha {100 * result['alpha']:.0f} %",
                             _verdict(bounded <= result["alpha"] if math.isfinite(bounded)
                                      else None)])
            redrawn = redrawn_bound_row(result, name)
            if redrawn:
                rows.append(redrawn)
        ece = row[group]["ece"]
        rows.append(["ECE <= 0.05", name, f"{ece:.3f}",
                     _verdict(ece <= ECE if math.isfinite(ece) else None)])
        worst = _worst_auroc(row, group)
        baseline = [b for b in result["prediction_error_auroc_4s"][group] if np.isfinite(b)]
        text = f"{worst:.3f}"
        ok = None
        if detector is not None and math.isfinite(worst):
            theirs_worst = _worst_auroc(detector, group)
            text += f", the detector's {theirs_worst:.3f}"
            ok = (100 * (worst - theirs_worst) >= AUROC_POINTS
                  if math.isfinite(theirs_worst) else None)
        aurocs = [e["auroc_4s"] for e in row[group]["environments"]]
        above = [a > b for a, b in zip(aurocs, result["prediction_error_auroc_4s"][group])
                 if np.isfinite(a) and np.isfinite(b)]
        if baseline:
            text += f"; above the prediction error in {sum(above)} of {len(above)} environments"
            ok = None if ok is None else ok and all(above)      # no detector: not judged
        rows.append(["worst AUROC (fails within 4 s) >= detector's + 5 points, above the "
                     "prediction error everywhere", name, text, _verdict(ok)])
    return rows


def redrawn_bound_row(result: dict, name: str):
    """The bound's row over `REDRAWS` redrawn splits of the family's calibration and
    held-out environments (the kept monitor's saved scores): what alpha bounds is an
    expectation over such draws, which one held-out group only samples, and how often
    one group reads above alpha. No verdict: for a monitor fixed in advance the mean
    over random splits of one sample is at most alpha whatever the monitor. None when
    the study saved no calibration scores. Not drawn (a row that says why) where the
    calibration environments were recorded with other run counts than the held-out
    ones: they are not exchangeable then."""
    kept = result["kept"]
    row = result["variants"][kept]
    scores = row.get("scores", {})
    if not (scores.get("calibrate") and scores.get("held_out")):
        return None
    counts = {k: sorted({int(n) for _, n in (result.get("failing_runs", {}).get(k) or {}).values()})
              for k in ("calibrate", "held_out")}
    if counts["calibrate"] and counts["held_out"] and counts["calibrate"] != counts["held_out"]:
        return ["the conformal bound (alpha) on the mean miss rate, over redrawn splits", name,
                f"not drawn: the calibration environments were recorded with "
                f"{'/'.join(map(str, counts['calibrate']))} runs each and the held-out ones "
                f"with {'/'.join(map(str, counts['held_out']))}, so a split could not swap "
                f"them", "-"]
    calibrate, judged = len(scores["calibrate"]), len(scores["held_out"])
    mode = "given failures" if row.get("given_failures") else "every"
    f = draw_figures(family_environments(result, kept), calibrate, result["alpha"],
                     draws=REDRAWS)[mode]
    among = result.get("kept_chosen_among")
    how = ("the kept monitor fixed before calibration" if among == 0 else
           "the kept monitor's choice on the calibration environments not repeated in the "
           "draws (it raises the miss rate)")
    bounded, over = (("E[miss | fails]", "where runs fail") if mode == "given failures"
                     else ("E[miss]", "an environment without failures counting 0"))
    return ["the conformal bound (alpha) on the mean miss rate, over redrawn splits "
            "(context for the row above: no verdict)", name,
            f"{100 * f[bounded]:.1f} % ({over}) over {REDRAWS} splits of the {calibrate + judged} "
            f"environments ({calibrate} to calibrate, {judged} new; "
            f"{100 * f['over alpha']:.0f} % of the groups of {judged} read above alpha, "
            f"{100 * f['refused']:.0f} % of draws refused); {how}. For a monitor fixed in "
            f"advance the mean over random splits is at most alpha by the draws' "
            f"exchangeability; the share above alpha is how often one group misleads",
            "-"]


def markdown(result: dict) -> str:
    lines = [f"Kept monitor: {result['kept']} (risk of failing within {result['within_s']:g} s, "
             f"the fallback's lead {result['lead_s']:.2f} s, alpha {result['alpha']:g}).", "",
             "| target | held out | measured | verdict |", "|---|---|---|---|"]
    lines += ["| " + " | ".join(r) + " |" for r in target_rows(result)]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("result", type=Path, help="a finished study's monitor.json")
    args = parser.parse_args(argv)
    if not args.result.is_file():
        parser.error(f"{args.result}: no such file (a finished study writes monitor.json)")
    print(markdown(read_study_result(args.result)))


if __name__ == "__main__":
    study_script(main)
