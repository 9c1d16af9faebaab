"""The monitor study's findings as a page shows them (`study_blocks`): the report's
section (`monitor_section`) and the benchmark's Markdown (`markdown_tables`) render the
same blocks. `pipeline.monitor_study` computes what they show."""

import json
from pathlib import Path

import numpy as np

from reachwatch.systems.files import nan_for_null
from reachwatch.training.conformal import NoConformalThreshold, conformal_threshold
from reachwatch.training.metrics import auroc
from reachwatch.training.monitor_eval import rate

from .monitor_saved import StudyFileError
from .monitor_spec import DETECTOR_ROW, ORACLE


def _number(value) -> str:
    """``value`` to 3 decimals; "-" for a figure of nothing (NaN or None)."""
    return f"{value:.3f}" if value is not None and np.isfinite(value) else "-"


#: What every monitor study's result holds (`pipeline.monitor_study`'s ``result``).
STUDY_RESULT_KEYS = ("lead_s", "within_s", "alpha", "variants")


def read_study_result(path) -> dict:
    """A monitor study's ``monitor.json`` as the study returned it: the study writes a
    number that is not finite as null (strict JSON, `systems.files.strict_json`). A null
    is read back as NaN (a rate of no runs), except in a ``warning`` or ``safe_max``
    list of scores, where it is -inf: a warnable run no flag rule can warn in time
    (missed at every threshold, and ranked below every run), or a safe run with no tick
    (never flagged). A file that is missing, damaged or not a study's result is a
    `StudyFileError` naming it."""
    try:
        result = json.loads(Path(path).read_text())
    except OSError as e:
        raise StudyFileError(f"{path}: cannot read a monitor study's result "
                             f"({e.strerror or e}); give a finished study's monitor.json") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise StudyFileError(f"{path}: not a monitor study's result (not JSON: {e})") from None
    missing = ([key for key in STUDY_RESULT_KEYS if key not in result]
               if isinstance(result, dict) else list(STUDY_RESULT_KEYS))
    if missing:
        raise StudyFileError(f"{path}: not a monitor study's result (it has no "
                             f"{', '.join(missing)})")
    return nan_for_null(result, lists={"warning": -np.inf, "safe_max": -np.inf})


def bounded_miss_rates(environments):
    """What the conformal bound speaks of, observed on judged environments (their rows
    of a study's result): ``(mean miss rate with an environment where no run fails
    counting 0, mean over those with a warnable failing run, how many those are, how
    many environments)``; None without environments."""
    if not environments:
        return None
    shares = [e["miss"]["rate"] for e in environments if e["miss"]["of"]]
    return (sum(shares) / len(environments), float(np.mean(shares)) if shares else float("nan"),
            len(shares), len(environments))


def observed_bound_text(observed, kept, alpha) -> str:
    """One sentence: `bounded_miss_rates` of the held-out environments beside alpha, the
    bounded one first (over every environment, or over those where runs fail when the
    threshold was fixed ``given_failures``)."""
    every, failing, with_failures, count = observed
    every_text = (f"{100 * every:.1f} % over all {count}, an environment where no run fails "
                  f"counting 0")
    failing_text = (f"{100 * failing:.1f} % over the {with_failures} where some run fails"
                    if with_failures else "no run failed in them")
    first, second = ((failing_text, every_text) if kept.get("given_failures")
                     else (every_text, failing_text))
    return (f"Observed on the held-out environments of the family, the mean miss rate is "
            f"{first} (the quantity bounded at {100 * alpha:.1f} %), and {second}. One draw "
            f"of calibration environments: the bound is an average over such draws.")


def rate_text(r):
    """A `rate` as ``"12.5 % [4.1, 29.9] (3/24)"`` (Wilson 95 %), ``"-"`` without trials."""
    if not r["of"]:
        return "-"
    return (f"{100 * r['rate']:.1f} % [{100 * r['lo']:.1f}, {100 * r['hi']:.1f}] "
            f"({r['count']}/{r['of']})")


def pooled_scores(entries) -> tuple:
    """``(warning, safe_max)`` of a group's environments (`row["scores"][group]`, as
    `run_monitor_study` records them), each pooled into one array."""
    return (np.concatenate([e["warning"] for e in entries] + [[]]),
            np.concatenate([e["safe_max"] for e in entries] + [[]]))


def threshold_tradeoff(row: dict, alphas=(0.1, 0.2, 0.3, 0.5)) -> list:
    """For each target ``alpha``: the conformal threshold from a variant's calibration
    scores (`row["scores"]`, as `run_monitor_study` records them) and what it gives on
    the held-out environments, pooled: ``[alpha, threshold, miss count, warnable
    failing runs, needless count, runs that did not fail]`` (threshold None when the
    calibration environments are too few for that alpha), bounded as the variant's own
    threshold was (``given_failures`` or not)."""
    out = []
    calibrate, held_out = row["scores"]["calibrate"], row["scores"]["held_out"]
    for alpha in alphas:
        try:
            tau = conformal_threshold([np.asarray(e["warning"]) for e in calibrate], alpha,
                                      given_failures=bool(row.get("given_failures"))).threshold
        except NoConformalThreshold:
            out.append([alpha, None, 0, 0, 0, 0])
            continue
        warning, safe = pooled_scores(held_out)
        out.append([alpha, tau, int(np.sum(warning < tau)), len(warning),
                    int(np.sum(safe >= tau)), len(safe)])
    return out


def run_ranking(row: dict, group: str, miss: float = 0.1) -> dict:
    """How well a variant's risk (under its kept flag rule) ranks whole runs of
    ``group`` (``calibrate`` or ``held_out``), pooled, from `row["scores"]`: ``auroc``,
    a warnable failing run's warning score against a run that did not fail's largest
    risk (NaN without both); ``needless``, the share of runs that did not fail flagged
    at the highest threshold that still warns all but ``miss`` of the warnable failing
    runs, that threshold set on these runs themselves: the fewest needless flags any
    threshold gives at that miss rate (None without runs of both kinds, or when more
    than ``miss`` of them score ``-inf``: a k-of-n rule that cannot flag them before
    the lead, so no threshold warns them)."""
    warning, safe = pooled_scores(row["scores"][group])
    warning = np.sort(warning)
    if not len(warning) or not len(safe):
        return {"auroc": float("nan"), "needless": None}
    tau = warning[int(np.floor(miss * len(warning) + 1e-9))]   # misses: warning < tau
    labels = np.r_[np.ones(len(warning), bool), np.zeros(len(safe), bool)]
    return {"auroc": float(auroc(labels, np.r_[warning, safe])),
            "needless": rate(int(np.sum(safe >= tau)), len(safe)) if np.isfinite(tau)
            else None}


def same_needless(result: dict, group: str = "held_out") -> list:
    """Each variant against the single-image detector's row (`DETECTOR_ROW`, when the
    study has one) at the same needless flags, offline over ``group``'s runs, pooled:
    ``[variant, warned, needless, detector warned, points]``, ``warned`` and ``needless``
    the variant's `rate`s at its threshold and flag rule, ``detector warned`` the
    detector's at the lowest threshold that flags no more of the runs that did not fail
    (that threshold set on these runs themselves, which favours the detector), and
    ``points`` the difference in warned percent. Empty without a detector row."""
    detector = result["variants"].get(DETECTOR_ROW)
    if detector is None or group not in detector.get("scores", {}):
        return []
    d_warning, d_safe = pooled_scores(detector["scores"][group])
    out = []
    for name, row in result["variants"].items():
        if name == DETECTOR_ROW or group not in row.get("scores", {}):
            continue
        warning, safe = pooled_scores(row["scores"][group])
        tau = row["threshold"]
        warned, needless = int(np.sum(warning >= tau)), int(np.sum(safe >= tau))
        # thresholds the detector can take (a score of -inf is no threshold: its k-of-n
        # rule cannot flag there at all)
        candidates = np.unique(np.r_[d_warning[np.isfinite(d_warning)],
                                     d_safe[np.isfinite(d_safe)], np.inf])
        allowed = [t for t in candidates if np.sum(d_safe >= t) <= needless]
        t = min(allowed)
        d_warned = int(np.sum(d_warning >= t))
        w, d = rate(warned, len(warning)), rate(d_warned, len(d_warning))
        out.append([name, w, rate(needless, len(safe)), d,
                    100 * (w["rate"] - d["rate"]) if len(warning) else float("nan")])
    return out


def rendered_text(rows: dict) -> str:
    """How many of each monitor's guarded runs were rendered (`monitor_guarded.
    guarded_missions`), as a sentence; empty for a result that does not say."""
    counts = [f"{name} {c['rendered']} of {c['runs']}" for name, c in rows.items()
              if "rendered" in c]
    if not counts:
        return ""
    return (" Until its first flag a guarded loop is the loop alone, so a run whose risk "
            "along its recording never reached the threshold is the loop alone's; rendered: "
            + ", ".join(counts) + " (the rest never reached it; the first such run of each "
            "environment was rendered and came out as the loop alone's).")


def per_environment_text(kept: dict) -> str:
    """The kept monitor's estimate for one new environment, as a sentence: the
    calibration environments' conformal quantile at 90 % of their miss rates, and how
    many of them had no warnable failing run (counted as missing none)."""
    calibrate = kept.get("scores", {}).get("calibrate")
    without = (sum(not len(e["warning"]) for e in calibrate)
               if calibrate is not None and not kept.get("given_failures") else 0)
    if calibrate is not None and without == len(calibrate):
        return ("For one new environment: no calibration environment had a warnable "
                "failing run, so their miss rates say nothing of one where runs fail.")
    note = (f" {without} of the {len(calibrate)} had no warnable failing run and count as "
            f"missing none." if without else "")
    return (f"For one new environment, an estimate, not a guarantee: the calibration "
            f"environments' miss rates at this threshold put nine in ten environments at "
            f"or below {100 * kept['per_environment_bound_90']:.1f} % (their conformal "
            f"quantile at 90 %; exchangeable environments).{note} The threshold was "
            f"fitted on those same environments, so it is optimistic.")


def uncalibrated_text(result: dict) -> str:
    """A sentence naming the variants whose Platt scaling could not be fitted (their
    calibration ticks all of one class), or empty."""
    names = [name for name, row in result["variants"].items()
             if not row.get("platt_fitted", True)]
    if not names:
        return ""
    return (f"Not calibrated: {', '.join(names)}. The calibration environments' ticks "
            f"were all of one class (no run failed within {result['within_s']:g} s of "
            f"one, or every one did), so Platt scaling could not be fitted: "
            f"{'its' if len(names) == 1 else 'their'} risks, ECE and Brier score are the "
            f"raw ones.")


def kept_text(result: dict) -> str:
    """How the kept monitor was kept, and what that means for the bound."""
    among = result.get("kept_chosen_among")
    if among == 0:
        return (" The kept monitor and its flag rule were fixed before the calibration "
                "environments were seen: the bound is exact for it.")
    among = f" among {among} (variants and flag rules)" if among else ""
    return (f" The kept monitor was chosen{among} on the same calibration environments, "
            f"which the bound does not account for: "
            f"it is exact for a monitor fixed before them, and the chosen one's miss rate on "
            f"new environments is higher (monitor.keep).")


def study_blocks(result: dict) -> list:
    """The study's findings as blocks a page renders: ``("heading", text)``,
    ``("text", text)`` and ``("table", header, rows)``: held-out environments pooled
    per variant (with the oracle and the prediction-error baseline), the guarantee, the
    guarded real loop, and the kept variant per environment."""
    blocks = []
    within = result["within_s"]
    guarded_header = ["monitor", "runs", "failures alone", "failures guarded",
                      "prevented % [95 % CI]", "needless stops % [95 % CI]",
                      f"failing <= {within:g} s after the window: stopped",
                      "distance guarded / alone"]
    for key, where in (("guarded", "the held-out environments of the family"),
                       ("guarded_also_held_out", "the named environments outside the family")):
        if result.get(key):
            blocks += [("heading", f"Guarded real loop (braking), pooled over {where}"),
                       ("table", guarded_header, [
                           [name, c["runs"], c["failed_alone"], c["failed_guarded"],
                            rate_text(c["prevented_rate"]), rate_text(c["needless_rate"]),
                            (f"{c['stopped_failing_after']} of {c['failing_after']}"
                             if "failing_after" in c else "- (an older result)"),
                            f"{c['distance_guarded_m'] / max(1e-9, c['distance_alone_m']):.3f}"]
                           for name, c in result[key].items()]),
                       ("text", f"A failure prevented is one the loop alone has within the "
                                f"run; a stop is needless when the loop alone survives the "
                                f"run and the {within:g} s after it (the risk's horizon: a "
                                f"stop near the run's end claims a failure up to {within:g} s "
                                f"past it). Runs the loop alone survives but leaves the safe "
                                f"set within {within:g} s after are counted apart."
                                + rendered_text(result[key]))]
    kept = result["variants"][result["kept"]]
    warnable = result["oracle"]["held_out"]["pooled"]["warnable"]
    if warnable["of"]:
        blocks.append(("text", f"Of the held-out environments' failing runs, "
                               f"{rate_text(warnable)} lasted at least {result['lead_s']:.2f} s: "
                               f"only those can be warned in time by any monitor with this "
                               f"fallback (the ceiling; the oracle warns them all). Miss rates "
                               f"below are over those warnable runs."))
    blocks += [("text", kept["statement"] + kept_text(result)),
               ("text", per_environment_text(kept))]
    if uncalibrated_text(result):
        blocks.append(("text", uncalibrated_text(result)))
    observed = bounded_miss_rates(kept["held_out"]["environments"])
    if observed is not None:
        blocks.append(("text", observed_bound_text(observed, kept, result["alpha"])))
    for group, title in (("held_out", "held-out environments of the family"),
                         ("also_held_out", "named environments outside the family (no "
                                           "guarantee: not drawn from it)")):
        first = next(iter(result["variants"].values()))[group]
        if not first["environments"]:
            continue
        rows = []
        for name, row in result["variants"].items():
            r = row[group]
            aurocs = [e["auroc_4s"] for e in r["environments"] if np.isfinite(e["auroc_4s"])]
            rows.append([name + (" (kept)" if name == result["kept"] else ""),
                         f"{row['threshold']:.3f}" + (" on its score" if row.get("kind") ==
                                                      "detector" else "") + (
                             " ({} of {} ticks)".format(*row["flag_rule"])
                             if row.get("flag_rule", [1, 1]) != [1, 1] else ""),
                         rate_text(r["pooled"]["miss"]),
                         rate_text(r["pooled"]["needless"]),
                         f"{min(aurocs):.3f}" if aurocs else "-", _number(r["ece"]),
                         _number(r["brier"])])
        o = result["oracle"][group]["pooled"]
        base = [b for b in result["prediction_error_auroc_4s"][group] if np.isfinite(b)]
        rows += [[ORACLE, "-", rate_text(o["miss"]), rate_text(o["needless"]), "-", "-", "-"],
                 ["prediction error (privileged)", "-", "-", "-",
                  f"{min(base):.3f}" if base else "-", "-", "-"]]
        blocks += [("heading", f"Offline on recorded runs, pooled over the {title}; a miss is "
                               f"a failing run with no flag {result['lead_s']:.2f} s before it "
                               f"fails"),
                   ("table", ["monitor", "threshold", "miss % [95 % CI]",
                              "needless flags % [95 % CI]", "worst AUROC, fails within 4 s",
                              "ECE", "Brier"], rows)]
    if all("scores" in row for row in result["variants"].values()):
        rows = []
        for name, row in result["variants"].items():
            for alpha, tau, missed, warnable_runs, needless, safe in threshold_tradeoff(row):
                rows.append([name, f"{alpha:g}", "-" if tau is None else f"{tau:.3f}",
                             rate_text(rate(missed, warnable_runs)) if tau is not None else "-",
                             rate_text(rate(needless, safe)) if tau is not None else "-"])
        blocks += [("heading", "The price of the guarantee: each target alpha's conformal "
                               "threshold on the calibration environments, and what it gives "
                               "on the held-out ones (pooled)"),
                   ("table", ["monitor", "alpha", "threshold", "miss % [95 % CI]",
                              "needless flags % [95 % CI]"], rows)]
        rows = []
        for name, row in result["variants"].items():
            cal, held = run_ranking(row, "calibrate"), run_ranking(row, "held_out")
            rows.append([name, *(f"{a:.3f}" if np.isfinite(a) else "-"
                                 for a in (cal["auroc"], held["auroc"])),
                         rate_text(held["needless"]) if held["needless"] else "-"])
        blocks += [("heading", "How each variant ranks whole runs: a warnable failing run's "
                               "warning score against the largest risk of a run that did not "
                               "fail (its flag rule's), pooled"),
                   ("table", ["monitor", "run AUROC, calibration", "run AUROC, held out",
                              "needless flags % at a 10 % miss, held out, threshold set on "
                              "them (the least any threshold gives)"], rows)]
    for group, title in (("held_out", "held-out environments of the family"),
                         ("also_held_out", "named environments outside the family")):
        if not kept[group]["environments"]:
            continue
        rows = [[name, rate_text(w), rate_text(n), rate_text(d),
                 f"{points:+.1f}" if np.isfinite(points) else "-"]
                for name, w, n, d, points in same_needless(result, group)]
        if rows:
            blocks += [("heading", f"Each variant against the single-image detector at the "
                                   f"same needless flags, offline, pooled over the {title}: "
                                   f"the detector's threshold is the lowest that flags no "
                                   f"more runs that did not fail, set on these runs (in "
                                   f"the detector's favour)"),
                       ("table", ["monitor", "warned % [95 % CI]", "needless flags % [95 % CI]",
                                  "detector warned % [95 % CI]", "points over the detector"],
                        rows)]
    rows = []
    for group in ("held_out", "also_held_out"):
        for e, b, o in zip(kept[group]["environments"],
                           result["prediction_error_auroc_4s"][group],
                           result["oracle"][group]["environments"]):
            fails = result["failing_runs"][group][e["environment"]]
            rows.append([e["environment"], f"{fails[0]}/{fails[1]} ({o['warnable']['count']})",
                         rate_text(e["miss"]),
                         rate_text(e["needless"]), _number(e["auroc_4s"]), _number(b),
                         rate_text(o["miss"])])
    blocks += [("heading", f"{result['kept']} (the kept variant), per environment"),
               ("table", ["environment", "failing runs (warnable)", "miss % [95 % CI]",
                          "needless flags % [95 % CI]", "AUROC, fails within 4 s",
                          "prediction-error AUROC", "oracle miss"], rows)]
    return blocks


def markdown_tables(result: dict) -> str:
    """`study_blocks` as Markdown."""
    lines = []
    for block in study_blocks(result):
        if block[0] == "heading":
            lines += [f"#### {block[1]}", ""]
        elif block[0] == "text":
            lines += [block[1], ""]
        else:
            header, rows = block[1], block[2]
            lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
            lines += ["| " + " | ".join(map(str, r)) + " |" for r in rows] + [""]
    return "\n".join(lines)


def monitor_section(page, run):
    """The report's section on the monitor study (when the run has one)."""
    outputs = run.outputs.get("monitor") or {}
    if not outputs:
        return
    result = read_study_result(run.path(outputs["result"]))
    page.section("Runtime monitor on environments it has never seen", "monitor")
    page.text(f"A monitor over the image history predicts the risk of failing within "
              f"{result['within_s']:g} s; its threshold is chosen on calibration environments "
              f"of the random family before any held-out environment is seen. The fallback "
              f"brakes and needs {result['lead_s']:.2f} s. Kept: {result['kept']} "
              + ("(fixed before calibration)." if result.get("kept_chosen_among") == 0 else
                 "(fewest needless flags on the calibration environments).")
              + (f" Each variant is an ensemble: the mean of {result['ensemble']} trainings' "
                 f"raw risks (other seeds), calibrated and thresholded as one monitor."
                 if result.get("ensemble", 1) > 1 else ""))
    for block in study_blocks(result):
        if block[0] in ("heading", "text"):
            page.text(block[1])
        else:
            page.table(block[1], block[2])
    if result.get("reliability_figure"):
        page.images([str(Path(outputs["result"]).parent / result["reliability_figure"])],
                    "reliability of the risk on the held-out environments")
