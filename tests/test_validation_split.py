"""The detector's validation split keeps each real run's samples together: states read
along one run are near-copies, and one on each side would make the threshold chosen
there look better than it is on new runs."""

import dataclasses as dc

import numpy as np

from reachwatch.training.dataset import LabelledData
from reachwatch.training.detector_train import DetectorTrainConfig, _split, run_groups
from reachwatch.training.labels import NO_RUN


def _data(n, runs=None):
    data = LabelledData.from_arrays(images=np.zeros((n, 2, 2, 3), np.uint8),
                                    states=np.zeros((n, 3)), values=np.ones(n),
                                    environment="E", camera_size=(2, 2))
    return dc.replace(data, runs=None if runs is None else np.asarray(runs, np.int64))


def test_run_groups_known_answer():
    assert run_groups([_data(3), _data(2)]) is None
    # 3 uniform samples, then 2 datasets whose runs 0 and 1 are different runs
    groups = run_groups([_data(3), _data(4, [NO_RUN, 0, 0, 1]), _data(3, [0, 0, NO_RUN])])
    assert len(groups) == 10 and len(set(groups.tolist())) == 8     # 5 alone, 3 runs
    assert groups[4] == groups[5] != groups[6]              # dataset 2's runs 0 and 1
    assert groups[7] == groups[8] not in groups[:7]           # dataset 3's run 0 is its own
    assert len({groups[i] for i in (0, 1, 2, 3, 9)}) == 5     # samples alone stay alone


def test_split_keeps_runs_whole_and_is_unchanged_without_them():
    config = DetectorTrainConfig(validation_fraction=0.25, seed=3)
    runs = np.repeat(np.arange(20), 5)                        # 20 runs of 5 samples
    groups = run_groups([_data(20), _data(100, runs)])
    val, train = _split(120, config, np.random.default_rng(3), groups)
    assert len(np.intersect1d(val, train)) == 0 and len(val) + len(train) == 120
    assert set(groups[val].tolist()).isdisjoint(groups[train].tolist())
    assert 30 <= len(val) < 35                                # whole runs up to a quarter
    again, _ = _split(120, config, np.random.default_rng(3), groups)
    np.testing.assert_array_equal(val, again)                 # a seed gives one split
    # datasets without runs: the random split of every earlier version
    val, train = _split(120, config, np.random.default_rng(3))
    order = np.random.default_rng(3).permutation(120)
    np.testing.assert_array_equal(val, np.sort(order[:30]))
    np.testing.assert_array_equal(train, order[30:])
