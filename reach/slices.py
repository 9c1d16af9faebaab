"""The default state-slice figure of an application that draws none of its own
(`Application.plot_slices`): the value functions over the grid's first two axes, the
others at their nodes nearest the box's centre."""

import numpy as np

from reachwatch.diagrams.plots import save_figure


def plot_value_slices(value_functions, *, path, title="", points=None):
    """One panel per (label, `ValueFunction`): its BRT (``values <= 0``) grey over the
    grid's axes 0 and 1, every other axis at its node nearest the box's centre (named
    in the panel's title); a grid of one axis is drawn along it. ``points``: (label,
    states ``(n, ndim)``, matplotlib style) drawn where their other axes lie within a
    node's spacing of the slice. Returns ``path``."""
    import matplotlib.pyplot as plt
    items = list(value_functions.items())
    fig, axes = plt.subplots(1, len(items), figsize=(4.0 * len(items), 3.6), squeeze=False)
    for ax, (label, vf) in zip(axes[0], items):
        grid = vf.grid
        names = list(getattr(grid, "names", None) or [f"x{k}" for k in range(grid.ndim)])
        values = np.asarray(vf.values).reshape(grid.shape)
        at = [int(np.argmin(np.abs(a - (a[0] + a[-1]) / 2))) for a in grid.axes]
        rest = range(2, grid.ndim)
        cut = values[(slice(None),) * min(grid.ndim, 2) + tuple(at[k] for k in rest)]
        if grid.ndim == 1:
            ax.plot(grid.axes[0], cut, "k-", lw=1)
            ax.axhline(0.0, color="0.5", lw=0.8)
            ax.set_ylabel("value")
        else:
            if cut.min() <= 0:
                ax.contourf(grid.axes[0], grid.axes[1], cut.T, levels=[cut.min() - 1, 0.0],
                            colors=["0.7"])
            ax.set_xlim(grid.lo[0], grid.hi[0])
            ax.set_ylim(grid.lo[1], grid.hi[1])
            ax.set_ylabel(names[1])
        for name, states, style in points or []:
            states = np.asarray(states, float).reshape(-1, grid.ndim)
            near = np.ones(len(states), bool)
            for k in rest:
                near &= np.abs(states[:, k] - grid.axes[k][at[k]]) <= grid.spacing[k]
            y = states[near, 1] if grid.ndim > 1 else np.zeros(int(near.sum()))
            ax.plot(states[near, 0], y, style, ms=3, label=name)
        if points:
            ax.legend(fontsize=6, loc="lower right")
        where = ", ".join(f"{names[k]} = {grid.axes[k][at[k]]:.3g}" for k in rest)
        ax.set_title(f"{label}" + (f": {where}" if where else ""), fontsize=9)
        ax.set_xlabel(names[0])
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)
