"""Binary-classification metrics against BRT labels (1 = anomalous)."""

import dataclasses as dc

import numpy as np
from scipy.stats import rankdata


@dc.dataclass
class Metrics:
    """Counts and rates in [0, 1]; NaN where undefined (e.g. recall with no positives)."""
    tp: int
    fp: int
    tn: int
    fn: int
    auroc: float = float("nan")

    @property
    def n(self):
        return self.tp + self.fp + self.tn + self.fn

    @property
    def accuracy(self):
        return (self.tp + self.tn) / self.n if self.n else float("nan")

    @property
    def recall(self):
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else float("nan")

    @property
    def precision(self):
        return self.tp / (self.tp + self.fp) if self.tp + self.fp else float("nan")

    @property
    def f1(self):
        p, r = self.precision, self.recall
        if np.isnan(p) or np.isnan(r) or p + r == 0:
            return float("nan") if np.isnan(p) or np.isnan(r) else 0.0
        return 2 * p * r / (p + r)

    def row(self) -> dict:
        return {"n": self.n, "positives": self.tp + self.fn, "recall": self.recall,
                "accuracy": self.accuracy, "precision": self.precision, "f1": self.f1,
                "auroc": self.auroc}


def auroc(labels, scores) -> float:
    """Area under the ROC curve (Mann-Whitney, ties averaged); NaN with one class."""
    labels = np.asarray(labels).astype(bool)
    n_pos, n_neg = labels.sum(), (~labels).sum()
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = rankdata(np.asarray(scores, dtype=float))
    return float((ranks[labels].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def binary_metrics(labels, predictions, scores=None) -> Metrics:
    labels = np.asarray(labels).astype(bool)
    predictions = np.asarray(predictions).astype(bool)
    if labels.shape != predictions.shape:
        raise ValueError(f"labels {labels.shape} and predictions {predictions.shape} differ")
    return Metrics(tp=int(np.sum(labels & predictions)), fp=int(np.sum(~labels & predictions)),
                   tn=int(np.sum(~labels & ~predictions)), fn=int(np.sum(labels & ~predictions)),
                   auroc=auroc(labels, scores) if scores is not None else float("nan"))


def best_threshold(labels, scores, *, objective="f1"):
    """The threshold on ``scores`` (flag where ``score >= t``) maximising ``objective``
    (``f1`` or ``accuracy``); returns ``(threshold, Metrics)``."""
    scores = np.asarray(scores, dtype=float)
    candidates = np.unique(np.quantile(scores, np.linspace(0, 1, 201)))
    best = None
    for t in candidates:
        m = binary_metrics(labels, scores >= t, scores)
        value = getattr(m, objective)
        if best is None or (not np.isnan(value) and value > best[0]):
            best = (value, t, m)
    return best[1], best[2]
