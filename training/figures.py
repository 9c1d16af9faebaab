"""Evaluation figures: error rate against the distance to the BRT boundary, and
flagged/misclassified states over a BRT slice."""

import matplotlib.pyplot as plt
import numpy as np

from reachwatch.diagrams.plots import save_figure
from reachwatch.taxi.plots import plot_brt_slices


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


def plot_overlay(value_function, states, labels, predictions, *, py, path, title="",
                 half_width=None):
    """States near the ``py`` slice over the BRT: flagged vs not, misclassified marked."""
    labels, predictions = np.asarray(labels).astype(bool), np.asarray(predictions).astype(bool)
    points = [("flagged", states[predictions & (labels == predictions)], "r."),
              ("not flagged", states[~predictions & (labels == predictions)], "b."),
              ("missed (false negative)", states[labels & ~predictions], "kx"),
              ("false alarm", states[~labels & predictions], "m+")]
    return plot_brt_slices({title or "BRT": value_function}, py=py, path=path, points=points,
                           half_width=half_width)
