"""How the monitor study judges one monitor's risks (`reachwatch.pipeline.monitor_study`):
system figures per environment and pooled at a threshold (`judge_environments`), the
k-of-n rule and conformal threshold fixed on the calibration environments
(`choose_flag_rule`), a monitor's whole row from its raw risks (`_judge_monitor`), and
the controller's prediction error ranked the same way (`prediction_error_aurocs`)."""

import numpy as np

from reachwatch.diagrams import make_controller
from reachwatch.diagrams.controller import estimate_size
from reachwatch.training.baselines import estimate_error_of
from reachwatch.training.conformal import (NoConformalThreshold, PlattCalibration, brier_score,
                                           conformal_threshold, expected_calibration_error,
                                           per_environment_bound, reliability_curve,
                                           warning_scores)
from reachwatch.training.monitor_eval import (decisive_scores, flag_outcomes, k_of_n_risks,
                                              labelled_ticks, run_times, system_figures,
                                              tick_auroc)


def watch_s(spec) -> float:
    """How long the study watches the loop alone to judge and label a run: its
    recordings' ``duration`` and the risk's horizon ``within`` after them
    (`monitor_runs.watched_failure_times`)."""
    return float(spec.duration) + float(spec.within)


def _labelled(groups, risks, *, period, watch, within):
    """`labelled_ticks` of every group's runs, concatenated, labelled from their failure
    times over the study's longer watch of the loop alone (``watch`` s,
    `monitor_runs.watched_failure_times`)."""
    pairs = [labelled_ticks(r, g["ticks"], g["watched_failure_time"], period=period,
                            duration=watch, within=within) for g, r in zip(groups, risks)]
    return (np.concatenate([p[0] for p in pairs] + [np.zeros(0, np.int8)]),
            np.concatenate([p[1] for p in pairs] + [np.zeros(0)]))


def fails_after(group) -> np.ndarray:
    """Per run of ``group``: survived its recording, and failed within the study's
    longer watch of the loop alone (censored, not safe: `flag_outcomes`)."""
    return (np.isfinite(np.asarray(group["watched_failure_time"], float))
            & ~np.isfinite(np.asarray(group["failure_time"], float)))


def judge_environments(groups, risks, *, threshold, period, lead, watch, flags=None):
    """Per environment and pooled system figures at ``threshold`` (flags read from
    ``flags``, the risks a k-of-n flag rule acts on, when given; AUROC from ``risks``,
    labelled over the ``watch`` s of `_labelled`)."""
    per_env = []
    pooled = {"failed": [], "warnable": [], "warned": [], "flagged": [], "failing_after": []}
    for i, (r, g) in enumerate(zip(risks, groups)):
        out = flag_outcomes(r if flags is None else flags[i], g["ticks"], g["failure_time"],
                            period=period, threshold=threshold, lead=lead,
                            fails_after=fails_after(g))
        for key in pooled:
            pooled[key].append(out[key])
        per_env.append({"environment": g["name"], **system_figures(out),
                        "auroc_4s": tick_auroc(r, g["ticks"], g["watched_failure_time"],
                                               period=period, duration=watch, within=4.0)})
    return per_env, system_figures({k: np.concatenate(v) if v else np.zeros(0, bool)
                                    for k, v in pooled.items()})


def check_calibration_bounds(spec, calibrate, *, period, lead):
    """Before any training: a `NoConformalThreshold` in one line when no k-of-n rule of
    ``spec.flag_rules`` can reach ``spec.alpha`` whatever the monitor's risks, from the
    recorded calibration runs ``calibrate`` alone: too few environments with a warnable
    failing run (with ``given_failures``), or too many runs failing before any warning
    can help. A risk of 1 at every tick flags as early as any monitor can, so its
    conformal bound at threshold 0 is every monitor's (`choose_flag_rule` would refuse
    the same after the trainings)."""
    refused = None
    for k, n in spec.flag_rules:
        ones = [[np.ones(int(t)) for t in g["ticks"]] for g in calibrate]
        env_scores = [warning_scores(r, run_times(g["ticks"], period), g["failure_time"],
                                     lead=lead)
                      for r, g in zip((k_of_n_risks(group, k, n) for group in ones), calibrate)]
        try:
            conformal_threshold(env_scores, spec.alpha, given_failures=spec.given_failures)
            return
        except NoConformalThreshold as e:
            refused = refused or NoConformalThreshold(
                f"monitor: the recorded calibration runs cannot bound the miss rate, whatever "
                f"the monitor (flag rule [{k}, {n}]): {e}")
    raise refused


def choose_flag_rule(spec, calibrate, risks, *, period, lead):
    """Of ``spec.flag_rules``' k-of-n rules, the one with the fewest needless flags on
    the calibration environments at its conformal threshold (fixed there): ``([k, n],
    flags, threshold, calibration figures)``, ``flags`` the risks the rule acts on per
    split (`k_of_n_risks`). A rule whose threshold cannot reach alpha is skipped."""
    best, refused = None, None
    for k, n in spec.flag_rules:
        flags = {s: [k_of_n_risks(group, k, n) for group in v] for s, v in risks.items()}
        env_scores = [warning_scores(r, run_times(g["ticks"], period), g["failure_time"],
                                     lead=lead) for r, g in zip(flags["calibrate"], calibrate)]
        try:
            chosen = conformal_threshold(env_scores, spec.alpha,
                                         given_failures=spec.given_failures)
        except ValueError as e:
            refused = refused or e
            continue
        calibration, pooled = judge_environments(
            calibrate, risks["calibrate"], threshold=chosen.threshold, period=period,
            lead=lead, watch=watch_s(spec), flags=flags["calibrate"])
        needless = pooled["needless"]["count"] / max(1, pooled["needless"]["of"])
        if best is None or needless < best[4]:
            best = ([int(k), int(n)], flags, chosen, calibration, needless)
    if best is None:
        raise refused
    return best[:4]


def _judge_monitor(spec, data, raw, *, period, lead, calibrated=True):
    """One monitor's row of the study from its raw risks (``raw[split][env][run]``, one
    array per run): Platt scaling fitted on the calibration environments' ticks, the
    k-of-n rule and conformal threshold fixed there (`choose_flag_rule`), and the
    held-out figures. The threshold reads the calibrated risk (a history monitor's
    output), or with ``calibrated`` False the raw score (an image detector's output, as
    its guarded loop reads it; Platt scaling is monotone, so the flags are the same
    where its slope is positive); calibration error and Brier score are the calibrated
    risk's either way. Returns ``(row, platt, chosen, rule, risks)``, ``risks`` those the
    threshold reads."""
    watch = watch_s(spec)
    y, q = _labelled(data["calibrate"], raw["calibrate"], period=period, watch=watch,
                     within=spec.within)
    try:
        platt, fitted = PlattCalibration.fit(q, y == 1), True
    except ValueError:                      # one class among the calibration ticks
        platt, fitted = PlattCalibration(), False
    probabilities = {k: [[platt(r) for r in group] for group in v] for k, v in raw.items()}
    risks = probabilities if calibrated else raw
    rule, flags, chosen, calibration = choose_flag_rule(
        spec, data["calibrate"], risks, period=period, lead=lead)
    needless = [c["needless"] for c in calibration]
    row = {"threshold": chosen.threshold, "statement": chosen.statement(lead),
           "given_failures": chosen.given_failures,
           "calibration_miss_rate": chosen.calibration_miss_rate,
           "per_environment_bound_90": per_environment_bound(
               [c["miss"]["rate"] if c["miss"]["of"] else 0.0 for c in calibration
                if c["miss"]["of"] or not chosen.given_failures], 0.1),
           "calibration_needless": sum(n["count"] for n in needless) / max(
               1, sum(n["of"] for n in needless)),
           "platt": [platt.a, platt.b], "platt_fitted": fitted, "flag_rule": rule}
    for k in ("held_out", "also_held_out"):
        per_env, pooled = judge_environments(
            data[k], risks[k], threshold=chosen.threshold, period=period, lead=lead,
            watch=watch, flags=flags[k])
        y, p = _labelled(data[k], probabilities[k], period=period, watch=watch,
                         within=spec.within)
        row[k] = {"environments": per_env, "pooled": pooled,
                  "ece": expected_calibration_error(p, y == 1) if len(y) else float("nan"),
                  "brier": brier_score(p, y == 1) if len(y) else float("nan"),
                  "reliability": [a.tolist() for a in reliability_curve(p, y == 1)]
                  if len(y) else []}
    # what any threshold does with the kept rule: each environment's warnable failing
    # runs' warning scores and its other runs' largest flag risk (a run is flagged
    # iff it is >= tau)
    row["scores"] = {k: [decisive_scores(r, g["ticks"], g["failure_time"], period=period,
                                         lead=lead, fails_after=fails_after(g))
                         for r, g in zip(flags[k], data[k])]
                     for k in ("calibrate", "held_out", "also_held_out")}
    return row, platt, chosen, rule, risks


def prediction_error_aurocs(application, scenario, splits: dict, *, period: float,
                            duration: float) -> dict:
    """Per split ``{name: groups}`` (`record_splits`'), per environment, the AUROC of
    "fails within 4 s" of the controller's prediction error along its runs
    (`baselines.EstimateError`: its estimate leads the recorded signals,
    `add_monitor_signals`), watched for ``duration`` s; NaN where the application does
    not say what its controller estimates (`Application.true_estimate`), the
    controller has no estimate, or its estimate is NaN or infinite along a run
    (`EstimateError.refusal`)."""
    error = estimate_error_of(application)
    k = estimate_size(make_controller(application.resolved(scenario).controller)) \
        if error else 0

    def auroc(g):
        ticks = list(enumerate(g["ticks"]))
        if not k or not ticks or error.refusal(
                np.concatenate([g["state"][i, :n] for i, n in ticks]),
                np.concatenate([g["signals"][i, :n, :k] for i, n in ticks])) is not None:
            return float("nan")             # among them: an estimate NaN along a run
        return tick_auroc([error(g["state"][i, :n], g["signals"][i, :n, :k]) if n
                           else np.zeros(0) for i, n in enumerate(g["ticks"])], g["ticks"],
                          g["watched_failure_time"], period=period, duration=duration,
                          within=4.0)
    return {name: [auroc(g) for g in groups] for name, groups in splits.items()}
