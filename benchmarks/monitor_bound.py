"""The conformal miss-rate bound checked on many draws of new environments, read off
finished monitor studies without rendering or training again.

A study fixes its threshold on one draw of calibration environments and judges it on
a handful of held-out ones: a few dozen failing runs, too few to see whether the bound
holds. Its family's calibration and held-out environments are exchangeable, so this
script draws the split again ``--draws`` times (seeded): each draw takes as many
environments as the study calibrated on, fixes the threshold there
(`reachwatch.training.conformal.conformal_threshold`, the variant's kept flag rule, the
study's alpha) and judges the others as new environments. It reads the per-environment
scores the study saved (``scores`` in ``monitor.json``: each warnable failing run's
largest flag risk at least the fallback's lead before it fails, each safe run's
largest), so a draw costs no render. The environments the study trained on are not
among them.

Per variant and per way of fixing the threshold (every calibration environment, or
``given failures``: those with a warnable failing run alone), the means over draws of:

- ``E[miss]``: a new environment's miss rate, counting one where nothing fails as 0
  (what the default bound promises: at most alpha);
- ``E[miss | fails]``: the same over new environments where some run fails (what a
  user sees where it matters; ``given failures`` promises alpha for it);
- ``p90 | fails``: the 90th percentile of one such environment's miss rate;
- ``pooled``: missed over warnable failing runs of the new environments together;
- ``needless``: safe runs flagged, over safe runs, and its 10th and 90th percentiles
  over draws (how much the calibration draw moves it);
- ``refused``: the share of draws where no threshold reaches alpha; the other figures
  are over the draws where one does (with ``given failures``, those are the draws that
  put more environments with failures into calibration, fewer into the new ones).

The draws reuse the same environments, so they are not independent: the figures are
the expectation over splits of this one family sample, not over new families.

    python benchmarks/monitor.py ... --out OUT            # the study first
    python benchmarks/monitor_bound.py OUT [OUT2 ...] --draws 1000
    python benchmarks/monitor_bound.py OUT --calibrate 32     # more per draw, fewer judged
"""

import argparse
from pathlib import Path

import numpy as np

from reachwatch.pipeline.monitor_sections import read_study_result
from reachwatch.training.conformal import NoConformalThreshold, conformal_threshold, miss_rate

MODES = {"every": False, "given failures": True}


def draw_figures(environments, calibrate: int, alpha: float, *, draws: int,
                 seed: int = 0) -> dict:
    """``{mode: {figure: mean over draws}}`` for ``environments``, a list of
    ``(warning scores, safe runs' largest risks)`` per environment (see the module's
    docstring)."""
    if not 0 < calibrate < len(environments):
        raise ValueError(f"need more environments than the {calibrate} calibrated on, "
                         f"got {len(environments)}")
    rng = np.random.default_rng(seed)
    out = {m: {"every": [], "fails": [], "pooled": [], "needless": [], "refused": 0,
               "shares": []} for m in MODES}
    for _ in range(draws):
        order = rng.permutation(len(environments))
        cal = [environments[i] for i in order[:calibrate]]
        new = [environments[i] for i in order[calibrate:]]
        for mode, given in MODES.items():
            f = out[mode]
            try:
                tau = conformal_threshold([w for w, _ in cal], alpha,
                                          given_failures=given).threshold
            except NoConformalThreshold:
                f["refused"] += 1
                continue
            shares = [miss_rate(w, tau) for w, _ in new if len(w)]
            f["every"].append(sum(shares) / len(new))
            if shares:
                f["fails"].append(float(np.mean(shares)))
                f["shares"] += shares
            warnable = sum(len(w) for w, _ in new)
            if warnable:
                f["pooled"].append(sum(int(np.sum(w < tau)) for w, _ in new) / warnable)
            safe = sum(len(s) for _, s in new)
            if safe:
                f["needless"].append(sum(int(np.sum(s >= tau)) for _, s in new) / safe)
    mean = lambda v: float(np.mean(v)) if v else float("nan")
    quantile = lambda v, q: float(np.quantile(v, q)) if v else float("nan")
    return {m: {"E[miss]": mean(f["every"]), "E[miss | fails]": mean(f["fails"]),
                "p90 | fails": quantile(f["shares"], 0.9),
                "pooled": mean(f["pooled"]), "needless": mean(f["needless"]),
                "needless p10": quantile(f["needless"], 0.1),
                "needless p90": quantile(f["needless"], 0.9),
                "refused": f["refused"] / draws} for m, f in out.items()}


def family_environments(result: dict, variant: str) -> list:
    """The family's calibration and held-out environments of a study's ``variant``:
    ``(warning scores, safe runs' largest risks)`` each, under its kept flag rule."""
    scores = result["variants"][variant]["scores"]
    return [(np.asarray(e["warning"], float), np.asarray(e["safe_max"], float))
            for split in ("calibrate", "held_out") for e in scores[split]]


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("studies", nargs="+", help="finished studies' output folders (monitor.json)")
    p.add_argument("--draws", type=int, default=1000, help="random splits per study")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variants", nargs="*", help="only these variants (default: all)")
    p.add_argument("--calibrate", type=int, default=None,
                   help="environments calibrated on per draw (default: as many as the study)")
    args = p.parse_args()
    print("| study | variant | threshold fixed on | E[miss] | E[miss given fails] | "
          "p90 given fails | pooled miss | needless | needless p10-p90 | refused |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for folder in args.studies:
        result = read_study_result(Path(folder) / "monitor.json")
        calibrate = args.calibrate or len(
            next(iter(result["variants"].values()))["scores"]["calibrate"])
        for variant in result["variants"]:
            if args.variants and variant not in args.variants:
                continue
            envs = family_environments(result, variant)
            figures = draw_figures(envs, calibrate, result["alpha"], draws=args.draws,
                                   seed=args.seed)
            for mode, f in figures.items():
                name = variant + (" (kept)" if variant == result["kept"] else "")
                print(f"| {Path(folder).name} | {name} | {mode} | "
                      + " | ".join(f"{100 * f[k]:.1f}" for k in (
                          "E[miss]", "E[miss | fails]", "p90 | fails", "pooled", "needless"))
                      + f" | {100 * f['needless p10']:.1f}-{100 * f['needless p90']:.1f} | "
                      f"{100 * f['refused']:.1f} |")
    print(f"alpha as each study's; {args.draws} draws of the family's calibration and "
          f"held-out environments, " + (f"{args.calibrate} calibrated on" if args.calibrate
                                        else "as many calibrated on as in the study")
          + " (percent)")


if __name__ == "__main__":
    main()
