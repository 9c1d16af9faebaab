"""The learning stages of ``reachwatch run``: train -> evaluate. The detector on the
dataset's labels and its baselines (the controller's prediction error, an ensemble's
variance), each with its operating threshold; then Table 2 on the held-out
environments, with its figures."""

import dataclasses as dc

import numpy as np

from reachwatch.diagrams import load_detector
from reachwatch.reach.fingerprint import modules_source_digest
from reachwatch.systems.checks import device_kind
from reachwatch.systems.files import atomic_write_bytes, file_hash
from reachwatch.training.baselines import estimate_error_of
from reachwatch.training.labels import SOURCE_BRT, SOURCE_PATH, label_source, labels_name
from reachwatch.training.detector_train import (THRESHOLD_CHOICE, held_out_operating_threshold,
                                                operating_threshold, train_detector,
                                                trained_detector)
from reachwatch.training.evaluation import (NOT_FAILED, READ_ALONG, UNIFORM_STARTS, Detector,
                                            csv_table, evaluate_environment, markdown_table,
                                            worst_mistakes)
from reachwatch.training.figures import (plot_error_vs_margin, plot_examples, plot_overlay,
                                         plot_roc)
from reachwatch.training.metrics import best_threshold

from .keys import digest
from .stages import Run


#: The source a trained detector's weights and operating threshold come from: its
#: network, its training loop and the threshold rules. In its checkpoint's name
#: (`detector_weights`), so that a training edited since is trained again, not read
#: back from the old file.
WEIGHTS_CODE = ("reachwatch.systems.detector", "reachwatch.training.detector_train",
                "reachwatch.training.metrics")

#: The source in the train and evaluate stages' keys: `WEIGHTS_CODE`, this module, and
#: every module of training/ they import (a test walks the imports), so that an edit
#: there trains and scores again instead of reporting the old figures.
DETECTOR_CODE = WEIGHTS_CODE + ("reachwatch.pipeline.detector_stages",
                                "reachwatch.training.baselines",
                                "reachwatch.training.evaluation", "reachwatch.training.figures",
                                "reachwatch.training.labels")


def controller_name(scenario) -> str:
    """The controller under test as tables name it: TaxiNet, or the user's factory
    (its function's name)."""
    factory = scenario.controller.factory
    return factory.rpartition(":")[2] if factory else "TaxiNet"


def baseline_code() -> str:
    """The source digest of the baselines' code (the prediction error, the ensemble's
    variance): in the keys of the stages that compute them and in the name of the
    prediction-error detector, as another definition gives other figures."""
    return modules_source_digest("reachwatch.training.baselines")


def estimate_error(run: Run):
    """The prediction-error baseline of ``run``'s controller (`baselines.EstimateError`),
    or None when its application does not say what the controller estimates."""
    return estimate_error_of(run.application, controller_name(run.spec.scenario))


def detector_weights(config) -> dict:
    """What a detector's trained weights depend on, which names its checkpoint file: its
    training settings, not how its threshold is chosen (that changes neither the weights
    nor the file); the content of its pretrained weights, not only their path (a file
    replaced in place trains again); the kind of device that trains it ("" resolved:
    CUDA when present; another kind trains other weights); and its code
    (`WEIGHTS_CODE`)."""
    weights = {k: v for k, v in dc.asdict(config).items() if k not in THRESHOLD_CHOICE}
    weights["device"] = device_kind(config.device)
    if config.pretrained_path:
        weights["pretrained_content"] = file_hash(config.pretrained_path)
    weights["code"] = modules_source_digest(*WEIGHTS_CODE)
    return weights


def train_key(run: Run) -> str:
    """The train stage's key: the datasets' content, which of them it trains on (their
    environments' names: the same datasets with the roles swapped train another
    detector), the weights' inputs (`detector_weights`), the threshold's settings, and
    `DETECTOR_CODE`."""
    spec = run.spec
    return digest(run.content_key("dataset"), spec.detector, detector_weights(spec.detector),
                  [e.name for e in spec.training_environments()],
                  {"code": modules_source_digest(*DETECTOR_CODE)})


def evaluate_key(run: Run) -> str:
    """The evaluate stage's key: what it scores (the trained detectors, the datasets,
    each held-out environment's BRT by content), the slice its figures draw, the
    scoring device's kind, and `DETECTOR_CODE`."""
    spec = run.spec
    return digest(run.content_key("train"), run.content_key("dataset"), spec.slice_py,
                  device_kind(spec.detector.device),
                  {e.name: run.content_key(f"solve_{e.name}") for e in spec.held_out_environments()},
                  {"code": modules_source_digest(*DETECTOR_CODE)})


def stage_train(run: Run) -> dict:
    """The detector on BRT labels, and the same detector on prediction-error labels
    (baseline a), each with its operating threshold."""
    spec, config = run.spec, run.spec.detector
    data = run.datasets(spec.training_environments())
    progress = run.bar()
    weights = detector_weights(config)
    folders = run.outputs["dataset"]["folders"]
    tag = digest(weights, {e.name: folders[e.name] for e in spec.training_environments()})
    brt_path = run.path(f"detectors/detector_brt_{tag}.pt")
    seconds = None

    def train():
        nonlocal seconds
        seconds = train_detector(data, config, brt_path, progress=progress)["train_seconds"]
    model, _, meta = trained_detector(brt_path, train)
    out = {"detector": run.rel(brt_path), "validation": meta.get("validation", {}),
           "train_seconds": seconds}

    held_out = []       # in the outputs, so that the record holds their hashes too

    def checkpoint_for_prefix(prefix, *labelling):
        def checkpoint_for(left_out):
            kept = {e.name: folders[e.name] for e in spec.training_environments()
                    if e.name not in left_out}
            key = digest(weights, kept, *labelling)
            held_out.append(run.rel(run.path(f"detectors/{prefix}_heldout_{key}.pt")))
            return run.path(held_out[-1])
        return checkpoint_for

    if config.threshold_folds:
        chosen = held_out_operating_threshold(data, config, checkpoint_for_prefix("detector_brt"),
                                              progress=progress)
        out["threshold"] = chosen.threshold
        out["held_out_threshold"] = dc.asdict(chosen)
        out["held_out_checkpoints"] = held_out
    else:
        out["threshold"] = float(operating_threshold(model, data, config))
    error = estimate_error(run)
    if error is None:
        return out          # a controller whose estimate the application does not know
    for env, d in zip(spec.training_environments(), data):
        refusal = error.refusal(d.states, d.estimates)
        if refusal is not None:
            run.log(f"no prediction-error baseline: {env.name}: {refusal}")
            return out
    errors = np.concatenate([error(d.states, d.estimates) for d in data])
    error_threshold, _ = best_threshold(np.concatenate([d.labels for d in data]), errors)
    labels = [error.labels(d, error_threshold) for d in data]
    # named by its labels too: another scale, error threshold or labelling code labels
    # other states
    labelling = [list(error.scale), float(error_threshold), baseline_code()]
    labelling_key = digest(*labelling)[:8]
    error_path = run.path(f"detectors/detector_prediction_error_{tag}_{labelling_key}.pt")
    trained_detector(error_path, lambda: train_detector(data, config, error_path,
                                                       progress=progress, labels=labels))
    out.update({"prediction_error_detector": run.rel(error_path),
                "prediction_error_threshold": float(error_threshold)})
    if config.threshold_folds:          # the baseline's threshold is chosen the same way
        chosen = held_out_operating_threshold(
            data, config, checkpoint_for_prefix("detector_prediction_error", *labelling),
            labels=labels, progress=progress)
        out["prediction_error_detector_threshold"] = chosen.threshold
        out["prediction_error_held_out_threshold"] = dc.asdict(chosen)
    else:
        model, _, _ = load_detector(error_path)
        out["prediction_error_detector_threshold"] = operating_threshold(model, data, config,
                                                                         labels)
    return out


def stage_evaluate(run: Run) -> dict:
    """Table 2 on the held-out environments, error-vs-margin and overlay figures."""
    spec, trained = run.spec, run.outputs["train"]
    detectors = []
    source = labels_name(label_source(spec.dataset.labels.source).table_name,
                         spec.dataset.labels.paths)
    candidates = [(f"detector ({source} labels)", trained["detector"], trained["threshold"])]
    if "prediction_error_detector" in trained:
        candidates.append((f"detector (prediction-error labels, error > "
                           f"{trained['prediction_error_threshold']:.3f})",
                           trained["prediction_error_detector"],
                           trained["prediction_error_detector_threshold"]))
    for name, path, threshold in candidates:
        model, config, _ = load_detector(run.path(path))
        detectors.append(Detector(name, model, config, threshold))
    rows, figures = [], {}
    held_out = spec.held_out_environments()
    # Each row's accuracy at an oracle threshold for the recall the figures are judged at.
    ceiling_recall = spec.detector.judged_recall
    error = estimate_error(run)
    for env, d in zip(held_out, run.datasets(held_out)):
        # States that have not failed yet: for the taxi, the aircraft still on the runway.
        inside = ~run.application.failed(run.scenario_for(env), d.states)
        subsets = {NOT_FAILED: inside}
        if np.any(d.sources == SOURCE_PATH):      # read-along states: each kind alone too
            subsets[UNIFORM_STARTS] = d.sources != SOURCE_PATH
            subsets[READ_ALONG] = d.sources == SOURCE_PATH
        refusal = None if error is None else error.refusal(d.states, d.estimates)
        if refusal is not None and "prediction_error_detector" in trained:
            # the training environments had the baseline, this one has not: say why
            run.log(f"{env.name}: no prediction-error rows in Table 2: {refusal}")
        env_rows, scores = evaluate_environment(d, detectors, device=spec.detector.device,
                                                subsets=subsets, target_recall=ceiling_recall,
                                                estimate_error=error)
        rows += env_rows
        if np.any(d.sources != SOURCE_BRT):       # also scored against the BRT's verdicts
            as_brt = dc.replace(d, labels=d.brt_labels,
                                manifest={**d.manifest, "labels": {"source": "brt"}})
            rows += evaluate_environment(as_brt, detectors, device=spec.detector.device,
                                         subsets=subsets, target_recall=ceiling_recall,
                                         estimate_error=error)[0]
        predictions = {r["method"]: scores[r["method"]] >= r["threshold"]
                       for r in env_rows if r["states"] == "all"}
        margin = plot_error_vs_margin({m: (d.values, d.labels, p) for m, p in predictions.items()},
                                      run.path(f"figures/error_vs_margin_{env.name}.png"))
        overlay = plot_overlay(run.application, run.scenario_for(env), run.value_function(env.name),
                               d.states, d.labels, predictions[detectors[0].name],
                               at=spec.slice_py, path=run.path(f"figures/overlay_{env.name}.png"),
                               title=f"{env.name}: {detectors[0].name}")
        thresholds = {r["method"]: r["threshold"] for r in env_rows if r["states"] == "all"}
        roc = plot_roc({m: (d.labels, scores[m], t) for m, t in thresholds.items()},
                       run.path(f"figures/roc_{env.name}.png"),
                       title=f"{env.name}: ROC over all states (dots: operating points)")
        main = detectors[0]
        misses, alarms = worst_mistakes(d.labels, scores[main.name], main.threshold, 4)
        caption = lambda kind, i: (f"{kind}: score {scores[main.name][i]:.3f}, "  # noqa: E731
                                   f"V {d.values[i]:+.2f}\nstate "
                                   f"{np.array2string(d.states[i], precision=2)}")
        examples = plot_examples([d.images[i] for i in np.r_[misses, alarms]],
                                 [caption("missed", i) for i in misses] +
                                 [caption("false alarm", i) for i in alarms],
                                 run.path(f"figures/mistakes_{env.name}.png"),
                                 title=f"{env.name}: {main.name}, its most confident misses "
                                       f"and false alarms")
        figures[env.name] = {"error_vs_margin": run.rel(margin), "overlay": run.rel(overlay),
                             "roc": run.rel(roc), "mistakes": run.rel(examples),
                             "mistake_counts": {"misses": len(misses), "false_alarms": len(alarms)}}
    atomic_write_bytes(run.path("table2.md"), markdown_table(rows).encode())
    atomic_write_bytes(run.path("table2.csv"), csv_table(rows).encode())
    return {"rows": rows, "figures": figures, "table_md": "table2.md", "table_csv": "table2.csv"}
