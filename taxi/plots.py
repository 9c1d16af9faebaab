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

