"""The flag budget: the bisection for the threshold that flags a set share of ticks, on
shares worked out by hand, and in table rollouts of a hand-made guarded loop."""

import numpy as np
import pytest

from reachwatch.diagrams import CONTROL_PORT, load_scenario
from reachwatch.reach import Grid
from reachwatch.reach.liveness import liveness_figures, threshold_for_flag_budget
from reachwatch.reach.score_noise import sigmoid
from reachwatch.taxi import (UNGUARDED, TaxiApplication, p_controller_policy,
                             taxi_fallback_rollouts)
from reachwatch.taxi.guarded import SCORE_PORT

flag_budget_threshold = TaxiApplication().flag_budget_threshold


def test_flag_budget_threshold_known_answer():
    """Bisection for the lowest threshold whose flagged share is within the budget, on
    shares worked out by hand: a straight line, a step, and the two edge cases."""
    threshold, share, steps = threshold_for_flag_budget(lambda t: 1.0 - t, 0.25)
    assert 0.75 <= threshold <= 0.75 + 1e-3 and share == pytest.approx(1.0 - threshold)
    assert all(s > 0.25 for t, s in steps if t < 0.75)       # every lower threshold tried is over
    step = lambda t: 0.5 if t < 0.3 else 0.05                 # noqa: E731
    threshold, share, _ = threshold_for_flag_budget(step, 0.1, tolerance=1e-4)
    assert 0.3 <= threshold <= 0.3 + 1e-4 and share == 0.05
    # within the budget already at the lowest threshold: that one; never within: a clear error
    assert threshold_for_flag_budget(lambda t: 0.01, 0.1)[:2] == (0.0, 0.01)
    with pytest.raises(ValueError, match="flags 60.0 % of its ticks, over the flag budget of 10 %"):
        threshold_for_flag_budget(lambda t: 0.6, 0.1)
    for bad in (0.0, 1.0, -0.2):
        with pytest.raises(ValueError, match="a flag budget is a share of control ticks"):
            threshold_for_flag_budget(lambda t: 0.0, bad)
    with pytest.raises(ValueError, match="low < high"):
        threshold_for_flag_budget(lambda t: 0.0, 0.1, low=0.5, high=0.5)


class _HandMadeTables(dict):
    """The swept tables `taxi_fallback_rollouts` reads, by port name, from hand-made arrays."""
    @property
    def tables(self):
        return self


def _braking_on_px(score_of_px):
    """Hand-made tables of a P-controller whose detector score rises with px, and a
    ``flagged(threshold)`` share of ticks when braking on it from 9 starts."""
    scenario = load_scenario(data="monitor: {brake_deceleration: 3.0}\n")
    policy = p_controller_policy(scenario.controller)
    grid = Grid(lo=[-10.0, 0.0, -0.3], hi=[10.0, 100.0, 0.3], shape=(11, 3, 7))
    nodes = grid.states()
    steer = policy(np.stack([nodes[:, 0], np.rad2deg(nodes[:, 2])], -1))
    tables = _HandMadeTables({CONTROL_PORT: steer.reshape(grid.shape),
                              SCORE_PORT: score_of_px(nodes[:, 0]).reshape(grid.shape)})
    starts = np.stack([np.linspace(-6.0, 6.0, 9), np.full(9, 10.0), np.zeros(9)], -1)

    def flagged(threshold):
        runs = taxi_fallback_rollouts(scenario, grid, tables, 4.0, ["brake"], threshold=threshold,
                                 starts=starts)
        return liveness_figures(runs[UNGUARDED], runs["brake"])["flagged_ticks"]
    return scenario, grid, tables, starts, flagged


def test_flag_budget_threshold_in_the_tables():
    """A detector whose score rises with px, braking when flagged: the chosen threshold
    keeps the flagged share of ticks within the budget, and a slightly lower one does
    not; the result names what it was chosen for."""
    scenario, grid, tables, starts, flagged = _braking_on_px(lambda px: (px + 10.0) / 20.0)
    chosen = flag_budget_threshold(scenario, grid, tables, 4.0, "brake", 0.3, starts=starts)
    assert (chosen["budget"], chosen["fallback"], chosen["starts"]) == (0.3, "brake", 9)
    assert flagged(chosen["threshold"]) == chosen["flagged_ticks"] <= 0.3
    assert flagged(chosen["threshold"] - 2e-3) > 0.3
    assert 0.3 < flagged(0.0) and 0.0 < chosen["threshold"] < 1.0


def test_flag_budget_threshold_of_a_saturated_detector():
    """A detector sure of itself: every score within 1e-4 of 1 (in order, as above).
    The budget still finds the threshold between the scores, searching their logit: a
    threshold a hundredth of a logit lower is over the budget."""
    scenario, grid, tables, starts, flagged = _braking_on_px(
        lambda px: 1.0 - 1e-4 * (10.0 - px) / 20.0 - 1e-6)
    chosen = flag_budget_threshold(scenario, grid, tables, 4.0, "brake", 0.3, starts=starts)
    assert 1.0 - 1.1e-4 < chosen["threshold"] < 1.0
    assert flagged(chosen["threshold"]) == chosen["flagged_ticks"] <= 0.3
    logit = np.log(chosen["threshold"] / (1.0 - chosen["threshold"]))   # unclipped, unlike
    # reach.score_noise.logit, which stops at 1 - 1e-4
    assert flagged(float(sigmoid(logit - 0.01))) > 0.3
    # a detector at 1 everywhere cannot keep any budget: the error names the score
    scenario, grid, tables, starts, _ = _braking_on_px(lambda px: np.ones_like(px))
    with pytest.raises(ValueError, match=r"even at threshold 0.9999999 the brake loop flags "
                                         r"100.0 % of its ticks, over the flag budget of 30 %"):
        flag_budget_threshold(scenario, grid, tables, 4.0, "brake", 0.3, starts=starts)


def test_a_loop_without_any_tick_has_no_flag_budget_threshold():
    """Every start failed before its first tick: the share is unknown, which read as 0
    and returned the lowest threshold, whose share the report then failed to format."""
    with pytest.raises(ValueError, match="the loop runs no control tick from these starts"):
        threshold_for_flag_budget(lambda t: None, 0.1)
