"""The scores of benchmarks/estimate_residual.py: the residual of an estimate that
follows the taxi's kinematics is zero, a jump shows as its size, and each environment's
AUROC is read over a recorded-runs folder as a study caches it."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from reachwatch.systems.dead_reckoning import propagate_estimate

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "estimate_residual.py"
_SPEC = importlib.util.spec_from_file_location("estimate_residual", _PATH)
residual = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(residual)

SPEED, PERIOD = 5.0, 0.05


def _consistent_run(ticks: int, steering: float = 0.02) -> np.ndarray:
    rows, estimate = [], np.array([1.0, 3.0])
    for _ in range(ticks):
        rows.append([*estimate, steering])
        estimate = propagate_estimate(estimate, steering, SPEED, PERIOD)
    return np.array(rows)


def test_an_estimate_that_follows_the_kinematics_has_no_residual_and_a_jump_shows():
    run = _consistent_run(40)
    assert np.allclose(residual.scores(run, speed=SPEED, period=PERIOD)["residual"], 0.0,
                       atol=1e-9)
    run[10:, 0] += 0.5                      # the estimate jumps 0.5 m at tick 10, then follows
    got = residual.scores(run, speed=SPEED, period=PERIOD)
    assert got["residual"][10] == pytest.approx(0.5)
    assert np.allclose(np.delete(got["residual"], 10), 0.0, atol=1e-9)
    # the 1 s mean: over the ticks so far until the 20th, then over the last 20
    mean = got["residual, 1 s"]
    assert mean[10:19] == pytest.approx(0.5 / np.arange(11, 20))
    assert mean[19:30] == pytest.approx(np.full(11, 0.5 / 20)) and mean[9] == 0.0


def test_trailing_mean_averages_what_there_is_at_the_start():
    assert residual.trailing_mean(np.array([2.0, 4.0, 6.0, 8.0]), 2).tolist() == [2, 3, 5, 7]


def test_an_environment_whose_failing_runs_jump_ranks_them_first(tmp_path):
    folder = tmp_path / "runs" / "record_runs_4_x"
    folder.mkdir(parents=True)
    T = 161
    signals = np.stack([_consistent_run(T) for _ in range(4)])
    signals[:2, 60:, 0] += np.cumsum(np.full(T - 60, 0.1))   # two runs' estimates wander
    np.savez(folder / "chunk_000000.npz", signals=signals, ticks=np.array([80, 80, T, T]),
             failure_time=np.array([3.95, 3.95, np.nan, np.nan]))
    got = residual.environment_aurocs(folder, speed=SPEED, period=PERIOD, duration=8.0,
                                      within=4.0)
    assert got["residual"] > 0.5 and np.isfinite(got["|estimate|"])
