"""Table rollouts of the guarded loop (`taxi.taxi_guarded_rollouts`) on hand-made tables:
what each fallback does, and that a batch of starts equals each start alone."""

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario
from reachwatch.reach import Grid
from reachwatch.reach.liveness import MISSION_FIELDS, SAME_DISTANCE_FIELDS, liveness_figures
from reachwatch.taxi import dynamics_for, taxi_guarded_rollouts
from reachwatch.reach.guard import perfect_detector_scores
from reachwatch.taxi.guarded import p_controller_policy


def _tables(grid, steering, score):
    """Tables on ``grid`` from functions of the node states (a hand-made controller)."""
    nodes = grid.states()
    estimate = np.stack([nodes[:, 0], np.rad2deg(nodes[:, 2])], axis=-1)
    return steering(nodes), score(nodes), estimate


def _wrong_way(score):
    """A hand-made controller on a small grid that steers the wrong way wherever px >
    0.5 (the P-controller elsewhere), and a detector scoring ``score(nodes)``: the
    scenario's dynamics and policy, the grid, and its steering, score and estimate
    tables."""
    scenario = load_scenario(data="")
    policy = p_controller_policy(scenario.controller)
    grid = Grid(lo=[-10.0, 0.0, -0.3], hi=[10.0, 100.0, 0.3], shape=(11, 3, 7))
    good = lambda x: policy(np.stack([x[:, 0], np.rad2deg(x[:, 2])], -1))   # noqa: E731
    steer, scores, estimate = _tables(grid, lambda x: np.where(x[:, 0] > 0.5, 0.3, good(x)),
                                      score)
    return dynamics_for(scenario), policy, grid, steer, scores, estimate


def test_table_rollouts_of_a_batch_equal_each_start_alone():
    """The rollouts integrate only the starts still under way. Starts that fail early
    (px > 0.5: the hand-made controller steers off), brake to a stop or cover the
    distance sit in one batch beside starts that keep going; every field of every
    start equals its rollout alone, for each speed strategy and steering mode, and
    the caller's starts are left as they were."""
    dynamics, policy, grid, steer, score, estimate = _wrong_way(
        lambda x: np.clip(x[:, 0] / 4 + 0.4, 0.0, 1.0))
    starts = np.array([[2.0, 10.0, 0.0], [-2.0, 10.0, 0.0], [6.0, 50.0, 0.2],
                       [0.0, 30.0, -0.1], [9.5, 5.0, 0.25], [-4.0, 80.0, 0.1]])
    before = starts.copy()
    for kw in (dict(strategy="slow_down"), dict(strategy="brake", brake_deceleration=4.0),
               dict(strategy="brake", steering="dead_reckoning", policy=policy,
                    estimate_table=estimate, brake_deceleration=1.0),
               dict(strategy="slow_down", steering="oracle", policy=policy)):
        common = dict(threshold=0.5, horizon=4.0, mission_limit=2.0, **kw)
        batch = taxi_guarded_rollouts(grid, dynamics, steer, score, starts=starts, **common)
        assert batch.failed.any() and not batch.failed.all()
        for i, start in enumerate(starts):
            one = taxi_guarded_rollouts(grid, dynamics, steer, score, starts=start[None], **common)
            for name in MISSION_FIELDS + SAME_DISTANCE_FIELDS:
                np.testing.assert_allclose(getattr(one, name)[0], getattr(batch, name)[i],
                                           err_msg=f"{kw} start {i} {name}")
    np.testing.assert_array_equal(starts, before)


def test_table_rollouts_liveness_and_dead_reckoning():
    """A controller steering the wrong way wherever px > 0: alone it fails there; a
    detector flagging px > 0 with dead reckoning saves those starts without stopping,
    braking saves them by stopping, and a detector that never flags changes nothing."""
    dynamics, policy, grid, steer, score, estimate = _wrong_way(
        lambda x: (x[:, 0] > 0.5).astype(float))
    starts = np.array([[2.0, 10.0, 0.0], [-2.0, 10.0, 0.0]])
    kw = dict(horizon=6.0, starts=starts)
    alone = taxi_guarded_rollouts(grid, dynamics, steer, None, **kw)
    assert alone.failed.tolist() == [True, False] and not alone.ever_stopped.any()
    never = taxi_guarded_rollouts(grid, dynamics, steer, score, threshold=1.5, **kw)
    f = liveness_figures(alone, never)
    assert (f["failure_set"]["rate"], f["ended_stopped"]["rate"], f["flagged_ticks"]) == (
        0.5, 0.0, 0.0) and f["distance_ratio"] == pytest.approx(1.0)
    reckoned = taxi_guarded_rollouts(grid, dynamics, steer, score, steering="dead_reckoning",
                                policy=policy, estimate_table=estimate, **kw)
    assert not reckoned.failed.any() and not reckoned.stopped.any()
    assert reckoned.flagged_ticks[0] > 0 and reckoned.flagged_ticks[1] == 0
    braked = taxi_guarded_rollouts(grid, dynamics, steer, score, strategy="brake",
                              brake_deceleration=4.0, **kw)
    assert braked.failed.tolist() == [False, False] and braked.stopped.tolist() == [True, False]
    with pytest.raises(ValueError, match="estimate table"):
        taxi_guarded_rollouts(grid, dynamics, steer, score, steering="dead_reckoning",
                              policy=policy)
    # a perfect detector for a BRT that holds px > 0.5 flags what the hand-made one does
    brt = type("HandMadeBRT", (), {"at": staticmethod(lambda x: 0.5 - np.asarray(x)[:, 0])})()
    scores = perfect_detector_scores(brt, grid)
    np.testing.assert_allclose(scores.ravel(), grid.states()[:, 0] - 0.5)
    perfect = taxi_guarded_rollouts(grid, dynamics, steer, scores, threshold=0.0, strategy="brake",
                               brake_deceleration=4.0, **kw)
    for name in ("failed", "stopped", "flagged_ticks", "distance"):
        np.testing.assert_allclose(getattr(perfect, name), getattr(braked, name))
    # a 3-of-3 rule on a detector that flags every tick from the start: the first two
    # ticks are not yet confirmed, every later one is
    always = np.ones_like(score)
    confirmed = taxi_guarded_rollouts(grid, dynamics, steer, always, flags_needed=3, flag_window=3,
                                 **kw)
    assert (confirmed.flagged_ticks == confirmed.ticks - 2).all()
    # a score table of NaN flags every tick, as the monitor's anomaly port does online
    unknown = taxi_guarded_rollouts(grid, dynamics, steer, np.full_like(score, np.nan), **kw)
    assert (unknown.flagged_ticks == unknown.ticks).all()
