"""Evaluation figures: error rate against the distance to the BRT boundary,
flagged/misclassified states over a state slice (drawn by the application), ROC curves,
and example images."""

import matplotlib.pyplot as plt
import numpy as np

from reachwatch.diagrams.plots import save_figure

from .metrics import auroc, roc_points


def plot_error_vs_margin(results, path, bins=(0, 0.25, 0.5, 1, 2, 4, 8, 100)):
    """``results``: {method: (values, labels, predictions)}. Error rate per bin of
    |V| (m): mistakes concentrate near the BRT boundary."""
    fig, ax = plt.subplots(figsize=(6, 3.6))
    edges = np.asarray(bins, float)
    centres = np.arange(len(edges) - 1)
    for name, (values, labels, predictions) in results.items():
        margin = np.abs(values)
        wrong = np.asarray(labels).astype(bool) != np.asarray(predictions).astype(bool)
        rates = [wrong[(margin >= a) & (margin < b)].mean() if np.any((margin >= a) & (margin < b))
                 else np.nan for a, b in zip(edges[:-1], edges[1:])]
        ax.plot(centres, 100 * np.asarray(rates), "o-", label=name)
    ax.set_xticks(centres, [f"{a:g}-{b:g}" for a, b in zip(edges[:-1], edges[1:])], fontsize=8)
    ax.set_xlabel("|V(x)|: distance to the BRT boundary (m)")
    ax.set_ylabel("error rate (%)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def plot_overlay(application, scenario, value_function, states, labels, predictions, *, at,
                 path, title=""):
    """States near the application's state slice through ``at`` over the BRT (its
    ``plot_slices``): flagged vs not, misclassified marked."""
    labels, predictions = np.asarray(labels).astype(bool), np.asarray(predictions).astype(bool)
    points = [("flagged", states[predictions & (labels == predictions)], "r."),
              ("not flagged", states[~predictions & (labels == predictions)], "b."),
              ("missed (false negative)", states[labels & ~predictions], "kx"),
              ("false alarm", states[~labels & predictions], "m+")]
    return application.plot_slices({title or "BRT": value_function}, scenario=scenario, at=at,
                                    path=path, points=points)


def plot_roc(curves, path, title=""):
    """``curves``: {method: (labels, scores, threshold)}: each method's ROC curve with its
    operating point (``score >= threshold``) marked; AUROC in the legend."""
    fig, ax = plt.subplots(figsize=(4.6, 4.2))
    for name, (labels, scores, threshold) in curves.items():
        fpr, tpr, _ = roc_points(labels, scores)
        line, = ax.plot(100 * fpr, 100 * tpr, lw=1.3,
                        label=f"{name} (AUROC {100 * auroc(labels, scores):.1f})")
        flagged = np.asarray(scores) >= threshold
        labels = np.asarray(labels).astype(bool)
        ax.plot(100 * flagged[~labels].mean(), 100 * flagged[labels].mean(), "o",
                color=line.get_color())
    ax.plot([0, 100], [0, 100], ":", color="grey", lw=0.8)
    ax.set_xlabel("false alarms: % of safe states flagged")
    ax.set_ylabel("recall: % of anomalous states flagged")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=6, loc="lower right")
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def plot_reliability(curves, path, title=""):
    """A reliability diagram: ``curves`` {name: (mean predicted, observed frequency,
    count)} per probability bin (`reachwatch.training.conformal.reliability_curve`),
    each with its expected calibration error in the legend; the diagonal is perfect."""
    fig, ax = plt.subplots(figsize=(4.6, 4.2))
    for name, (mean_p, freq, counts) in curves.items():
        mean_p, freq, counts = map(np.asarray, (mean_p, freq, counts))
        ece = float(np.sum(counts * np.abs(mean_p - freq)) / max(1, counts.sum()))
        ax.plot(mean_p, freq, "o-", ms=3, lw=1.2, label=f"{name} (ECE {ece:.3f})")
    ax.plot([0, 1], [0, 1], ":", color="grey", lw=0.8)
    ax.set_xlabel("predicted risk")
    ax.set_ylabel("observed frequency of failure within the horizon")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=6, loc="upper left")
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def plot_examples(images, captions, path, *, columns=4, title=""):
    """Images in a grid, each with its caption (e.g. misses and false alarms)."""
    rows = max(1, -(-len(images) // columns))
    fig, axes = plt.subplots(rows, columns, figsize=(3.0 * columns, 2.3 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, image, caption in zip(axes.ravel(), images, captions):
        ax.imshow(image)
        ax.set_title(caption, fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    return save_figure(fig, path)
