"""The test-time BatchNorm adaptation of benchmarks/detector_variants.py."""

import importlib.util
from pathlib import Path

import numpy as np
import torch

from reachwatch.systems.detector import DetectorConfig, SmallDetectorCNN, detector_input

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "detector_variants.py"
_SPEC = importlib.util.spec_from_file_location("detector_variants", _PATH)
variants = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(variants)


def test_adapted_statistics_are_those_of_the_images_and_the_weights_stay():
    torch.manual_seed(0)
    config = DetectorConfig(height=12, width=20, channels=[4, 6])
    model = SmallDetectorCNN(config).eval()
    images = np.random.default_rng(0).integers(0, 255, (10, 12, 20, 3), dtype=np.uint8)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    out = variants.adapted(model, config, images, batch_size=len(images))
    # the first BatchNorm now holds the mean and (unbiased) variance of the first
    # convolution's output over the images, per channel
    with torch.no_grad():
        y = model.features[0](detector_input(torch.from_numpy(images), config))
    bn = out.features[1]
    assert torch.allclose(bn.running_mean, y.mean(dim=(0, 2, 3)), atol=1e-5)
    assert torch.allclose(bn.running_var, y.var(dim=(0, 2, 3), unbiased=True), rtol=1e-4)
    assert not torch.allclose(bn.running_mean, before["features.1.running_mean"])
    assert not out.training
    # the weights are unchanged, and so is the model adapted from
    after = out.state_dict()
    for key, value in before.items():
        if "running" not in key and "num_batches" not in key:
            assert torch.equal(after[key], value), key
        assert torch.equal(model.state_dict()[key], value), key


def test_nominal_states_are_near_the_centreline_and_aligned():
    states = np.array([[0.0, 150.0, 0.0], [5.0, 150.0, 0.0], [1.0, 150.0, np.deg2rad(12.0)],
                       [-2.0, 200.0, np.deg2rad(-9.0)]])
    assert variants.nominal_states(states, half_width=12.0).tolist() == [True, False, False,
                                                                          True]


def test_promise_line_puts_the_left_out_promise_beside_the_held_out_recall():
    from reachwatch.training.metrics import held_out_threshold
    # two left-out groups; the lower group threshold (0.4) reaches full recall on both
    groups = {"a": (np.array([1, 1, 0, 0]), np.array([0.9, 0.4, 0.3, 0.1])),
              "b": (np.array([1, 0, 0, 0]), np.array([0.8, 0.5, 0.2, 0.1]))}
    chosen = held_out_threshold(groups, 1.0)
    assert chosen.threshold == 0.4
    results = [{"all": {"recall": 1.0, "flagged": 0.5}}, {"all": {"recall": 0.5, "flagged": 0.2}},
               {"all": {"recall": 0.75, "flagged": 0.3}}]
    line = variants.promise_line("x", chosen, results)
    # promised: recall 100 on the lowest group; 4 of 8 samples flagged, one of them a
    # false alarm (b's 0.5), so pooled accuracy 7/8; got: recall 50 / 75, flagged 20 / 30
    assert "promised on 2 left-out groups: recall 100.0 (lowest group), accuracy  87.5, " \
           "flagged  50.0" in line
    assert "got on 3 held-out: recall min/median  50.0/ 75.0, flagged  20.0/ 30.0" in line


def test_summary_lines_split_the_held_out_environments_by_group():
    def row(env, method, recall, accuracy, auroc):
        return {"environment": env, "method": method, "labels": "brt", "states": "all",
                "n": 100, "positives": 20, "tp": int(20 * recall), "fp": 0,
                "fn": 20 - int(20 * recall), "tn": 80, "recall": recall, "accuracy": accuracy,
                "auroc": auroc, "accuracy_at_target_recall": accuracy}

    rows = [row("DAY", "det", 1.0, 0.97, 0.99), row("DAY", "base", 0.5, 0.8, 0.7),
            row("RND1-0", "det", 0.5, 0.9, 0.6), row("RND1-0", "base", 0.5, 0.8, 0.7)]
    listed, rand = variants.summary_lines("v", rows, {"listed": ["DAY"],
                                                      "random, seed 1": ["RND1-0"]})
    assert listed.startswith("v                        listed           all             ")
    assert "recall 100.0/100.0" in listed and "both >= 95 in 1/1" in listed
    assert "AUROC beats baselines in 1/1" in listed
    assert "random, seed 1" in rand and "recall  50.0/ 50.0" in rand
    assert "both >= 95 in 0/1" in rand and "AUROC beats baselines in 0/1" in rand
