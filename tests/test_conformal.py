"""The monitor's threshold with a miss-rate bound over environments: the bound holds
on new environments of a family whose environments differ (checked by simulation),
warning scores respect the fallback's lead, calibration maps are right."""

import math

import numpy as np
import pytest

from reachwatch.training.conformal import (PlattCalibration, brier_score, conformal_threshold,
                                           expected_calibration_error, miss_rate,
                                           per_environment_bound, reliability_curve,
                                           warning_scores)


def test_warning_scores_read_only_ticks_the_fallback_can_still_use():
    time = np.arange(6) * 0.5
    risks = [np.array([0.1, 0.2, 0.9, 0.3, 0.95, 0.99]), np.array([0.5, 0.1]),
             np.array([0.7, 0.8, 0.9])]
    times, failures = [time, time[:2], time[:3]], [2.5, 0.3, float("nan")]
    scores = warning_scores(risks, times, failures, lead=1.0, warnable_only=False)
    # run 0: ticks at or before 1.5 s count (max 0.9 at 1.0 s; 0.95 at 2.0 s is too late);
    # run 1 fails 0.3 s in: no tick 1 s before it (unwarnable); run 2 did not fail
    assert scores[0] == 0.9 and scores[1] == -math.inf and len(scores) == 2
    assert miss_rate(scores, 0.5) == 0.5 and miss_rate(scores, 0.95) == 1.0
    # by default the unwarnable run is left out: no monitor could warn it in time
    assert warning_scores(risks, times, failures, lead=1.0).tolist() == [0.9]


def _family(rng, environments, runs=30):
    """Environments that differ: each shifts its failing runs' warning scores."""
    out = []
    for _ in range(environments):
        shift = rng.normal(0, 0.15)
        n = rng.integers(0, runs)
        out.append(np.clip(rng.beta(4, 2, size=n) + shift, 0, 1))
    return out


def test_the_expected_miss_rate_on_new_environments_is_bounded():
    rng = np.random.default_rng(1)
    alpha, misses = 0.15, []
    for _ in range(1500):
        calibration, new = _family(rng, 12), _family(rng, 1)[0]
        chosen = conformal_threshold(calibration, alpha)
        if len(new):
            misses.append(miss_rate(new, chosen.threshold))
    assert np.mean(misses) <= alpha + 0.01       # the guarantee (simulation error ~0.004)
    assert np.mean(misses) >= alpha - 0.06       # and not a trivially low threshold


def _sparse_family(rng, environments, runs=12):
    """Environments of which about half have no failing run (as many do in the study)."""
    out = []
    for _ in range(environments):
        shift = rng.normal(0, 0.15)
        n = rng.integers(1, 5) if rng.random() < 0.5 else 0
        out.append(np.clip(rng.beta(4, 2, size=n) + shift, 0, 1))
    return out


def test_given_failures_bounds_the_miss_rate_where_runs_fail():
    rng = np.random.default_rng(2)
    alpha, every, given = 0.2, [], []
    for _ in range(1500):
        calibration, new = _sparse_family(rng, 24), _sparse_family(rng, 1)[0]
        if not len(new):
            continue
        every.append(miss_rate(new, conformal_threshold(calibration, alpha).threshold))
        given.append(miss_rate(new, conformal_threshold(calibration, alpha,
                                                        given_failures=True).threshold))
    # counting failure-free environments as 0 dilutes the bound where runs fail ...
    assert np.mean(every) > alpha + 0.03
    # ... fixing the threshold on environments with failures alone keeps it there
    assert alpha - 0.08 <= np.mean(given) <= alpha + 0.01
    chosen = conformal_threshold(_sparse_family(rng, 24), alpha)
    assert 0 < chosen.failing_environments < chosen.environments
    assert "counting an environment where no run fails as missing none" in chosen.statement(1.7)
    with pytest.raises(ValueError, match="with a warnable failing run cannot bound"):
        conformal_threshold([np.array([0.5])] * 3 + [np.array([])] * 20, 0.2,
                            given_failures=True)


def test_a_calibration_without_failing_runs_says_its_bound_says_nothing_where_runs_fail():
    chosen = conformal_threshold([np.array([])] * 10, 0.1)
    assert chosen.failing_environments == 0
    assert "it says nothing of an environment where runs fail" in chosen.statement(1.7)


def test_the_largest_threshold_is_kept_and_impossible_targets_refused():
    scores = [np.array([0.2, 0.6, 0.8]), np.array([0.7, 0.9]), np.array([]),
              np.array([0.5, 0.95])] * 3
    chosen = conformal_threshold(scores, 0.3)
    bound = lambda t: 12 / 13 * np.mean([miss_rate(s, t) if len(s) else 0 for s in scores]) + 1 / 13
    assert bound(chosen.threshold) <= 0.3
    higher = [t for t in np.unique(np.concatenate(scores)) if t > chosen.threshold]
    assert all(bound(t) > 0.3 for t in higher)
    assert "at most 30.0 %" in chosen.statement(lead=1.7)
    with pytest.raises(ValueError, match="use at least 9"):
        conformal_threshold(scores[:5], 0.1)
    with pytest.raises(ValueError, match="fail before a warning can help"):
        conformal_threshold([np.array([-np.inf, 0.5])] * 20, 0.2)


def test_a_threshold_whose_bound_is_alpha_exactly_is_kept():
    # 109 environments, 10 of them with their one failing run missed below 0.5:
    # (10 + 1) / 110 = 0.1 exactly, which float arithmetic reads 0.10000000000000002
    scores = [np.array([0.4])] * 10 + [np.array([0.9])] * 99
    assert conformal_threshold(scores, 0.1).threshold == 0.9
    assert conformal_threshold(scores[:-1], 0.1).threshold == 0.4     # (10 + 1) / 109 > 0.1


def test_a_nan_risk_is_refused_not_read_as_warned():
    time = np.arange(4) * 0.5
    with pytest.raises(ValueError, match="risk is NaN at 1 of its ticks before its warning"):
        warning_scores([np.array([0.1, np.nan, 0.2, 0.9])], [time], [1.6], lead=0.5)
    # a NaN score (none reaches warning_scores now) is a miss, as flag_outcomes reads it
    assert miss_rate([np.nan, 0.9], 0.5) == 0.5


def test_without_failing_runs_nothing_is_flagged():
    chosen = conformal_threshold([np.array([])] * 9, 0.1)
    assert chosen.threshold == 1.0 and chosen.failing_runs == 0


def test_per_environment_bound_is_a_calibration_quantile():
    rates = np.linspace(0, 0.9, 10)
    assert per_environment_bound(rates, 0.2) == pytest.approx(rates[8])    # ceil(11 * 0.8) = 9
    assert per_environment_bound(rates, 0.05) == 1.0                        # rank 11 > 10


def test_platt_scaling_recovers_a_known_miscalibration():
    rng = np.random.default_rng(0)
    true = rng.uniform(0.02, 0.98, 20000)
    y = rng.uniform(size=true.size) < true
    z = np.log(true / (1 - true))
    overconfident = 1 / (1 + np.exp(-(2.0 * z - 0.5)))
    fit = PlattCalibration.fit(overconfident, y)
    assert fit.a == pytest.approx(0.5, abs=0.05) and fit.b == pytest.approx(0.25, abs=0.05)
    assert expected_calibration_error(fit(overconfident), y) < 0.02
    assert expected_calibration_error(overconfident, y) > 0.05
    assert brier_score(fit(overconfident), y) < brier_score(overconfident, y)
    mean_p, freq, counts = reliability_curve(fit(overconfident), y, bins=5)
    assert counts.sum() == y.size and np.all(np.abs(mean_p - freq) < 0.03)


def test_platt_scaling_keeps_the_order_of_risks_far_below_one_in_a_million():
    """A confident monitor's raw risks on safe ticks lie far below 1e-7; clipped there
    before their logit (as they were), most of an environment's ticks came out of
    calibration as one risk, and the ties pulled its AUROC down (0.895 -> 0.831 on the
    fourth protocol run's worst environment). The order is kept, and with it the AUROC
    of the raw risks."""
    from reachwatch.training.metrics import auroc
    rng = np.random.default_rng(2)
    logits = np.concatenate([rng.normal(-30.0, 6.0, 4000), rng.normal(-18.0, 6.0, 400),
                             rng.normal(2.0, 2.0, 400)])
    y = np.r_[np.zeros(4000), np.ones(400), np.ones(400)].astype(bool)
    raw = 1 / (1 + np.exp(-logits))                    # as the monitor's float64 sigmoid
    assert np.mean(raw < 1e-7) > 0.8                   # what the old clip made one value
    fit = PlattCalibration.fit(raw, y)
    calibrated = fit(raw)
    assert fit.a > 0 and np.all(np.diff(calibrated[np.argsort(raw)]) >= 0)
    assert len(np.unique(calibrated)) == len(np.unique(raw))
    assert auroc(y, calibrated) == pytest.approx(auroc(y, raw), abs=1e-12)
    assert auroc(y, raw) - auroc(y, np.clip(raw, 1e-7, 1)) > 0.02   # the ties it cost


def test_platt_scaling_never_reverses_a_backward_model():
    """Raw risks that rank the labels backwards get slope 0 (the base rate for every
    input), not a negative slope that would turn the risks round."""
    rng = np.random.default_rng(1)
    true = rng.uniform(0.05, 0.95, 5000)
    y = rng.uniform(size=true.size) < true
    fit = PlattCalibration.fit(1.0 - true, y)
    assert fit.a == 0.0
    assert np.allclose(fit(1.0 - true), y.mean(), atol=1e-3)


def test_flag_outcomes_count_misses_among_warnable_runs_only():
    from reachwatch.training.monitor_eval import flag_outcomes, oracle_risks, system_figures
    ticks, failures = [10, 3, 10, 10], [0.45, 0.1, float("nan"), float("nan")]
    risks = [np.r_[np.zeros(5), np.ones(5)], np.ones(3), np.zeros(10), np.r_[np.zeros(9), 1.0]]
    out = flag_outcomes(risks, ticks, failures, period=0.05, threshold=0.5, lead=0.2)
    assert out["warnable"].tolist() == [True, False, False, False]
    assert out["warned"].tolist() == [True, False, False, False]      # flag at 0.25 s
    figures = system_figures(out)
    assert (figures["miss"]["count"], figures["miss"]["of"]) == (0, 1)
    assert (figures["needless"]["count"], figures["needless"]["of"]) == (1, 2)
    assert (figures["warnable"]["count"], figures["warnable"]["of"]) == (1, 2)
    late = flag_outcomes([np.r_[np.zeros(7), np.ones(3)]] + risks[1:], ticks, failures,
                         period=0.05, threshold=0.5, lead=0.2)
    assert system_figures(late)["miss"]["count"] == 1                  # flag at 0.35 s: late
    oracle = flag_outcomes(oracle_risks(ticks, failures, period=0.05, lead=0.2), ticks,
                           failures, period=0.05, threshold=0.5, lead=0.2)
    assert system_figures(oracle)["miss"]["count"] == 0 and not oracle["flagged"][2:].any()
    # a NaN risk flags, as the monitor's anomaly port does online (`flag_of`)
    nan = flag_outcomes(risks[:2] + [np.r_[np.zeros(4), np.nan, np.zeros(5)], risks[3]], ticks,
                        failures, period=0.05, threshold=0.5, lead=0.2)
    assert nan["flagged"].tolist() == [True, True, True, True]


def test_a_run_failing_after_its_recording_is_neither_safe_nor_needless():
    """The run flagged near its recording's end fails just after it (a longer watch of
    the loop): its flag is not needless, and it leaves the safe runs, in the figures and
    in the scores any threshold is read from; a run that failed within the recording
    is not moved by it."""
    from reachwatch.training.monitor_eval import decisive_scores, flag_outcomes, system_figures
    ticks, failures = [10, 10, 10], [float("nan"), float("nan"), 0.45]
    risks = [np.r_[np.zeros(9), 1.0], np.r_[np.zeros(9), 0.8], np.r_[np.ones(3), np.zeros(7)]]
    before = system_figures(flag_outcomes(risks, ticks, failures, period=0.05, threshold=0.5,
                                          lead=0.2))
    assert (before["needless"]["count"], before["needless"]["of"]) == (2, 2)
    out = flag_outcomes(risks, ticks, failures, period=0.05, threshold=0.5, lead=0.2,
                        fails_after=[True, False, True])
    assert out["failing_after"].tolist() == [True, False, False]
    figures = system_figures(out)
    assert (figures["needless"]["count"], figures["needless"]["of"]) == (1, 1)
    assert figures["miss"] == before["miss"]
    scores = decisive_scores(risks, ticks, failures, period=0.05, lead=0.2,
                             fails_after=[True, False, True])
    assert scores["safe_max"] == [0.8]
    with pytest.raises(ValueError, match="one entry per run"):
        flag_outcomes(risks, ticks, failures, period=0.05, threshold=0.5, lead=0.2,
                      fails_after=[True])


def test_k_of_n_risks_flag_what_the_flag_filter_confirms():
    """A threshold on `k_of_n_risks` flags exactly the ticks the FlagFilter's array rule
    (`confirmed_flags`) confirms from the raw flags, at every tick, for any threshold
    (0 too: the ticks before a run's k-th are never confirmed)."""
    from reachwatch.systems import confirmed_flags
    from reachwatch.training.monitor_eval import flag_outcomes, k_of_n_risks
    rng = np.random.default_rng(3)
    runs = [rng.uniform(0, 1, n) for n in (0, 1, 4, 25, 40)]
    for k, n in ((1, 1), (2, 2), (2, 3), (3, 5), (1, 4)):
        filtered = k_of_n_risks(runs, k, n)
        for tau in (0.0, 0.2, 0.5, 0.8):
            for risk, held in zip(runs, filtered):
                assert len(held) == len(risk)
                history, expected = np.zeros((1, n - 1), bool), []
                for r in risk:
                    confirmed, history = confirmed_flags([r >= tau], history, k)
                    expected.append(bool(confirmed[0]))
                assert (held >= tau).tolist() == expected
    # a single spike no longer flags a run that does not fail; a held warning still does
    spike, held = np.r_[0.1, 0.9, 0.1, 0.1, 0.1], np.r_[0.1, 0.6, 0.8, 0.7, 0.2]
    out = flag_outcomes(k_of_n_risks([spike, held], 2, 2), [5, 5], [float("nan"), 0.25],
                        period=0.05, threshold=0.5, lead=0.05)
    assert out["flagged"].tolist() == [False, True] and out["warned"].tolist() == [False, True]
    with pytest.raises(ValueError, match="k-of-n flag rule"):
        k_of_n_risks([held], 3, 2)
    # a run that fails before a 3-of-3 rule can confirm a flag lead s ahead is warnable
    # (it has an early enough tick) and missed, at any threshold
    early = np.r_[0.9, 0.9, 0.9]
    out = flag_outcomes(k_of_n_risks([early], 3, 3), [3], [0.10], period=0.05,
                        threshold=0.0, lead=0.05)
    assert out["warnable"].tolist() == [True] and out["warned"].tolist() == [False]


def test_a_safe_run_with_no_tick_is_never_flagged_in_the_decisive_scores():
    from reachwatch.training.monitor_eval import decisive_scores, flag_outcomes
    risks, ticks, failures = [np.zeros(0), np.array([0.2])], [0, 1], [np.nan, np.nan]
    scores = decisive_scores(risks, ticks, failures, period=0.05, lead=0.5)
    flagged = flag_outcomes(risks, ticks, failures, period=0.05, threshold=0.0,
                            lead=0.5)["flagged"]
    assert [s >= 0.0 for s in scores["safe_max"]] == flagged.tolist() == [False, True]
