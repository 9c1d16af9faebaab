"""BRT slice figures: theta (deg) against px (m) at one downtrack position, as in
the paper's figures (grey = BRT)."""

import matplotlib.pyplot as plt
import numpy as np

from reachwatch.diagrams.plots import save_figure
from reachwatch.reach import ValueFunction


def slice_index(grid, py: float) -> int:
    """Nearest grid index along py to ``py`` (m)."""
    return int(np.argmin(np.abs(grid.axes[1] - py)))


def plot_brt_slices(value_functions, *, py: float, path, half_width=None, title="",
                    points=None):
    """One panel per (label, `ValueFunction`): BRT grey, boundary black, runway edges
    dashed; ``points`` = optional list of (label, states (N, 3), style) overlays."""
    items = list(value_functions.items()) if isinstance(value_functions, dict) else value_functions
    fig, axes = plt.subplots(1, len(items), figsize=(4.2 * len(items), 3.8), squeeze=False)
    for ax, (label, vf) in zip(axes[0], items):
        j = slice_index(vf.grid, py)
        px, theta = vf.grid.axes[0], np.rad2deg(vf.grid.axes[2])
        v = vf.values[:, j, :].T                                    # (theta, px)
        ax.contourf(px, theta, v, levels=[v.min() - 1, 0.0], colors=["0.7"])
        ax.contour(px, theta, v, levels=[0.0], colors="k", linewidths=1.2)
        if half_width is not None:
            for s in (-1, 1):
                ax.axvline(s * half_width, color="tab:red", ls="--", lw=1)
        for name, states, style in points or []:
            states = np.asarray(states)
            states = states.reshape(-1, 3)
            near = np.abs(states[:, 1] - vf.grid.axes[1][j]) <= max(0.5 * vf.grid.spacing[1], 10.0)
            ax.plot(states[near, 0], np.rad2deg(states[near, 2]), style, ms=3, label=name)
        ax.set_title(f"{label}: py = {vf.grid.axes[1][j]:.0f} m, BRT {100 * vf.brt_fraction:.1f}%",
                     fontsize=9)
        if points:
            ax.legend(fontsize=6, loc="lower right")
        ax.set_xlabel("px (m)")
        ax.set_ylabel("theta (deg)")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_failure_sets(failures, grid, horizon, *, py, path, half_width, title):
    """One BRT-style slice panel per failure set (failing starts grey)."""
    sets = {k: ValueFunction(grid, np.where(v.reshape(grid.shape), -1.0, 1.0), horizon,
                             "rollouts") for k, v in failures.items()}
    return plot_brt_slices(sets, py=py, path=path, half_width=half_width, title=title)


def plot_tradeoff(curves, *, operating=None, alone=None, path, title="", noisy_curves=None,
                  noisy_operating=None):
    """Failure set against % of starts ended stopped (left) and against the distance
    travelled relative to the controller alone (right), one curve per fallback as the
    detector threshold sweeps (`taxi.guarded.tradeoff_curves`); ``operating``:
    {fallback: the row at the run's threshold}, marked with a star; ``alone``: the
    controller alone's failure set, a dashed line. Rows judged by distance too are
    plotted by their same-distance failure set (a slower aircraft on the same path only
    fails later), which for the controller alone is its failure set. ``noisy_curves``:
    the same curves rolled out with the detector's variation between nodes
    (``score_noise`` of `tradeoff_curves`), dashed in the same colour, and
    ``noisy_operating`` their rows at the run's threshold, hollow stars."""
    noisy_curves, noisy_operating = noisy_curves or {}, noisy_operating or {}
    rows_all = ([r for rows in curves.values() for r in rows]
                + [r for rows in noisy_curves.values() for r in rows]
                + list((operating or {}).values()) + list(noisy_operating.values()))
    by_distance = bool(rows_all) and all("same_distance_failure_set" in r for r in rows_all)
    key = "same_distance_failure_set" if by_distance else "failure_set"
    fig, axes = plt.subplots(1, 2, figsize=(9.0, 3.8))
    for k, (name, rows) in enumerate(curves.items()):
        color = f"C{k}"
        fail = [100 * r[key] for r in rows]
        stopped = [100 * r["ended_stopped"] for r in rows]
        distance = [r["distance_ratio"] for r in rows]
        axes[0].plot(stopped, fail, "o-", color=color, ms=3, label=name)
        axes[1].plot(distance, fail, "o-", color=color, ms=3, label=name)
        if name in noisy_curves:
            noisy = noisy_curves[name]
            fail_n = [100 * r[key] for r in noisy]
            axes[0].plot([100 * r["ended_stopped"] for r in noisy], fail_n, "s--", color=color,
                         ms=3, lw=1, label=f"{name}, + score noise")
            axes[1].plot([r["distance_ratio"] for r in noisy], fail_n, "s--", color=color,
                         ms=3, lw=1)
        if name in noisy_operating:
            op = noisy_operating[name]
            axes[0].plot(100 * op["ended_stopped"], 100 * op[key], "*", mfc="white", mec=color,
                         ms=12, mew=1.5)
            axes[1].plot(op["distance_ratio"], 100 * op[key], "*", mfc="white", mec=color,
                         ms=12, mew=1.5)
        if operating and name in operating:
            op = operating[name]
            axes[0].plot(100 * op["ended_stopped"], 100 * op[key], "*", color=color,
                         ms=12, mec="k")
            axes[1].plot(op["distance_ratio"], 100 * op[key], "*", color=color,
                         ms=12, mec="k")
    for ax in axes:
        if alone is not None:
            ax.axhline(100 * alone, color="k", ls="--", lw=1, label="controller alone")
        ax.set_ylabel("fails at the same distance (% of starts)" if by_distance
                      else "failure set (% of starts)")
        ax.grid(alpha=0.3)
    axes[0].set_xlabel("starts ended stopped (%)")
    axes[1].set_xlabel("distance travelled / controller alone")
    axes[0].legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)
