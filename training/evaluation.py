"""The paper's Table 2 and its baselines: per held-out environment, recall, accuracy,
precision, F1 and AUROC of each method against the dataset's labels (whatever their
source: the BRT, the real loop, or both; the ``labels`` column says which)."""

import csv
import dataclasses as dc
import io

import numpy as np

from .baselines import ensemble_variance, has_pose_estimate, prediction_error
from .detector_train import detector_scores
from .metrics import best_threshold, binary_metrics

COLUMNS = ("environment", "method", "labels", "n", "positives", "recall", "accuracy", "precision",
           "f1", "auroc", "threshold")


@dc.dataclass
class Detector:
    """A trained detector to evaluate: model, `DetectorConfig`, decision threshold."""
    name: str
    model: object
    config: object
    threshold: float = 0.5


def evaluate_environment(data, detectors, *, device="") -> list:
    """Rows (dicts with `COLUMNS`) for one `LabelledData`: each detector at its own
    threshold, then the baselines at the threshold maximising F1 on this same data
    (oracle-tuned, i.e. as generous to them as possible)."""
    env, labels, rows = data.manifest["environment"], data.labels, []
    source = data.manifest.get("labels", {}).get("source", "brt")
    scores = {}
    for det in detectors:
        s = detector_scores(det.model, det.config, data.images, device=device)
        scores[det.name] = s
        rows.append({"environment": env, "method": det.name, "labels": source,
                     "threshold": det.threshold,
                     **binary_metrics(labels, s >= det.threshold, s).row()})
    baselines = {}
    if has_pose_estimate(data):
        baselines["TaxiNet prediction error (best threshold)"] = \
            prediction_error(data.states, data.estimates)
    if data.ensemble.shape[1] >= 2:
        baselines[f"ensemble of {data.ensemble.shape[1]} variance (best threshold)"] = \
            ensemble_variance(data.ensemble)
    for name, s in baselines.items():
        threshold, metrics = best_threshold(labels, s)
        scores[name] = s
        rows.append({"environment": env, "method": name, "labels": source,
                     "threshold": float(threshold),
                     **metrics.row()})
    return rows, scores


def format_cell(value, key) -> str:
    """One Table-2 cell as text: rates in %, counts as integers, missing as -."""
    if isinstance(value, str):
        return value
    if key in ("n", "positives"):
        return str(int(value))
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "-"
    return f"{100 * value:.1f}" if key in ("recall", "accuracy", "precision", "f1", "auroc") \
        else f"{value:.3g}"


def markdown_table(rows) -> str:
    """Rows as a Markdown table (rates in %)."""
    head = "| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    return head + "\n".join("| " + " | ".join(format_cell(r.get(k), k) for k in COLUMNS) + " |"
                            for r in rows) + "\n"


def csv_table(rows) -> str:
    """Rows as CSV (rates as fractions; method names quoted when they hold commas)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(COLUMNS)
    for r in rows:
        writer.writerow([r.get(k, "") for k in COLUMNS])
    return out.getvalue()
