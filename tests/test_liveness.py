"""Liveness arithmetic on hand-made outcomes (`reach.liveness`): no loop, no plant."""

import pytest

from reachwatch.reach.liveness import MissionOutcomes, liveness_figures, percent


def test_liveness_arithmetic_known_answer():
    alone = MissionOutcomes(failed=[1, 1, 0, 0, 0], stopped=[0] * 5, ever_stopped=[0] * 5,
                            distance=[10, 20, 40, 40, 40], flagged_ticks=[0] * 5,
                            ticks=[10, 20, 40, 40, 40])
    guarded = MissionOutcomes(failed=[0, 1, 0, 0, 1], stopped=[1, 0, 0, 1, 0],
                              ever_stopped=[1, 0, 1, 1, 0], distance=[15, 20, 40, 10, 30],
                              flagged_ticks=[40, 5, 10, 40, 0], ticks=[40, 20, 40, 40, 30])
    f = liveness_figures(alone, guarded)
    assert f["failure_set"]["count"] == 2 and f["alone_failure_set"]["count"] == 2
    assert f["failure_cut"] == pytest.approx(0.0)
    assert (f["ended_stopped"]["count"], f["ever_stopped"]["count"]) == (2, 3)
    assert (f["needless_stops"]["count"], f["needless_stops"]["of"]) == (1, 3)
    assert (f["harmed"]["count"], f["saved"]["count"], f["saved_moving"]["count"]) == (1, 1, 0)
    assert f["distance_ratio"] == pytest.approx(115 / 150)
    assert f["flagged_ticks"] == pytest.approx(95 / 170)
    assert percent(f["needless_stops"]).startswith("33.3 % [")
    with pytest.raises(ValueError, match="both fail and end stopped"):
        MissionOutcomes(failed=[1], stopped=[1], ever_stopped=[1], distance=[0],
                        flagged_ticks=[0], ticks=[1])
    with pytest.raises(ValueError, match="same starts"):
        liveness_figures(alone, MissionOutcomes(**{k: v[:2] for k, v in
                                                   guarded.as_fields().items()}))


def test_cut_over_starts_inside_the_safe_set():
    """Two starts outside the safe set (failed before their first tick) count in both
    failure sets and no fallback can save them: 4 of 6 fail alone, 2 guarded, a 50 %
    cut over all starts but 100 % over the two that start inside."""
    out = dict(failed=[1, 1, 1, 1, 0, 0], stopped=[0] * 6, ever_stopped=[0] * 6,
               distance=[0, 0, 10, 20, 40, 40], flagged_ticks=[0] * 6,
               ticks=[0, 0, 10, 20, 40, 40], failed_same_distance=[1, 1, 1, 1, 0, 0],
               short_of_distance=[0] * 6)
    alone = MissionOutcomes(**out)
    guarded = MissionOutcomes(**{**out, "failed": [1, 1, 0, 0, 0, 0],
                                 "failed_same_distance": [1, 1, 0, 1, 0, 0],
                                 "distance": [0, 0, 40, 40, 40, 40],
                                 "ticks": [0, 0, 40, 40, 40, 40]})
    f = liveness_figures(alone, guarded)
    assert (f["failed_at_start"]["count"], f["failed_at_start"]["of"]) == (2, 6)
    assert f["failure_cut"] == pytest.approx(0.5)
    assert f["failure_cut_inside"] == pytest.approx(1.0)
    # saves too: 2 of the 4 alone-failures (the two at the start no fallback can
    # save), both of the 2 that start inside
    assert (f["saved"]["count"], f["saved"]["of"]) == (2, 4)
    assert (f["saved_inside"]["count"], f["saved_inside"]["of"]) == (2, 2)
    assert (f["saved_moving_inside"]["count"], f["saved_moving_inside"]["of"]) == (2, 2)
    assert f["same_distance_failure_cut"] == pytest.approx(0.25)
    assert f["same_distance_failure_cut_inside"] == pytest.approx(0.5)

