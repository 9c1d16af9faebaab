import dataclasses as dc
import json

import numpy as np
import pytest
import torch
from pydrake.systems.sensors import ImageRgba8U

from reachwatch.diagrams import CheckpointError, load_detector, load_scenario, save_checkpoint
from reachwatch.reach import solve_brt
from reachwatch.taxi import TaxiDynamics, paper_grid
from reachwatch.systems import AnomalyDetector, DetectorConfig, build_detector
from reachwatch.taxi.application import TaxiApplication
from reachwatch.training.baselines import EstimateError, ensemble_variance, estimate_error_of
from reachwatch.training.dataset import DatasetSpec, LabelledData, build_dataset, load_dataset
from reachwatch.training.evaluation import NOT_FAILED, evaluate_environment
from reachwatch.training.metrics import auroc, best_threshold, binary_metrics
from tiny_run import taxi_application

TINY = DetectorConfig(height=24, width=40, channels=[4, 8])
TAXINET_ERROR = estimate_error_of(TaxiApplication(), "TaxiNet")


# --- metrics -----------------------------------------------------------------------

def test_metrics_on_a_hand_made_confusion_matrix():
    labels = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0, 0])
    preds = np.array([1, 1, 1, 0, 1, 0, 0, 0, 0, 0])
    m = binary_metrics(labels, preds)
    assert (m.tp, m.fn, m.fp, m.tn) == (3, 1, 1, 5)
    assert m.recall == pytest.approx(0.75) and m.precision == pytest.approx(0.75)
    assert m.accuracy == pytest.approx(0.8) and m.f1 == pytest.approx(0.75)
    assert np.isnan(binary_metrics([0, 0], [0, 1]).recall)


def test_auroc_and_best_threshold():
    labels = np.array([0, 0, 1, 1])
    assert auroc(labels, [0.1, 0.2, 0.8, 0.9]) == 1.0
    assert auroc(labels, [0.9, 0.8, 0.2, 0.1]) == 0.0
    assert auroc(labels, [0.5, 0.5, 0.5, 0.5]) == 0.5
    t, m = best_threshold(labels, np.array([0.1, 0.2, 0.8, 0.9]))
    assert 0.2 < t <= 0.8 and m.f1 == 1.0


def test_baseline_scores():
    states = np.array([[1.0, 150.0, np.deg2rad(10.0)]])
    assert TAXINET_ERROR(states, [[1.0, 10.0]])[0] == pytest.approx(0.0)
    assert TAXINET_ERROR(states, [[11.0, 10.0]])[0] == pytest.approx(1.0)      # 10 m
    assert TAXINET_ERROR(states, [[1.0, 40.0]])[0] == pytest.approx(1.0)       # 30 deg
    same = np.ones((3, 4, 2))
    np.testing.assert_allclose(ensemble_variance(same, TAXINET_ERROR.scale), 0.0)
    spread = np.stack([np.zeros((3, 2)), np.full((3, 2), 2.0)], axis=1)       # variance 1
    np.testing.assert_allclose(ensemble_variance(spread), 2.0)
    np.testing.assert_allclose(ensemble_variance(spread, (1.0, 2.0)), 1.25)
    with pytest.raises(ValueError, match=">= 2 members"):
        ensemble_variance(np.ones((3, 1, 2)))
    with pytest.raises(ValueError, match="scale needs 2 finite numbers > 0"):
        ensemble_variance(spread, (1.0, 0.0))


def test_the_prediction_error_baseline_reads_the_applications_truth():
    """A plant of one's own: its truth, not the taxi's ``[px, theta deg]`` (which read a
    2-state plant's ``states[:, 2]`` and failed), and no baseline where the application
    does not say what its controller estimates or the estimate has another size."""
    own = EstimateError(truth=lambda s: s[:, :2], controller="RailFollower")
    states = np.array([[0.1, 0.2], [0.0, 0.0]])
    np.testing.assert_allclose(own(states, [[0.1, 0.2], [3.0, 4.0]]), [0.0, 5.0])
    assert not own.applies(states, np.zeros((2, 3))) and not own.applies(states, np.zeros((2, 0)))
    assert own.refusal(states, np.zeros((2, 3))) == ("the controller's estimate has 3 "
                                                     "numbers, the true estimate 2")
    assert own.refusal(states, np.zeros((2, 0))) == "the controller has no estimate"
    assert own.refusal(states[:0], np.zeros((0, 2))) == ("no states to measure it at (states "
                                                          "(0, 2), estimates (0, 2))")
    with pytest.raises(ValueError, match="RailFollower: the controller's estimate has 3"):
        own(states, np.zeros((2, 3)))
    # an estimate NaN or infinite anywhere is no estimate to measure an error of: an
    # error of NaN labelled nothing and ranked nothing, yet gave Table 2 rows
    for bad in (np.nan, np.inf):
        estimates = np.array([[0.1, 0.2], [bad, 0.0]])
        assert own.refusal(states, estimates) == ("the controller's estimate is NaN or "
                                                  "infinite at 1 of 2 states")
        with pytest.raises(ValueError, match="NaN or infinite at 1 of 2 states"):
            own(states, estimates)
    assert estimate_error_of(type("NoEstimate", (), {"true_estimate": None})) is None
    data, _ = _six_samples([0.0, 10.0, 20.0, 30.0, 20.0, 30.0])
    methods = lambda error: [r["method"] for r in evaluate_environment(      # noqa: E731
        data, [], estimate_error=error)[0]]
    assert methods(TAXINET_ERROR) == ["TaxiNet prediction error (best threshold)"]
    assert methods(None) == []
    assert methods(EstimateError(truth=lambda s: s[:, :1])) == []     # the estimate is 2 wide
    data.estimates[3, 1] = np.nan
    assert methods(TAXINET_ERROR) == []                 # no row of an error it cannot measure


# --- detector system -----------------------------------------------------------------

def _image(h, w, value):
    image = ImageRgba8U(w, h)
    image.mutable_data[:] = value
    return image


def test_detector_system_ports_threshold_and_size():
    torch.manual_seed(0)
    model = build_detector(TINY)
    for threshold, expected in [(0.0, 1.0), (1.0, 0.0)]:
        system = AnomalyDetector(model=model, config=TINY, threshold=threshold,
                                 image_size=(50, 90))
        context = system.CreateDefaultContext()
        system.get_color_image_input_port().FixValue(context, _image(50, 90, 120))
        score = system.get_score_output_port().Eval(context)[0]
        assert 0.0 < score < 1.0
        assert system.get_anomaly_output_port().Eval(context)[0] == expected
    assert [system.get_output_port(i).get_name() for i in range(2)] == ["anomaly", "score"]
    system.get_color_image_input_port().FixValue(context, _image(40, 90, 0))
    with pytest.raises(ValueError, match="40x90.*50x90"):
        system.get_score_output_port().Eval(context)
    with pytest.raises(ValueError, match="threshold"):
        AnomalyDetector(model=model, config=TINY, threshold=1.5)


def test_detector_checkpoint_round_trip_and_errors(tmp_path):
    model = build_detector(TINY)
    save_checkpoint(tmp_path / "d.pt", kind="detector", model=model, model_config=TINY,
                    preprocess_config=None, metadata={"image_size": [50, 90]})
    loaded, config, meta = load_detector(tmp_path / "d.pt")
    assert config == TINY and meta["image_size"] == [50, 90]
    x = torch.rand(2, 3, 24, 40)
    model.eval()
    torch.testing.assert_close(loaded(x), model(x))
    with pytest.raises(CheckpointError, match="'detector' model, not a 'taxinet'"):
        from reachwatch.diagrams import load_taxinet
        load_taxinet(tmp_path / "d.pt")
    with pytest.raises(ValueError, match="could not load EfficientNet"):
        build_detector(DetectorConfig.paper(), pretrained_path=str(tmp_path / "missing.pt"))


# --- dataset -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny_brt():
    grid = paper_grid(10.0, (9, 3, 9))
    px, _, th = grid.mesh()
    table = np.deg2rad(-0.74 * px - 0.44 * np.rad2deg(th) + 8.0)     # a biased controller
    return solve_brt(grid, TaxiDynamics(half_width=10.0), table, horizon=4.0, device="cpu")


def test_dataset_labels_follow_the_value_sign_and_resume(tmp_path, tiny_brt):
    scenario = load_scenario(data="")
    spec = DatasetSpec(samples=24, seed=3, height=20, width=36, chunk_size=10)
    folder = build_dataset(tmp_path, scenario, tiny_brt, spec, progress=False, application=taxi_application())
    data = load_dataset(folder)
    assert data.images.shape == (24, 20, 36, 3) and data.estimates.shape == (24, 2)
    np.testing.assert_array_equal(data.labels, tiny_brt.at(data.states) <= 0)
    assert np.all(tiny_brt.grid.contains(data.states))
    assert 0 < data.labels.sum() < 24
    first = np.array(data.images)
    # an interrupted build: the manifest lost its last chunk and the images were wiped
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["chunks_done"] = manifest["chunks_done"][:1]
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="incomplete"):
        load_dataset(folder)
    images = np.load(folder / "images.npy", mmap_mode="r+")
    images[10:] = 0
    images.flush()
    del images
    assert build_dataset(tmp_path, scenario, tiny_brt, spec, progress=False, application=taxi_application()) == folder
    np.testing.assert_array_equal(load_dataset(folder).images, first)


def test_online_detector_sees_the_pixels_the_dataset_stored():
    """The system resizes camera frames exactly as datasets store them (area filter)."""
    from reachwatch.systems import resize_for_detector
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (3, 200, 360, 3), dtype=np.uint8)
    small = resize_for_detector(frames, TINY)
    assert small.shape == (3, TINY.height, TINY.width, 3) and small.dtype == np.uint8
    model = build_detector(TINY).eval()
    system = AnomalyDetector(model=model, config=TINY)
    np.testing.assert_allclose(system.scores(frames), system.scores(small), rtol=1e-6)
    # The system's path: the camera's RGBA frame, alpha dropped by OpenCV, same pixels.
    rgba = np.concatenate([frames, rng.integers(0, 256, (3, 200, 360, 1), np.uint8)], -1)
    np.testing.assert_array_equal(resize_for_detector(rgba, TINY), small)
    np.testing.assert_allclose(system.scores(rgba), system.scores(small), rtol=1e-6)
    with pytest.raises(ValueError, match=r"\(N, H, W, 3\|4\)"):
        resize_for_detector(frames[..., :2], TINY)


@pytest.mark.parametrize("stem_stride", [1, 2])
def test_inference_model_computes_the_same_scores_and_leaves_the_model_alone(stem_stride):
    """The system's copy folds BatchNorm into the convolutions (channels-last); its
    scores equal the trained model's, and the caller's model is not touched."""
    from reachwatch.systems.detector import inference_model
    config = DetectorConfig(height=64, width=96, channels=[4, 8, 8], stem_stride=stem_stride)
    torch.manual_seed(0)
    model = build_detector(config)
    for m in model.modules():                         # non-trivial running statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.3, 0.3)
            m.running_var.uniform_(0.5, 2.0)
    model.train()
    fast = inference_model(model)
    assert model.training and sum(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules()) == 3
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fast.modules())
    x = torch.randn(5, 3, 64, 96)
    with torch.no_grad():
        np.testing.assert_allclose(fast(x).numpy(), model.eval()(x).numpy(), atol=1e-5)
    with pytest.raises(ValueError, match="stem_stride"):
        DetectorConfig(stem_stride=3).validate()


@pytest.mark.skipif(not torch.backends.mkldnn.is_available(), reason="no oneDNN in this torch")
def test_inference_model_computes_one_frame_as_a_batch_does():
    """One frame through `inference_model`'s convolutions gives exactly the numbers the
    same frame gives inside a batch (the offline path): they run oneDNN's kernel
    at batch 1 too, where PyTorch would pick its reference kernel for a small input and
    round differently. Its convolutions stay `Conv2d`s."""
    from reachwatch.systems import HistoryMonitorConfig, HistoryRiskModel
    from reachwatch.systems.detector import OneDnnConv2d, detector_input, inference_model
    from reachwatch.systems.history_model import normalised
    torch.manual_seed(0)
    model = HistoryRiskModel(HistoryMonitorConfig(frames=1)).eval()
    fast = inference_model(model)
    convs = [m for m in fast.modules() if isinstance(m, torch.nn.Conv2d)]
    assert convs and all(type(m) is OneDnnConv2d for m in convs)
    frames = torch.randint(0, 256, (4, 48, 80, 3), dtype=torch.uint8)
    x = normalised(detector_input(frames, model.config.image_config), model.config.input_norm)
    with torch.inference_mode():              # the convolutions (the projection after
        batch = fast.encoder(x)               # them is a matrix product, whose rounding
        alone = torch.cat([fast.encoder(x[i:i + 1]) for i in range(4)])   # may differ)
    np.testing.assert_array_equal(alone.numpy(), batch.numpy())


def _six_samples(errors):
    """6 samples labelled 0 0 1 1 1 1 whose TaxiNet px estimates are off by ``errors`` m
    (what the prediction-error baseline scores); the last two states have already
    failed (px 20 m, beyond the edge): easy positives. ``(data, states)``."""
    states = np.zeros((6, 3))
    states[4:, 0] = 20.0
    data = LabelledData.from_arrays(images=np.zeros((6, 4, 4, 3), np.uint8), states=states,
                                    values=np.array([1, 1, -1, -1, -1, -1.0]),
                                    environment="tiny", camera_size=(4, 4))
    estimates = np.stack([states[:, 0] + np.asarray(errors, float), np.zeros(6)], axis=1)
    return dc.replace(data, estimates=estimates), states


def test_table2_rows_over_the_states_that_have_not_failed_yet():
    # the prediction-error baseline scores the 6 samples 0 1 2 3 2 3
    data, states = _six_samples([0.0, 10.0, 20.0, 30.0, 20.0, 30.0])
    inside = np.abs(states[:, 0]) < 10.0
    rows, scores = evaluate_environment(data, [], estimate_error=TAXINET_ERROR,
                                        subsets={NOT_FAILED: inside})
    assert [(r["states"], r["n"], r["positives"]) for r in rows] == [("all", 6, 4),
                                                                     (NOT_FAILED, 4, 2)]
    assert rows[1]["recall"] == rows[1]["accuracy"] == 1.0      # tuned again on the 4 states
    assert [rows[1][k] for k in ("tp", "fp", "fn", "tn")] == [2, 0, 0, 2]
    assert 1.0 < rows[1]["threshold"] <= 2.0 == scores[rows[1]["method"]][2]
    with pytest.raises(ValueError, match="subset 'x' must be a boolean mask of the 6"):
        evaluate_environment(data, [], estimate_error=TAXINET_ERROR,
                             subsets={"x": np.ones(5, bool)})
    # an empty subset adds no rows
    assert len(evaluate_environment(data, [], estimate_error=TAXINET_ERROR,
                                    subsets={"none": np.zeros(6, bool)})[0]) == 1


def test_table2_rows_give_the_accuracy_an_oracle_threshold_reaches_at_the_recall_target():
    # labels 0 0 1 1 1 1; the prediction-error baseline ranks them 3 0 1 2 4 5 (x10 m)
    data, _ = _six_samples([30.0, 0.0, 10.0, 20.0, 40.0, 50.0])
    # 95 %: every positive flagged, so the threshold is the lowest positive (10 m), which
    # also flags the negative at 30 m: 5 of 6 right
    row, = evaluate_environment(data, [], estimate_error=TAXINET_ERROR)[0]
    assert row["accuracy_at_target_recall"] == pytest.approx(5 / 6)
    # 50 %: two of four positives may be missed, the threshold is 40 m: 4 of 6 right
    row, = evaluate_environment(data, [], estimate_error=TAXINET_ERROR,
                                target_recall=0.5)[0]
    assert row["accuracy_at_target_recall"] == pytest.approx(4 / 6)
    # no positives: nothing to reach
    safe = dc.replace(data, labels=np.zeros(6, bool))
    row, = evaluate_environment(safe, [], estimate_error=TAXINET_ERROR)[0]
    assert np.isnan(row["accuracy_at_target_recall"])


def test_roc_points_and_worst_mistakes_known_answers():
    from reachwatch.training.evaluation import worst_mistakes
    from reachwatch.training.metrics import auroc, roc_points
    labels = [1, 0, 1, 0, 1]
    scores = [0.9, 0.8, 0.8, 0.3, 0.1]
    fpr, tpr, thresholds = roc_points(labels, scores)
    # flag nothing; >= 0.9; >= 0.8 (one of each); >= 0.3; >= 0.1 (everything)
    np.testing.assert_array_equal(thresholds, [np.inf, 0.9, 0.8, 0.3, 0.1])
    np.testing.assert_allclose(tpr, [0, 1 / 3, 2 / 3, 2 / 3, 1])
    np.testing.assert_allclose(fpr, [0, 0, 0.5, 1, 1])
    # the trapezoid area of the curve is the rank AUROC (ties averaged)
    assert np.trapezoid(tpr, fpr) == pytest.approx(auroc(labels, scores))
    misses, alarms = worst_mistakes(labels, scores, 0.5, 4)
    assert list(misses) == [4] and list(alarms) == [1]
    misses, alarms = worst_mistakes([1, 1, 1, 0, 0, 0], [0.1, 0.0, 0.2, 0.9, 0.7, 0.95], 0.5, 2)
    assert list(misses) == [1, 0] and list(alarms) == [5, 3]


def test_verdicts_call_out_a_detector_that_flags_everything():
    from reachwatch.pipeline.detector_sections import detector_verdicts

    def row(env, method, tp, fp, fn, tn, auroc, states="all"):
        n = tp + fp + fn + tn
        return {"environment": env, "method": method, "labels": "brt", "states": states,
                "n": n, "positives": tp + fn, "tp": tp, "fp": fp, "fn": fn, "tn": tn,
                "recall": tp / (tp + fn), "accuracy": (tp + tn) / n, "auroc": auroc}

    rows = [row("NIGHT", "detector", 19, 77, 1, 3, 0.55),     # flags 96 of 100
            row("NIGHT", "baseline", 10, 10, 10, 70, 0.75),
            row("NIGHT", "detector", 10, 80, 0, 0, 0.5, states="not yet failed"),
            row("DAY", "detector", 18, 5, 2, 75, 0.95),
            row("DAY", "baseline", 10, 10, 10, 70, 0.70),
            row("DUSK", "detector", 15, 30, 5, 50, 0.70),
            row("DUSK", "baseline", 10, 10, 10, 70, 0.80),
            row("DARK", "detector", 10, 40, 10, 40, 0.52)]
    night, day, dusk, dark = detector_verdicts(rows)
    assert night.startswith("NIGHT: the detector flags 96.00% of the images, while 20.00% "
                            "are anomalous; it catches 95.00% of the anomalies at 22.00% accuracy, "
                            "AUROC 55.00 (best other method: baseline, 75.00).")
    assert "here it is an alarm, not a detector" in night
    assert day.endswith("AUROC 95.00 (best other method: baseline, 70.00).")
    assert dusk.endswith("A baseline ranks the images better here.")
    assert dark.endswith("AUROC 52.00. Its scores barely separate the classes here (chance is 50).")
    assert detector_verdicts([]) == []
    # with the oracle's accuracy at the recall target, the verdict says what the ranking
    # allows, so a reader sees whether the threshold or the scores lost the accuracy
    night_row = {**rows[0], "accuracy_at_target_recall": 0.475}
    sentence, = detector_verdicts([night_row])
    assert ("AUROC 55.00. A threshold set on this environment's own labels for the recall "
            "target would give 47.50% accuracy (what its ranking allows). It flags nearly "
            "every image") in sentence
    assert detector_verdicts([{**rows[0], "accuracy_at_target_recall": float("nan")}]) == \
        detector_verdicts([rows[0]])


def test_target_summary_counts_environments_on_target_by_group_with_known_answers():
    from reachwatch.training.evaluation import target_summary

    def row(env, method, tp, fp, fn, tn, auroc, ceiling=0.9, states="all"):
        n = tp + fp + fn + tn
        return {"environment": env, "method": method, "labels": "brt", "states": states,
                "n": n, "positives": tp + fn, "tp": tp, "fp": fp, "fn": fn, "tn": tn,
                "recall": tp / (tp + fn) if tp + fn else float("nan"),
                "accuracy": (tp + tn) / n, "auroc": auroc, "accuracy_at_target_recall": ceiling}

    rows = [row("A", "det", 20, 2, 0, 78, 0.99),          # recall 100, accuracy 98: on target
            row("A", "base", 10, 10, 10, 70, 0.80),
            row("B", "det", 19, 30, 1, 50, 0.85, 0.6),    # recall 95, accuracy 69
            row("B", "base", 10, 10, 10, 70, 0.90),       # a baseline ranks B better
            row("C", "det", 10, 0, 10, 80, 0.97),         # recall 50, accuracy 90
            row("C", "base", 10, 10, 10, 70, 0.70),
            row("C", "det", 0, 5, 0, 45, None, float("nan"), states="not yet failed")]
    listed, rand, night = target_summary(rows, {"listed": ["A", "B"], "random": ["C"],
                                                "missing": ["Z"]})
    assert (listed["group"], listed["states"], listed["environments"]) == ("listed", "all", 2)
    assert listed["recall"] == pytest.approx((0.95, 0.975))
    assert listed["accuracy"] == pytest.approx((0.69, 0.835))
    assert listed["auroc"] == pytest.approx((0.85, 0.92))
    assert listed["accuracy_at_target_recall"] == pytest.approx((0.6, 0.75))
    assert listed["flagged"] == pytest.approx((0.22, 0.355))
    assert (listed["meet_recall"], listed["meet_both"], listed["beats_baselines"]) == (2, 1, 1)
    assert listed["worst"] == "B" and listed["method"] == "det"
    assert (rand["meet_recall"], rand["meet_both"], rand["beats_baselines"]) == (0, 0, 1)
    # a subset without positives: NaN figures stay NaN, no baseline to compare with
    assert night["states"] == "not yet failed" and night["beats_baselines"] is None
    assert np.isnan(night["recall"][0]) and np.isnan(night["auroc"][1])
    assert night["accuracy"] == pytest.approx((0.9, 0.9)) and night["meet_recall"] == 0
    # one group of everything by default; the recall target moves the counts
    everything, _ = target_summary(rows, recall=0.5, accuracy=0.9)
    assert everything["environments"] == 3 and everything["meet_both"] == 2
    assert target_summary([]) == []


def test_target_section_writes_the_target_rows_the_console_prints():
    from reachwatch.pipeline.evaluate_commands import target_text
    from reachwatch.training.detector_train import DetectorTrainConfig

    def row(env, method, tp, fp, fn, tn, auroc):
        n = tp + fp + fn + tn
        return {"environment": env, "method": method, "labels": "brt", "states": "all", "n": n,
                "positives": tp + fn, "tp": tp, "fp": fp, "fn": fn, "tn": tn,
                "recall": tp / (tp + fn), "accuracy": (tp + tn) / n, "auroc": auroc,
                "accuracy_at_target_recall": 0.9}

    rows = [row("A", "det", 20, 2, 0, 78, 0.99), row("A", "base", 10, 10, 10, 70, 0.8),
            row("B", "det", 10, 0, 10, 80, 0.97), row("B", "base", 10, 10, 10, 70, 0.7)]
    text = target_text(rows, {"listed": ["A"], "random, seed 1": ["B"]},
                           DetectorTrainConfig(target_recall=0.9))
    assert "recall >= 90.00% and accuracy >= 95.00%" in text
    assert ("| listed | brt | all | 1 | 100.00 / 100.00 | 98.00 / 98.00 | 99.00 / 99.00 | "
            "90.00 / 90.00 | 22.00 / 22.00 | 1 of 1 | 1 of 1 | 1 of 1 | A |") in text
    assert "| random, seed 1 | brt | all | 1 | 50.00 / 50.00 | 90.00 / 90.00 |" in text
    # a fixed threshold (target_recall 0) is judged at 95 % recall
    assert "recall >= 95.00%" in target_text(rows, {"listed": ["A"]}, DetectorTrainConfig())
    assert target_text([], {"listed": ["A"]}, DetectorTrainConfig()) == ""
