"""The paper's Table 2 and its baselines: per held-out environment, recall, accuracy,
precision, F1 and AUROC of each method against the dataset's labels (whatever their
source: the BRT, the real loop, or both; the ``labels`` column says which), over all
the environment's states and over named subsets of them (the ``states`` column), e.g.
the states that have not failed yet: states already outside the safe set are failures
by definition, easy to flag, and on a wide safe set a large share of the positives."""

import csv
import dataclasses as dc
import io

import numpy as np

from .baselines import ensemble_variance
from .detector_train import detector_scores
from .metrics import accuracy_at_recall, best_threshold, binary_metrics
from .labels import labels_name

COLUMNS = ("environment", "method", "labels", "states", "n", "positives", "tp", "fp", "fn", "tn",
           "recall", "accuracy", "precision", "f1", "auroc", "threshold",
           "accuracy_at_target_recall")
#: Columns that are rates, shown in %.
RATES = ("recall", "accuracy", "precision", "f1", "auroc", "accuracy_at_target_recall")
COUNTS = ("n", "positives", "tp", "fp", "fn", "tn")

#: The ``states`` subset of the samples that have not failed yet (inside the safe set).
NOT_FAILED = "not yet failed"
#: The subset of a dataset with read-along states that is its uniform states (the rest are
#: states the real runs passed through).
UNIFORM_STARTS = "uniform states"
#: The subset that is the states real runs passed through (`SOURCE_PATH`), with the
#: runs' own labels: the states the loop visits, which an online monitor scores.
READ_ALONG = "read along runs"


@dc.dataclass
class Detector:
    """A trained detector to evaluate: model, `DetectorConfig`, decision threshold."""
    name: str
    model: object
    config: object
    threshold: float = 0.5


def evaluate_environment(data, detectors, *, device="", subsets=None,
                         target_recall=0.95, estimate_error=None) -> tuple:
    """``(rows, scores)`` for one `LabelledData`: rows (dicts with `COLUMNS`) for each
    detector at its own threshold, then the baselines at the threshold maximising F1 on
    the same states (oracle-tuned, i.e. as generous to them as possible); ``scores``
    {method: score per sample}. ``subsets`` {name: boolean mask over the samples} adds
    the same rows over each subset (the baselines tuned again on it); ``"all"`` is
    always first. An empty subset gives no rows.

    Every row also has ``accuracy_at_target_recall``: the accuracy at the highest
    threshold reaching ``target_recall`` on these very samples, chosen with their labels
    (an oracle; NaN without positives). It is what the method's ranking allows at that
    recall, so a detector's accuracy far below it was lost by its threshold, not by
    its scores. ``estimate_error`` (a `baselines.EstimateError`; None: none) gives the
    prediction-error baseline, when the dataset's estimates are the ones it reads, and
    the units of the ensemble's variance."""
    env, labels, rows = data.manifest["environment"], data.labels, []
    label_info = data.manifest.get("labels", {})
    source = labels_name(label_info.get("source", "brt"), label_info.get("paths"))
    n = len(labels)
    masks = {"all": np.ones(n, bool)}
    for name, mask in (subsets or {}).items():
        mask = np.asarray(mask)
        if mask.dtype != bool or mask.shape != (n,):
            raise ValueError(f"subset '{name}' must be a boolean mask of the {n} samples, got "
                             f"dtype {mask.dtype} shape {mask.shape}")
        masks[name] = mask
    scores = {det.name: detector_scores(det.model, det.config, data.images, device=device)
              for det in detectors}
    thresholds = {det.name: det.threshold for det in detectors}
    baselines = []
    if estimate_error is not None and estimate_error.applies(data.states, data.estimates):
        baselines.append(f"{estimate_error.controller} prediction error (best threshold)")
        scores[baselines[-1]] = estimate_error(data.states, data.estimates)
    if data.ensemble.shape[1] >= 2:
        baselines.append(f"ensemble of {data.ensemble.shape[1]} variance (best threshold)")
        scores[baselines[-1]] = ensemble_variance(
            data.ensemble, estimate_error.scale if estimate_error is not None else ())
    for subset, mask in masks.items():
        if not mask.any():
            continue
        head = {"environment": env, "labels": source, "states": subset}
        for det in detectors:
            s = scores[det.name][mask]
            rows.append({**head, "method": det.name, "threshold": thresholds[det.name],
                         **binary_metrics(labels[mask], s >= thresholds[det.name], s).row(),
                         "accuracy_at_target_recall": accuracy_at_recall(labels[mask], s,
                                                                         target_recall)})
        for name in baselines:
            s = scores[name][mask]
            threshold, metrics = best_threshold(labels[mask], s)
            rows.append({**head, "method": name, "threshold": float(threshold), **metrics.row(),
                         "accuracy_at_target_recall": accuracy_at_recall(labels[mask], s,
                                                                         target_recall)})
    return rows, scores


def target_summary(rows, groups=None, *, recall=0.95, accuracy=0.95) -> list:
    """Table 2 against a target, one dict per group of environments, label source and
    ``states`` subset, for the first method of ``rows`` (the detector): how many
    environments; min and median (NaN-aware) of its recall, accuracy, AUROC,
    ``accuracy_at_target_recall`` and share of images flagged; how many environments
    reach ``recall``, how many reach both ``recall`` and ``accuracy`` (an environment
    without anomalies, whose recall is NaN, reaches neither), and in how many its AUROC
    is above every other method's (None when no other method has one); and
    the environment with the lowest accuracy. The minimum is the figure a target is
    about, so it comes first. ``groups`` {name: environment names} (default: one group
    "all" of every environment in ``rows``); a name with no rows is left out."""
    if not rows:
        return []
    method = rows[0]["method"]
    if groups is None:
        groups = {"all": list(dict.fromkeys(r["environment"] for r in rows))}
    keys = list(dict.fromkeys((r["labels"], r["states"]) for r in rows if r["method"] == method))
    out = []
    for group, names in groups.items():
        names = set(names)
        for labels, states in keys:
            same = [r for r in rows if r["environment"] in names and r["labels"] == labels
                    and r["states"] == states]
            mine = [r for r in same if r["method"] == method]
            if not mine:
                continue
            figures = {k: np.array([np.nan if r.get(k) is None else r[k] for r in mine], float)
                       for k in ("recall", "accuracy", "auroc", "accuracy_at_target_recall")}
            figures["flagged"] = np.array([(r["tp"] + r["fp"]) / r["n"] if r["n"] else np.nan
                                           for r in mine])
            beats, compared = 0, 0
            for r in mine:
                others = [o["auroc"] for o in same if o["environment"] == r["environment"]
                          and o["method"] != method and o.get("auroc") is not None
                          and np.isfinite(o["auroc"])]
                if others:
                    compared += 1
                    beats += int(r["auroc"] is not None and r["auroc"] > max(others))
            meet_recall = figures["recall"] >= recall
            worst = int(np.nanargmin(figures["accuracy"])) if np.isfinite(
                figures["accuracy"]).any() else 0
            out.append({"group": group, "method": method, "labels": labels, "states": states,
                        "environments": len(mine),
                        **{k: (_nan_stat(np.nanmin, v), _nan_stat(np.nanmedian, v))
                           for k, v in figures.items()},
                        "meet_recall": int(meet_recall.sum()),
                        "meet_both": int((meet_recall & (figures["accuracy"] >= accuracy)).sum()),
                        "beats_baselines": beats if compared else None,
                        "worst": mine[worst]["environment"]})
    return out


def _nan_stat(fn, values):
    """``fn`` over the finite ``values``; NaN when there are none (without a warning)."""
    finite = values[np.isfinite(values)]
    return float(fn(finite)) if len(finite) else float("nan")


def worst_mistakes(labels, scores, threshold, k: int):
    """``(misses, false_alarms)``: indices of up to ``k`` anomalous samples left unflagged,
    lowest score first, and of up to ``k`` safe samples flagged, highest score first (the
    detector's most confident mistakes; ties keep sample order)."""
    labels = np.asarray(labels).astype(bool)
    scores = np.asarray(scores, dtype=float)
    flagged = scores >= threshold
    misses = np.flatnonzero(labels & ~flagged)
    alarms = np.flatnonzero(~labels & flagged)
    misses = misses[np.argsort(scores[misses], kind="stable")][:k]
    alarms = alarms[np.argsort(-scores[alarms], kind="stable")][:k]
    return misses, alarms


def format_cell(value, key) -> str:
    """One Table-2 cell as text: rates in %, counts as integers, missing as -."""
    if isinstance(value, str):
        return value
    if key in COUNTS:
        return str(int(value))
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "-"
    return f"{100 * value:.1f}" if key in RATES else f"{value:.3g}"


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
