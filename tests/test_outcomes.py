"""Real-loop rollouts from given starts: chunked, cached by content, resumable, and
equal to direct simulation."""

import functools

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario, make_closed_loop_diagram, simulate
from reachwatch.reach.outcomes import outcomes_key, run_outcomes
from reachwatch.taxi import OffRunway, paper_grid
from reachwatch.taxi.fidelity import real_missions, real_outcomes

CALLS = []


def drift_rollout(speed, states):
    """A deterministic stand-in for a loop: px drifts at ``speed`` m/s for 1 s; it
    fails when |px| reaches 1."""
    CALLS.append(len(states))
    end = states[:, 0] + speed
    return {"failed": np.abs(end) >= 1.0, "ticks": np.full(len(states), 20)}


def test_outcomes_are_cached_and_a_killed_batch_resumes(tmp_path):
    starts = np.column_stack([np.linspace(-0.9, 0.9, 10), np.zeros(10)])
    rollout = functools.partial(drift_rollout, 0.5)
    CALLS.clear()
    first = run_outcomes(rollout, starts, cache_dir=tmp_path, chunk_size=4, progress=False)
    assert CALLS == [4, 4, 2] and first.computed == 10
    np.testing.assert_array_equal(first.failed, np.abs(starts[:, 0] + 0.5) >= 1.0)
    CALLS.clear()
    again = run_outcomes(rollout, starts, cache_dir=tmp_path, chunk_size=4, progress=False)
    assert CALLS == [] and again.computed == 0
    # a kill mid-batch leaves some chunks missing and one torn: only those run again
    folder = tmp_path / first.key
    (folder / "chunk_000001.npz").unlink()
    (folder / "chunk_000002.npz").write_bytes(b"torn")
    resumed = run_outcomes(rollout, starts, cache_dir=tmp_path, chunk_size=4, progress=False)
    assert CALLS == [4, 2] and resumed.computed == 6
    np.testing.assert_array_equal(resumed.failed, first.failed)
    # other starts or another rollout function are another batch
    assert outcomes_key(rollout, starts) != outcomes_key(rollout, starts[:5])
    assert outcomes_key(rollout, starts) != outcomes_key(functools.partial(drift_rollout, 0.6), starts)


def test_bad_starts_and_bad_rollout_output_are_named(tmp_path):
    with pytest.raises(ValueError, match="non-empty"):
        run_outcomes(functools.partial(drift_rollout, 0.5), np.zeros(3), cache_dir=tmp_path)
    with pytest.raises(ValueError, match="'failed'"):
        run_outcomes(lambda s: {"ok": s}, np.zeros((2, 2)), cache_dir=tmp_path, progress=False)


def test_real_outcomes_equal_direct_simulation(tmp_path):
    """The taxi rollout function is the real closed loop: same failure verdicts and
    failure times as simulate() from the same starts, and box exits counted."""
    scenario = load_scenario(data="environment: {runway: KMWH, hour: 9.0, sky: clear}\n")
    grid = paper_grid(scenario.environment.half_width, (3, 3, 3))
    starts = np.array([[0.0, 120.0, 0.0], [9.5, 120.0, 0.4], [-30.0, 120.0, 0.0]])
    outcomes = real_outcomes(scenario, starts, grid=grid, duration=1.5, cache_dir=tmp_path,
                             progress=False)
    diagram = make_closed_loop_diagram(scenario)
    for i, x in enumerate(starts[:2]):
        run = simulate(diagram, initial_state=x, duration=1.5, period=0.05,
                       failed=OffRunway(scenario.environment.half_width))
        assert outcomes.failed[i] == run.failed
        np.testing.assert_equal(outcomes["failure_time"][i], run.failure_time)
        assert outcomes["ticks"][i] == len(run.time)
    assert outcomes.failed[2] and outcomes["ticks"][2] == 0      # started off the runway
    assert outcomes.failed[1] and not outcomes.failed[0]


def test_runs_of_the_controller_alone_are_cached_without_the_monitor(tmp_path):
    """The loop alone never reads the monitor: scenarios that differ only there share
    its cached runs (a new detector or fallback setting does not re-run them)."""
    text = "environment: {runway: KMWH, hour: 9.0, sky: clear}\n"
    plain = load_scenario(data=text)
    braking = load_scenario(data=text + "monitor: {strategy: brake, threshold: 0.3, "
                                        "resume_acceleration: 1.0}\n")
    starts = np.array([[-30.0, 120.0, 0.0]])        # off the runway: no frame rendered
    grid = paper_grid(plain.environment.half_width, (3, 3, 3))
    for scenario in (plain, braking):
        real_missions(scenario, starts, duration=1.0, cache_dir=tmp_path / "missions",
                      progress=False)
        real_outcomes(scenario, starts, grid=grid, duration=1.0,
                      cache_dir=tmp_path / "outcomes", progress=False)
    assert len(list((tmp_path / "missions").iterdir())) == 1
    assert len(list((tmp_path / "outcomes").iterdir())) == 1
    other = load_scenario(data="environment: {runway: KMWH, hour: 21.0, sky: clear}\n")
    real_missions(other, starts, duration=1.0, cache_dir=tmp_path / "missions", progress=False)
    assert len(list((tmp_path / "missions").iterdir())) == 2      # the environment counts


def _row_index(states):
    return {"row": states[:, 0].copy()}


def test_a_batch_cached_with_another_chunk_size_is_not_read_into_the_wrong_rows(tmp_path):
    """The key holds the states, not the chunk size: before, 10 states run in chunks of
    8 and then of 2 read rows 8-9's values into rows 2-3."""
    from reachwatch.reach.outcomes import map_states
    states = np.stack([np.arange(10.0), np.zeros(10)], axis=1)
    for size in (8, 2, 3):
        fields, _, _ = map_states(_row_index, states, cache_dir=tmp_path, chunk_size=size,
                                  progress=False)
        np.testing.assert_array_equal(fields["row"], np.arange(10.0))
    fields, _, computed = map_states(_row_index, states, cache_dir=tmp_path, chunk_size=3,
                                     progress=False)
    assert computed == 0 and set(fields) == {"row"}      # cached, the rows entry not a field
