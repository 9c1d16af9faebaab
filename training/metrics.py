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
        return {"n": self.n, "positives": self.tp + self.fn, "tp": self.tp, "fp": self.fp,
                "fn": self.fn, "tn": self.tn, "recall": self.recall,
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


def roc_points(labels, scores):
    """The ROC curve ``(false_positive_rate, true_positive_rate, thresholds)``: one point
    per distinct score, flagging ``score >= threshold``, from flagging nothing
    (threshold +inf) to flagging everything. NaN rates where a class is absent."""
    labels = np.asarray(labels).astype(bool)
    scores = np.asarray(scores, dtype=float)
    order = np.argsort(-scores, kind="stable")
    s, y = scores[order], labels[order]
    last = np.r_[np.flatnonzero(np.diff(s)), len(s) - 1]      # last sample of each score
    tp, fp = np.cumsum(y)[last], np.cumsum(~y)[last]
    n_pos, n_neg = labels.sum(), (~labels).sum()
    with np.errstate(invalid="ignore", divide="ignore"):
        tpr = np.r_[0, tp] / n_pos if n_pos else np.full(len(last) + 1, np.nan)
        fpr = np.r_[0, fp] / n_neg if n_neg else np.full(len(last) + 1, np.nan)
    return fpr, tpr, np.r_[np.inf, s[last]]


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


def recall_threshold(labels, scores, target_recall: float):
    """The highest threshold ``t`` (flag where ``score >= t``) whose recall on these
    samples is at least ``target_recall``: one of the positives' scores. None when there
    are no positives (any threshold has undefined recall)."""
    labels = np.asarray(labels).astype(bool)
    scores = np.asarray(scores, dtype=float)
    if labels.shape != scores.shape:
        raise ValueError(f"labels {labels.shape} and scores {scores.shape} differ")
    if not 0.0 < target_recall <= 1.0:
        raise ValueError(f"target_recall must be in (0, 1], got {target_recall}")
    positives = np.sort(scores[labels])
    if len(positives) == 0:
        return None
    # Flagging the top n - k positives leaves k misses; the most k may be is
    # floor((1 - target) n). Ties at the threshold are flagged too, which only helps.
    k = int(np.floor((1.0 - target_recall) * len(positives) + 1e-9))
    return float(positives[k])


def accuracy_at_recall(labels, scores, target_recall: float) -> float:
    """The accuracy at `recall_threshold` on these very samples (an oracle: what the
    ranking allows at that recall); nan when there are no positives."""
    t = recall_threshold(labels, scores, target_recall)
    return float("nan") if t is None else binary_metrics(labels, np.asarray(scores) >= t).accuracy


@dc.dataclass
class HeldOutThreshold:
    """A threshold chosen on held-out scores (`held_out_threshold`). ``per_group``:
    for each held-out group, the highest threshold reaching the target on it alone,
    its recall and accuracy at the chosen ``threshold``, its sample and positive
    counts. ``promised``: recall (lowest over the groups and pooled) and pooled
    accuracy at ``threshold`` on the held-out scores: what the threshold promises for
    an environment it has not seen."""
    threshold: float
    rule: str
    target_recall: float
    per_group: dict
    promised: dict


HELD_OUT_RULES = ("every_group", "pooled")


def held_out_threshold(groups, target_recall: float, *, rule: str = "every_group",
                       ) -> HeldOutThreshold:
    """The operating threshold from scores of samples their model never trained on.

    ``groups`` maps a group name (e.g. one left-out environment) to ``(labels,
    scores)``, the scores coming from a model trained without that group. ``rule``:
    ``every_group`` takes the lowest of the groups' own thresholds, so that the
    target recall holds on each left-out group (the target says "every environment");
    ``pooled`` reaches it on all held-out samples together. Groups without positives
    constrain nothing under ``every_group``."""
    if rule not in HELD_OUT_RULES:
        raise ValueError(f"rule must be one of {HELD_OUT_RULES}, got '{rule}'")
    if not groups:
        raise ValueError("held_out_threshold needs at least one group")
    own = {name: recall_threshold(y, s, target_recall) for name, (y, s) in groups.items()}
    if all(t is None for t in own.values()):
        raise ValueError(f"no held-out group has a positive sample ({sorted(groups)}): "
                         f"no threshold reaches a recall")
    all_labels = np.concatenate([np.asarray(y) for y, _ in groups.values()])
    all_scores = np.concatenate([np.asarray(s, dtype=float) for _, s in groups.values()])
    if rule == "every_group":
        threshold = min(t for t in own.values() if t is not None)
    else:
        threshold = recall_threshold(all_labels, all_scores, target_recall)
    per_group = {}
    for name, (y, s) in groups.items():
        m = binary_metrics(y, np.asarray(s, dtype=float) >= threshold)
        per_group[name] = {"own_threshold": own[name], "recall": m.recall,
                           "accuracy": m.accuracy, "n": m.n, "positives": m.tp + m.fn}
    pooled = binary_metrics(all_labels, all_scores >= threshold)
    recalls = [g["recall"] for g in per_group.values() if g["positives"]]
    promised = {"min_recall": float(min(recalls)), "pooled_recall": pooled.recall,
                "pooled_accuracy": pooled.accuracy, "flagged": (pooled.tp + pooled.fp) / pooled.n}
    return HeldOutThreshold(float(threshold), rule, float(target_recall), per_group, promised)
