"""Time-to-failure labels: right-censored at the end of a run, never "safe" by default;
path labels are the same machinery at the BRT's horizon."""

import numpy as np
import pytest

from reachwatch.reach.outcomes import fails_within, path_labels, time_to_failure


def test_a_failing_run_gives_observed_times_to_failure():
    time = np.arange(5) * 0.5                        # 0 .. 2 s
    ttf, observed = time_to_failure(time, 2.25, duration=8.0)
    np.testing.assert_allclose(ttf, [2.25, 1.75, 1.25, 0.75, 0.25])
    assert observed.all()
    assert fails_within(ttf, observed, 1.0).tolist() == [0, 0, 0, 1, 1]


def test_a_run_that_did_not_fail_is_censored_not_safe():
    time = np.arange(5) * 0.5
    ttf, observed = time_to_failure(time, float("nan"), duration=2.0)
    np.testing.assert_allclose(ttf, [2.0, 1.5, 1.0, 0.5, 0.0])
    assert not observed.any()
    # known safe only where the run went on at least the horizon past the tick
    assert fails_within(ttf, observed, 1.0).tolist() == [0, 0, 0, -1, -1]
    assert fails_within(ttf, observed, 3.0).tolist() == [-1] * 5


def test_path_labels_are_fails_within_the_horizon():
    rng = np.random.default_rng(0)
    for _ in range(50):
        time = np.arange(rng.integers(1, 40)) * 0.05
        failure = float(rng.uniform(0, 3)) if rng.uniform() < 0.5 else None
        duration, horizon = float(rng.uniform(0.5, 3)), float(rng.uniform(0.2, 2))
        expected = np.full(len(time), -1)
        for i, t in enumerate(time):
            if failure is not None:
                expected[i] = 1 if failure - t <= horizon else 0
            elif t + horizon <= duration + 1e-9:
                expected[i] = 0
        assert path_labels(time, failure, duration, horizon).tolist() == expected.tolist()


def test_bad_inputs_name_the_problem():
    with pytest.raises(ValueError, match="duration must be a finite number > 0"):
        time_to_failure([0.0, 0.1], None, 0.0)
    with pytest.raises(ValueError, match="horizon must be a finite number > 0"):
        fails_within([1.0], [True], float("nan"))
    with pytest.raises(ValueError, match="1-d array of finite tick times"):
        time_to_failure([[0.0]], None, 1.0)
