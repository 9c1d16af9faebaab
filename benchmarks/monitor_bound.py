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
- ``over alpha``: the share of draws whose new environments' mean miss rate (the
  same count) is above alpha: how often one held-out group judged against the bound
  would seem to break it, the bound holding in expectation;
- ``E[miss | fails]``: the same over new environments where some run fails (what a
  user sees where it matters; ``given failures`` promises alpha for it);
- ``p90 | fails``: the 90th percentile of one such environment's miss rate;
- ``pooled``: missed over warnable failing runs of the new environments together, and
  its 90th percentile over draws (``pooled p90``: the pooled miss rate one held-out
  group reads in the unluckiest tenth of draws);
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
    python benchmarks/monitor_bound.py OUT --alpha 0.05       # another guarantee, same scores
"""

import argparse
from pathlib import Path

import numpy as np

from reachwatch.pipeline.monitor_sections import read_study_result
from reachwatch.pipeline.monitor_spec import DETECTOR_ROW
from reachwatch.pipeline.monitor_saved import open_saved_risks, saved_risks, study_script
from reachwatch.training.conformal import NoConformalThreshold, conformal_threshold, miss_rate
from reachwatch.training.monitor_eval import decisive_scores, k_of_n_risks

MODES = {"every": False, "given failures": True}


def alpha_value(text: str) -> float:
    """The argparse type of ``--alpha`` (here and in ``monitor_mean.py``): a miss rate
    strictly between 0 and 1."""
    value = float(text)
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"a miss rate between 0 and 1, got {text}")
    return value


def draw_figures(environments, calibrate: int, alpha: float, *, draws: int,
                 seed: int = 0) -> dict:
    """``{mode: {figure: mean over draws}}`` for ``environments``, a list of
    ``(warning scores, safe runs' largest risks)`` per environment (see the module's
    docstring)."""
    if not 0 < calibrate < len(environments):
        raise ValueError(f"need more environments than the {calibrate} calibrated on, "
                         f"got {len(environments)}")
    rng = np.random.default_rng(seed)
    out = {m: _tally() for m in MODES}
    for _ in range(draws):
        order = rng.permutation(len(environments))
        cal = [environments[i] for i in order[:calibrate]]
        new = [environments[i] for i in order[calibrate:]]
        for mode, given in MODES.items():
            try:
                tau = conformal_threshold([w for w, _ in cal], alpha,
                                          given_failures=given).threshold
            except NoConformalThreshold:
                out[mode]["refused"] += 1
                continue
            _judge_new(out[mode], new, tau)
    return {m: _summary(f, draws, alpha, given_failures=MODES[m]) for m, f in out.items()}


def _tally() -> dict:
    return {"every": [], "fails": [], "pooled": [], "needless": [], "refused": 0,
            "shares": []}


def _judge_new(f: dict, new, tau: float):
    """Adds one draw's figures on its ``new`` environments at ``tau`` to the tally ``f``."""
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


def _summary(f: dict, draws: int, alpha: float, *, given_failures: bool = False) -> dict:
    """The means over draws of a tally; ``over alpha`` of the quantity the threshold
    bounds (with ``given_failures``, the mean over new environments where runs fail)."""
    mean = lambda v: float(np.mean(v)) if v else float("nan")
    quantile = lambda v, q: float(np.quantile(v, q)) if v else float("nan")
    bounded = f["fails"] if given_failures else f["every"]
    return {"E[miss]": mean(f["every"]), "over alpha": mean([m > alpha for m in bounded]),
            "E[miss | fails]": mean(f["fails"]),
            "p90 | fails": quantile(f["shares"], 0.9),
            "pooled": mean(f["pooled"]), "pooled p90": quantile(f["pooled"], 0.9),
            "needless": mean(f["needless"]),
            "needless p10": quantile(f["needless"], 0.1),
            "needless p90": quantile(f["needless"], 0.9),
            "refused": f["refused"] / draws}


def choice_figures(candidates: dict, calibrate: int, alpha: float, *, draws: int,
                   seed: int = 0, given_failures: bool = False) -> dict:
    """The study's choice of its kept monitor, repeated in every draw: of
    ``candidates`` (``{name: environments}``, each as `draw_figures` takes them, in the
    same order), the one with the fewest needless flags on the draw's calibration
    environments at its own conformal threshold (fixed there, on those with a warnable
    failing run alone with ``given_failures``; a candidate without one is skipped),
    judged on the draw's new environments. Returns ``{"chosen": figures, "fixed":
    figures of the first candidate in every draw, "times chosen": {name: draws}}``
    (figures as `draw_figures`' mode of the same ``given_failures``; the same draws as
    it for the same ``seed``)."""
    names = list(candidates)
    count = len(candidates[names[0]])
    if any(len(envs) != count for envs in candidates.values()):
        raise ValueError("every candidate needs the same environments")
    if not 0 < calibrate < count:
        raise ValueError(f"need more environments than the {calibrate} calibrated on, "
                         f"got {count}")
    rng = np.random.default_rng(seed)
    chosen, fixed, times = _tally(), _tally(), dict.fromkeys(names, 0)
    for _ in range(draws):
        order = rng.permutation(count)
        best = None
        for name in names:
            cal = [candidates[name][i] for i in order[:calibrate]]
            try:
                tau = conformal_threshold([w for w, _ in cal], alpha,
                                          given_failures=given_failures).threshold
            except NoConformalThreshold:
                if name == names[0]:
                    fixed["refused"] += 1
                continue
            new = [candidates[name][i] for i in order[calibrate:]]
            if name == names[0]:
                _judge_new(fixed, new, tau)
            safe = sum(len(s) for _, s in cal)
            needless = sum(int(np.sum(s >= tau)) for _, s in cal) / max(1, safe)
            if best is None or needless < best[0]:
                best = (needless, name, new, tau)
        if best is None:
            chosen["refused"] += 1
            continue
        times[best[1]] += 1
        _judge_new(chosen, best[2], best[3])
    summary = dict(draws=draws, alpha=alpha, given_failures=given_failures)
    return {"chosen": _summary(chosen, **summary), "fixed": _summary(fixed, **summary),
            "times chosen": times}


def family_environments(result: dict, variant: str) -> list:
    """The family's calibration and held-out environments of a study's ``variant``:
    ``(warning scores, safe runs' largest risks)`` each, under its kept flag rule."""
    scores = result["variants"][variant]["scores"]
    return [(np.asarray(e["warning"], float), np.asarray(e["safe_max"], float))
            for split in ("calibrate", "held_out") for e in scores[split]]


def environment_scores(groups, *, period: float, lead: float) -> list:
    """``(warning scores, safe runs' largest risks)`` per environment, as `draw_figures`
    takes them, of ``groups`` as `saved_risks` gives them (``(risks per run, ticks,
    failure times, fails_after)``; `decisive_scores`)."""
    out = []
    for risks, ticks, failure, after in groups:
        d = decisive_scores(risks, ticks, failure, period=period, lead=lead, fails_after=after)
        out.append((np.asarray(d["warning"], float), np.asarray(d["safe_max"], float)))
    return out


def rule_candidates(folder, rules, *, period: float) -> dict:
    """``{"variant, k/n": environments}`` of a finished study (its ``risks.npz``): every
    variant (the detector's row left out: never kept) under every k-of-n rule of
    ``rules``, its calibration and held-out environments as `family_environments`
    gives them, in that order (the first variant's first rule first)."""
    result = read_study_result(Path(folder) / "monitor.json")
    out = {}
    with open_saved_risks(Path(folder) / "risks.npz") as saved:
        for variant in result["variants"]:
            if variant == DETECTOR_ROW:
                continue
            data = [g for split in ("calibrate", "held_out")
                    for g in saved_risks(saved, variant, split)]
            kept = "{}/{}".format(*result["variants"][variant].get("flag_rule", [1, 1]))
            by_rule = {}
            for rule in dict.fromkeys([kept, *rules]):
                k, n = (int(v) for v in rule.split("/"))
                envs = environment_scores([(k_of_n_risks(r, k, n), t, f, a)
                                           for r, t, f, a in data],
                                          period=period, lead=result["lead_s"])
                # the variant's own rule must give the scores its study saved: else the
                # period given is not the study's, and every warning is read wrong
                if rule == kept and any(len(w) != len(s) or not np.allclose(w, s) for (w, _), (
                        s, _) in zip(envs, family_environments(result, variant))):
                    raise ValueError(f"{folder}: {variant!r} under its rule {kept} does not "
                                     f"give the warning scores its study saved: give the "
                                     f"study's --period (now {period:g} s)")
                by_rule[rule] = envs
            out.update({f"{variant}, {rule}": by_rule[rule] for rule in rules})
    return out


FIGURES = ("E[miss]", "over alpha", "E[miss | fails]", "p90 | fails", "pooled",
           "pooled p90", "needless")


def _cells(f: dict) -> str:
    return (" | ".join(f"{100 * f[k]:.1f}" for k in FIGURES)
            + f" | {100 * f['needless p10']:.1f}-{100 * f['needless p90']:.1f} | "
            f"{100 * f['refused']:.1f} |")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("studies", nargs="+", help="finished studies' output folders (monitor.json)")
    p.add_argument("--draws", type=int, default=1000, help="random splits per study")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variants", nargs="*", help="only these variants (default: all)")
    p.add_argument("--calibrate", type=int, default=None,
                   help="environments calibrated on per draw (default: as many as the study)")
    p.add_argument("--choose-among", nargs="+", metavar="K/N",
                   help="instead: repeat the study's choice of its kept monitor in every "
                        "draw, among every variant under each of these k-of-n rules (read "
                        "from risks.npz), beside the first variant under the first rule "
                        "fixed in advance")
    p.add_argument("--period", type=float, default=0.05,
                   help="the control period (s), for --choose-among")
    p.add_argument("--alpha", type=alpha_value, default=None,
                   help="fix each draw's threshold at this alpha (default: each study's): "
                        "what another guarantee would cost, from the same saved scores")
    args = p.parse_args()
    if args.choose_among:
        if args.variants:
            p.error("--choose-among chooses among every variant: leave out --variants")
        for rule in args.choose_among:
            k, _, n = rule.partition("/")
            if not (k.isdigit() and n.isdigit()):
                p.error(f"--choose-among takes K/N rules such as 2/3, got {rule!r}")
        return _choice_table(args)
    print("| study | variant | threshold fixed on | E[miss] | draws over alpha | "
          "E[miss given fails] | "
          "p90 given fails | pooled miss | pooled miss p90 | needless | needless p10-p90 | "
          "refused |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for folder in args.studies:
        result = read_study_result(Path(folder) / "monitor.json")
        calibrate = args.calibrate or len(
            next(iter(result["variants"].values()))["scores"]["calibrate"])
        for variant in result["variants"]:
            if args.variants and variant not in args.variants:
                continue
            envs = family_environments(result, variant)
            figures = draw_figures(envs, calibrate, _alpha(args, result), draws=args.draws,
                                   seed=args.seed)
            for mode, f in figures.items():
                name = variant + (" (kept)" if variant == result["kept"] else "")
                print(f"| {Path(folder).name} | {name} | {mode} | " + _cells(f))
    print(f"{_alpha_text(args)}; {args.draws} draws of the family's calibration and "
          f"held-out environments, " + (f"{args.calibrate} calibrated on" if args.calibrate
                                        else "as many calibrated on as in the study")
          + " (percent)")


def _alpha(args, result) -> float:
    return result["alpha"] if args.alpha is None else args.alpha


def _alpha_text(args) -> str:
    return "alpha as each study's" if args.alpha is None else f"alpha {args.alpha:g}"


def _choice_table(args):
    print("| study | kept monitor | E[miss] | draws over alpha | E[miss given fails] | "
          "p90 given fails | pooled miss | pooled miss p90 | needless | needless p10-p90 | "
          "refused |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    chosen_counts = []
    for folder in args.studies:
        result = read_study_result(Path(folder) / "monitor.json")
        try:
            candidates = rule_candidates(folder, args.choose_among, period=args.period)
        except ValueError as e:
            raise SystemExit(f"monitor_bound.py: {e}") from None
        calibrate = args.calibrate or len(
            next(iter(result["variants"].values()))["scores"]["calibrate"])
        given = bool(next(v for n, v in result["variants"].items()
                          if n != DETECTOR_ROW).get("given_failures"))
        f = choice_figures(candidates, calibrate, _alpha(args, result), draws=args.draws,
                           seed=args.seed, given_failures=given)
        name = Path(folder).name
        print(f"| {name} | chosen in each draw among {len(candidates)} | " + _cells(f["chosen"]))
        print(f"| {name} | fixed: {next(iter(candidates))} | " + _cells(f["fixed"]))
        chosen_counts.append(f"{name}: " + ", ".join(
            f"{k} {v}" for k, v in f["times chosen"].items() if v))
    print(f"{_alpha_text(args)}; {args.draws} draws (percent). Times each was chosen: "
          + "; ".join(chosen_counts))


if __name__ == "__main__":
    study_script(main)
