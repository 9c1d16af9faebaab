"""The monitor study's threshold: fixed on the calibration environments with failures
alone when asked (`monitor.given_failures`), and the bounded miss rate the report sets
beside alpha."""

import dataclasses as dc

import numpy as np
import pytest


def test_the_report_shows_the_bounded_miss_rate_observed():
    from reachwatch.pipeline.monitor_sections import bounded_miss_rates, observed_bound_text
    envs = [{"miss": {"rate": r, "of": n}} for r, n in ((0.5, 2), (0.0, 3), (None, 0),
                                                          (None, 0))]
    observed = bounded_miss_rates(envs)
    assert observed == pytest.approx((0.125, 0.25, 2, 4))
    assert "12.5 % over all 4, an environment where no run fails counting 0 (the quantity " \
           "bounded at 10.0 %), and 25.0 % over the 2" in observed_bound_text(observed, {}, 0.1)
    assert "is 25.0 % over the 2 where some run fails (the quantity bounded" in \
        observed_bound_text(observed, {"given_failures": True}, 0.1)
    assert bounded_miss_rates([]) is None


def test_given_failures_fixes_the_threshold_where_runs_fail():
    """Six calibration environments with one failing run each (warning risks 0.3 to
    0.8) and six where nothing fails. At alpha 0.2 the default bound lets the lowest
    warning be missed (the six without failures count as missing none); fixed on the
    six with failures alone, nothing may be missed."""
    from reachwatch.pipeline.monitor_judge import choose_flag_rule
    from reachwatch.pipeline.monitor_spec import MonitorStudySpec
    period, ticks = 0.05, 100
    groups, risks = [], []
    for e in range(12):
        fails = e < 6
        groups.append({"name": f"env{e}", "ticks": np.array([40 if fails else ticks, ticks]),
                       "failure_time": np.array([2.0 if fails else np.nan, np.nan]),
                       "watched_failure_time": np.array([2.0 if fails else np.nan, np.nan])})
        risks.append([np.full(40 if fails else ticks, 0.3 + 0.1 * e if fails else 0.05),
                      np.full(ticks, 0.05)])
    spec = MonitorStudySpec(kind="history", alpha=0.2, calibrate=12, flag_rules=[[1, 1]])
    every = choose_flag_rule(spec, groups, {"calibrate": risks}, period=period, lead=1.0)[2]
    given = choose_flag_rule(dc.replace(spec, given_failures=True), groups,
                             {"calibrate": risks}, period=period, lead=1.0)[2]
    assert every.threshold == pytest.approx(0.4) and not every.given_failures
    assert given.threshold == pytest.approx(0.3) and given.environments == 6
    assert "where some run fails that is about 40.0 %" in every.statement(1.0)
    assert "and with a warnable failing run" in given.statement(1.0)
    with pytest.raises(ValueError, match="6 calibration environments with a warnable failing "
                                         "run cannot bound the miss rate at 0.1"):
        choose_flag_rule(dc.replace(spec, alpha=0.1, given_failures=True), groups,
                         {"calibrate": risks}, period=period, lead=1.0)
