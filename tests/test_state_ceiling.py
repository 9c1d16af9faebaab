"""The arithmetic of benchmarks/state_ceiling.py: runs numbered across pooled datasets,
and k-NN votes cross-validated by run (a test run is never among its own neighbours)."""

import importlib.util
from pathlib import Path

import numpy as np

from reachwatch.training.labels import NO_RUN
from reachwatch.training.metrics import auroc

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "state_ceiling.py"
_SPEC = importlib.util.spec_from_file_location("state_ceiling", _PATH)
ceiling = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(ceiling)


def test_run_ids_keep_pooled_runs_apart_and_give_lone_samples_their_own():
    first = ceiling.run_ids([NO_RUN, 0, 0, 1, NO_RUN], offset=0)
    assert first.tolist() == [2, 0, 0, 1, 3]
    second = ceiling.run_ids([0, NO_RUN], offset=int(first.max()) + 1)
    assert second.tolist() == [4, 5]
    assert ceiling.run_ids([NO_RUN, NO_RUN], offset=10).tolist() == [10, 11]


def test_votes_never_see_the_run_they_score():
    """Every run sits still at one random point with a random label: its own states are
    its nearest neighbours at distance 0, so a split by sample would score perfectly;
    split by run, the votes come from other runs and rank no better than chance."""
    rng = np.random.default_rng(0)
    runs = np.repeat(np.arange(60), 5)
    points = rng.uniform(-1, 1, (60, 3))
    x, y = points[runs], rng.uniform(size=60)[runs] < 0.4
    scores, _ = ceiling.knn_votes(x, y, runs, folds=3, share=1.0, k=5,
                                  rng=np.random.default_rng(1))
    assert auroc(y, scores) < 0.7
    # a label that follows the state is learnt from other runs (along one axis here:
    # each vote is in effect the nearest other run's label)
    x = x * [1.0, 0.0, 0.0]
    y = x[:, 0] > 0
    scores, used = ceiling.knn_votes(x, y, runs, folds=3, share=1.0, k=5,
                                     rng=np.random.default_rng(1))
    assert auroc(y, scores) > 0.95
    assert used == 200                      # two folds of the three, all their runs
    _, half = ceiling.knn_votes(x, y, runs, folds=3, share=0.5, k=5,
                                rng=np.random.default_rng(1))
    assert half == 100
