"""What a runtime monitor does on recorded runs of the loop it watches, judged as a
system: which failing runs it warned at least ``lead`` s (the fallback's need) before
they failed, which runs that did not fail it flagged anyway, and the same for the
oracle monitor that flags exactly when the true time to failure drops to ``lead``.

Up to its first flag a guarded loop is the loop alone, so on runs of the loop alone
the miss rate read here is the guarded loop's; whether a timely flag prevents the
failure, and how often a flag stops the plant for nothing, only runs of the guarded
real loop answer."""

import math

import numpy as np

from reachwatch.reach.fidelity import wilson_interval
from reachwatch.systems.detector import flags_at
from reachwatch.systems.flag_filter import check_k_of_n
from reachwatch.reach.outcomes import fails_within, time_to_failure

from .conformal import warning_scores
from .metrics import auroc


def run_labels(ticks: int, failure_time, *, period: float, duration: float,
               within: float) -> np.ndarray:
    """The labels of one run's ``ticks`` ticks (``period`` s apart, the run ``duration``
    s long unless it failed at ``failure_time``): `fails_within` ``within`` s of
    `time_to_failure`, -1 where censoring leaves it unknown."""
    return fails_within(*time_to_failure(np.arange(int(ticks)) * period, failure_time,
                                         duration), within)


def labelled_ticks(risks, ticks, failure_times, *, period: float, duration: float,
                   within: float):
    """``(labels, risks)`` of every tick of the runs whose label the runs settle
    (`run_labels` >= 0), concatenated."""
    labels, scores = [np.zeros(0, np.int8)], [np.zeros(0)]
    for risk, n, failure in zip(risks, ticks, failure_times):
        label = run_labels(n, failure, period=period, duration=duration, within=within)
        labels.append(label[label >= 0])
        scores.append(np.asarray(risk, float)[label >= 0])
    return np.concatenate(labels), np.concatenate(scores)


def decisive_scores(risks, ticks, failure_times, *, period: float, lead: float,
                    fails_after=None) -> dict:
    """What any threshold does with one environment's runs: ``warning``, each warnable
    failing run's largest risk at least ``lead`` s before it fails (`warning_scores`),
    and ``safe_max``, each safe run's largest risk (a run is flagged iff its score is
    >= the threshold; a run with no tick: -inf, never flagged). A safe run did not fail, and (``fails_after``, per run, when
    given) does not fail soon after its recording ends either (`flag_outcomes`)."""
    failed = np.isfinite(np.asarray(failure_times, float))
    safe = ~failed & ~_failing_after(fails_after, failed)
    return {"warning": warning_scores(risks, run_times(ticks, period), failure_times,
                                      lead=lead).tolist(),
            "safe_max": [float(np.max(x)) if len(x) else -math.inf
                         for x, keep in zip(risks, safe) if keep]}


def _failing_after(fails_after, failed) -> np.ndarray:
    """``fails_after`` as bools, False where the run failed within its recording (None:
    no run known to fail after it)."""
    if fails_after is None:
        return np.zeros(len(failed), bool)
    fails_after = np.asarray(fails_after, bool).reshape(-1)
    if len(fails_after) != len(failed):
        raise ValueError(f"fails_after needs one entry per run, got {len(fails_after)} for "
                         f"{len(failed)} runs")
    return fails_after & ~failed


def run_times(ticks, period: float) -> list:
    """Each run's tick times (s), ``ticks[i]`` of them."""
    return [np.arange(int(n)) * period for n in ticks]


def flag_outcomes(risks, ticks, failure_times, *, period: float, threshold: float,
                  lead: float, fails_after=None) -> dict:
    """Per run (bool arrays): ``failed``; ``warnable`` (failed, with a tick at least
    ``lead`` s before the failure: a monitor could have warned it in time); ``warned``
    (warnable, with a flag at least ``lead`` s before the failure); ``flagged`` (any
    tick with risk >= ``threshold``, or NaN: `reachwatch.systems.detector.flags_at`);
    ``failing_after``: survived its recording but fails soon after it (``fails_after``,
    per run, from a longer watch of the loop; None: none known), so it is censored, not
    safe, and a flag of it is not needless."""
    failure_times = np.asarray(failure_times, float)
    failed = np.isfinite(failure_times)
    times = run_times(ticks, period)
    scores = warning_scores(risks, times, failure_times, lead=lead, warnable_only=False)
    warnable, warned = np.zeros(len(failed), bool), np.zeros(len(failed), bool)
    # from the tick times alone: a k-of-n rule's risk is -inf at a run's first k-1
    # ticks, and a run it cannot warn there is a miss, not unwarnable
    warnable[failed] = [bool(np.any(t <= f - lead + 1e-9))
                        for t, f in zip(times, failure_times) if np.isfinite(f)]
    warned[failed] = flags_at(scores, threshold)
    flagged = np.array([bool(flags_at(r, threshold).any()) for r in risks])
    return {"failed": failed, "warnable": warnable, "warned": warned, "flagged": flagged,
            "failing_after": _failing_after(fails_after, failed)}


def k_of_n_risks(risks, flags_needed: int, window: int) -> list:
    """The risk the k-of-n flag rule (`reachwatch.systems.FlagFilter`: flag when at
    least ``flags_needed`` of the last ``window`` ticks reached the threshold, ticks
    before the run's first clear) acts on: at each tick the ``flags_needed``-th largest
    risk of the last ``window`` ticks (-inf for ticks before the first, which no
    threshold reaches). Any threshold, 0 included, on it flags exactly the ticks the
    filter confirms, so every figure here (misses, needless flags, conformal thresholds)
    applies to a filtered monitor unchanged; 1-of-1 is the risk itself."""
    k, n = check_k_of_n(flags_needed, window)
    out = []
    for risk in risks:
        risk = np.asarray(risk, float)
        if n == 1 or len(risk) == 0:
            out.append(risk.copy())
            continue
        padded = np.concatenate([np.full(n - 1, -np.inf), risk])
        windows = np.lib.stride_tricks.sliding_window_view(padded, n)
        out.append(np.sort(windows, axis=1)[:, n - k])
    return out


def oracle_risks(ticks, failure_times, *, period: float, lead: float) -> list:
    """The oracle monitor's risk per tick: 1 where the true time to failure is at most
    ``lead`` s plus one tick (the last tick that still leaves the fallback its need,
    and those after), else 0. Privileged: the ceiling for any monitor with this fallback."""
    out = []
    for n, failure in zip(ticks, failure_times):
        ttf, observed = time_to_failure(np.arange(int(n)) * period, failure, 1e9)
        out.append((observed & (ttf <= lead + period + 1e-9)).astype(float))
    return out


def rate(count: int, trials: int) -> dict:
    """``{"count", "of", "rate", "lo", "hi"}`` with the Wilson 95 % interval (NaN when
    there are no trials)."""
    if trials == 0:
        return {"count": 0, "of": 0, "rate": float("nan"), "lo": float("nan"),
                "hi": float("nan")}
    lo, hi = wilson_interval(count, trials)
    return {"count": int(count), "of": int(trials), "rate": count / trials, "lo": lo, "hi": hi}


def system_figures(outcomes: dict) -> dict:
    """Miss rate (warnable failing runs not warned in time), needless-flag rate (safe
    runs, neither failing nor ``failing_after``, that were flagged), and the share of
    failing runs that were warnable at all (the ceiling of any monitor with this
    fallback), with Wilson intervals, from `flag_outcomes`."""
    failed, warned, flagged = outcomes["failed"], outcomes["warned"], outcomes["flagged"]
    warnable = outcomes["warnable"]
    safe = ~failed & ~outcomes.get("failing_after", np.zeros(len(failed), bool))
    return {"miss": rate(int(np.sum(warnable & ~warned)), int(warnable.sum())),
            "needless": rate(int(np.sum(safe & flagged)), int(np.sum(safe))),
            "warnable": rate(int(warnable.sum()), int(failed.sum()))}


def tick_auroc(risks, ticks, failure_times, *, period: float, duration: float,
               within: float) -> float:
    """AUROC of the per-tick risk for "fails within ``within`` s" over the ticks whose
    label the runs settle (censored ticks left out); NaN with one class."""
    labels, scores = labelled_ticks(risks, ticks, failure_times, period=period,
                                    duration=duration, within=within)
    return auroc(labels == 1, scores) if len(labels) else float("nan")
