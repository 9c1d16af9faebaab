"""The operating threshold chosen on environments the detector never saw: known
answers for the pure functions, and the fold training on tiny in-memory datasets
(one checkpoint per left-out group, none trained twice, each blind to its group)."""

import os

import numpy as np
import pytest

from reachwatch.diagrams import load_detector
from reachwatch.systems import DetectorConfig
from reachwatch.training.dataset import LabelledData
from reachwatch.training.detector_train import (DetectorTrainConfig, detector_scores,
                                                environment_groups,
                                                held_out_operating_threshold)
from reachwatch.training.metrics import accuracy_at_recall, held_out_threshold, recall_threshold


def test_recall_threshold_known_answers():
    labels = [1, 1, 1, 1, 0, 0]
    scores = [0.9, 0.8, 0.7, 0.6, 0.95, 0.1]
    assert recall_threshold(labels, scores, 1.0) == 0.6
    assert recall_threshold(labels, scores, 0.75) == 0.7      # 3 of 4 flagged
    assert recall_threshold(labels, scores, 0.76) == 0.6      # 3 of 4 is not enough
    # (1 - 0.9) * 10 is 0.999... in floating point: one miss is still allowed.
    assert recall_threshold([1] * 10, np.arange(10) / 10, 0.9) == 0.1
    assert recall_threshold([0, 0], [0.3, 0.4], 0.95) is None
    with pytest.raises(ValueError, match="target_recall must be in"):
        recall_threshold(labels, scores, 0.0)
    with pytest.raises(ValueError, match="differ"):
        recall_threshold([1, 0], [0.5], 0.9)
    # the oracle accuracy there: threshold 0.6 flags all 4 positives and the 0.95 negative
    assert accuracy_at_recall(labels, scores, 1.0) == 5 / 6
    assert accuracy_at_recall(labels, scores, 0.75) == 4 / 6   # 0.7: one positive missed
    assert np.isnan(accuracy_at_recall([0, 0], [0.3, 0.4], 0.95))


def test_held_out_threshold_every_group_and_pooled():
    groups = {"A": ([1, 1, 1, 1, 0, 0], [0.9, 0.8, 0.7, 0.6, 0.5, 0.05]),
              "B": ([1, 1, 0, 0], [0.5, 0.4, 0.3, 0.2]),
              "C": ([0, 0], [0.99, 0.01])}                    # no positives: no constraint
    every = held_out_threshold(groups, 0.75)
    # A alone: 0.7; B alone: floor(0.25 * 2) = 0 misses -> 0.4; the lower one holds for both.
    assert every.per_group["A"]["own_threshold"] == 0.7
    assert every.per_group["B"]["own_threshold"] == 0.4
    assert every.per_group["C"]["own_threshold"] is None
    assert every.threshold == 0.4
    assert every.per_group["A"]["recall"] == 1.0 and every.per_group["B"]["recall"] == 1.0
    assert every.per_group["A"]["accuracy"] == 5 / 6              # 0.5 >= 0.4 is a false alarm
    assert every.per_group["C"]["accuracy"] == 0.5
    assert every.promised["min_recall"] == 1.0
    assert every.promised["pooled_accuracy"] == 10 / 12    # A 5, B 4, C 1 right
    assert every.promised["flagged"] == 8 / 12             # A 5, B 2, C 1 flagged
    # Pooled: positives 0.9 0.8 0.7 0.6 0.5 0.4, one miss allowed (floor(0.25 * 6) = 1).
    pooled = held_out_threshold(groups, 0.75, rule="pooled")
    assert pooled.threshold == 0.5
    assert pooled.per_group["B"]["recall"] == 0.5
    assert pooled.promised["min_recall"] == 0.5
    assert pooled.promised["pooled_recall"] == 5 / 6
    with pytest.raises(ValueError, match="rule must be one of"):
        held_out_threshold(groups, 0.75, rule="median")
    with pytest.raises(ValueError, match="no held-out group has a positive"):
        held_out_threshold({"C": groups["C"]}, 0.75)


def test_environment_groups_are_contiguous():
    assert environment_groups(12, 3) == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]]
    assert environment_groups(5, 2) == [[0, 1, 2], [3, 4]]
    assert environment_groups(3, 3) == [[0], [1], [2]]
    with pytest.raises(ValueError, match="between 2 and the number of training datasets"):
        environment_groups(3, 4)


@pytest.mark.parametrize("edit, message", [
    ({"threshold_folds": 1}, "threshold_folds must be 0 (validation split) or a whole number >= 2"),
    ({"threshold_folds": 2, "target_recall": 0.0}, "chooses a threshold for target_recall"),
    ({"threshold_rule": "median"}, "threshold_rule must be one of"),
])
def test_config_errors_name_the_field(edit, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        DetectorTrainConfig(**edit).validate()


def _dataset(name, seed):
    rng = np.random.default_rng(seed)
    values = rng.uniform(-1, 1, 24)
    # Bright images are the anomalies, with some overlap: something to learn.
    brightness = np.where(values <= 0, 170, 90) + rng.integers(-60, 60, 24)
    images = np.clip(brightness[:, None, None, None] + rng.integers(-20, 20, (24, 16, 20, 3)),
                     0, 255).astype(np.uint8)
    return LabelledData.from_arrays(images=images, states=np.zeros((24, 3)), values=values,
                                    environment=name, camera_size=(16, 20))


def test_fold_training_is_blind_to_its_group_and_resumes(tmp_path):
    data = [_dataset(f"ENV{i}", i) for i in range(3)]
    config = DetectorTrainConfig(detector=DetectorConfig(height=16, width=20, channels=[4, 8]),
                                 epochs=1, batch_size=8, device="cpu", augment=False,
                                 threshold_folds=3, target_recall=0.9)
    asked = []

    def checkpoint_for(left_out):
        asked.append(tuple(left_out))
        return tmp_path / f"without_{'_'.join(left_out)}.pt"

    chosen = held_out_operating_threshold(data, config, checkpoint_for)
    assert asked == [("ENV0",), ("ENV1",), ("ENV2",)]
    # Each fold's detector trained on the other two only, and scored its own.
    groups = {}
    for d in data:
        name = d.manifest["environment"]
        model, detector_config, meta = load_detector(tmp_path / f"without_{name}.pt")
        assert sorted(meta["environments"]) == sorted({"ENV0", "ENV1", "ENV2"} - {name})
        groups[name] = (d.labels, detector_scores(model, detector_config, d.images, device="cpu"))
    expected = held_out_threshold(groups, 0.9)
    assert chosen.threshold == expected.threshold
    assert chosen.per_group == expected.per_group
    # A second call trains nothing: the checkpoints are kept.
    stamps = {p: os.stat(p).st_mtime_ns for p in tmp_path.iterdir()}
    again = held_out_operating_threshold(data, config, checkpoint_for)
    assert again.threshold == chosen.threshold
    assert {p: os.stat(p).st_mtime_ns for p in tmp_path.iterdir()} == stamps


def test_fold_training_uses_the_labels_it_is_given(tmp_path):
    data = [_dataset(f"ENV{i}", i) for i in range(2)]
    config = DetectorTrainConfig(detector=DetectorConfig(height=16, width=20, channels=[4, 8]),
                                 epochs=1, batch_size=8, device="cpu", augment=False,
                                 threshold_folds=2, target_recall=0.9)
    flipped = [1 - d.labels for d in data]
    chosen = held_out_operating_threshold(data, config, lambda left: tmp_path / f"{left[0]}.pt",
                                          labels=flipped)
    for d, labels in zip(data, flipped):
        name = d.manifest["environment"]
        _, _, meta = load_detector(tmp_path / f"{name}.pt")
        assert meta["positives"] == int(sum((1 - o.labels).sum() for o in data if o is not d))
        assert chosen.per_group[name]["positives"] == int(labels.sum())
    with pytest.raises(ValueError, match="2 datasets need 2 label arrays, got 1"):
        held_out_operating_threshold(data, config, lambda left: tmp_path / "x.pt",
                                     labels=flipped[:1])


def test_report_sets_the_promise_beside_what_was_got():
    import dataclasses as dc
    from reachwatch.pipeline.detector_sections import threshold_section
    from reachwatch.pipeline.report import Page
    chosen = held_out_threshold({"A": ([1, 1, 0], [0.9, 0.6, 0.7]), "B": ([1, 0], [0.8, 0.1])}, 1.0)
    rows = [{"environment": "NEW", "method": "detector", "labels": "brt", "states": "all",
             "recall": 0.5},
            {"environment": "NEW", "method": "detector", "labels": "brt",
             "states": "not yet failed", "recall": 0.25}]
    page = Page("t")
    threshold_section(page, {"threshold": chosen.threshold, "held_out_threshold": dc.asdict(chosen)},
                      rows, DetectorTrainConfig(threshold_folds=2))
    text = "\n".join(page.md)
    assert "chosen on the training environments left out in 2 groups" in text
    assert "promised recall >= 100.00% on every left-out group" in text
    assert "| A | 3 | 2 | 0.6 | 100.00 | 66.67 |" in text
    assert "got on the held-out environments: NEW 50.00%." in text
    assert "prediction-error baseline" not in text
    baseline = held_out_threshold({"A": ([1, 0, 0], [0.9, 0.6, 0.7]), "B": ([1, 0], [0.8, 0.1])},
                                  1.0)
    page = Page("t")
    threshold_section(page, {"threshold": chosen.threshold, "held_out_threshold": dc.asdict(chosen),
                             "prediction_error_detector_threshold": baseline.threshold,
                             "prediction_error_held_out_threshold": dc.asdict(baseline)},
                      rows, DetectorTrainConfig(threshold_folds=2))
    assert ("The prediction-error baseline's threshold 0.8 was chosen the same way, on its own "
            "labels: it promised recall >= 100.00% on every left-out group, flagging 40.00% of "
            "their images.") in "\n".join(page.md)
    page = Page("t")
    threshold_section(page, {"threshold": 0.3}, rows, DetectorTrainConfig())
    assert "a random validation split of the training images" in "\n".join(page.md)


def test_class_balance_weights_each_class_to_half_the_loss(tmp_path):
    from reachwatch.training.detector_train import class_weights, train_detector
    balanced = DetectorTrainConfig(class_balance=True)
    assert class_weights(np.array([0, 0, 0, 1]), DetectorTrainConfig()) is None
    assert class_weights(np.array([0, 0, 0, 1]), balanced).tolist() == pytest.approx([2 / 3, 2.0])
    assert class_weights(np.array([0, 0]), balanced).tolist() == pytest.approx([0.5, 1.0])
    with pytest.raises(ValueError, match="detector.class_balance must be true or false, got 'yes'"):
        DetectorTrainConfig(class_balance="yes").validate()
    # The weights used are the training split's, kept in the checkpoint's metadata.
    data = [_dataset("ENV0", 0)]
    config = DetectorTrainConfig(detector=DetectorConfig(height=16, width=20, channels=[4, 8]),
                                 epochs=1, batch_size=8, device="cpu", augment=False,
                                 class_balance=True, target_recall=0.0)
    train_detector(data, config, tmp_path / "balanced.pt")
    _, _, meta = load_detector(tmp_path / "balanced.pt")
    val = np.sort(np.random.default_rng(0).permutation(24)[:5])
    train_labels = np.delete(data[0].labels, val)
    assert meta["class_weights"] == pytest.approx(
        class_weights(train_labels, config).tolist())


def test_an_unreadable_checkpoint_is_trained_again_not_refused(tmp_path, caplog):
    """A checkpoint that cannot be read where a detector would be reused (a damaged
    file) is trained again, said in one line."""
    from reachwatch.training.detector_train import trained_detector
    path = tmp_path / "detector.pt"
    path.write_bytes(b"not a checkpoint")
    trained = []

    def train():
        trained.append(1)
        from reachwatch.diagrams import save_checkpoint
        from reachwatch.systems import DetectorConfig, build_detector
        config = DetectorConfig(height=24, width=40, channels=[4, 8])
        save_checkpoint(path, kind="detector", model=build_detector(config),
                        model_config=config, preprocess_config=None,
                        metadata={"image_size": [24, 40], "threshold": 0.5})
    with caplog.at_level("WARNING", logger="reachwatch"):
        model, config, meta = trained_detector(path, train)
    assert trained == [1] and meta["threshold"] == 0.5
    assert "training it again" in caplog.text
    trained_detector(path, train)                 # readable now: not trained again
    assert trained == [1]


def test_a_checkpoint_of_another_version_is_refused_not_trained_over(tmp_path):
    """Only a file torch cannot read is trained again; one a newer reachwatch wrote is
    refused as it is, and kept."""
    import torch
    from reachwatch.diagrams.checkpoints import CheckpointError, UnreadableCheckpoint
    from reachwatch.training.detector_train import trained_detector
    path = tmp_path / "detector.pt"
    from reachwatch.diagrams import checkpoints
    torch.save({"format": checkpoints.FORMAT, "version": 10**6}, path)
    with pytest.raises(CheckpointError) as e:
        trained_detector(path, lambda: pytest.fail("trained over a newer checkpoint"))
    assert not isinstance(e.value, UnreadableCheckpoint) and path.is_file()
