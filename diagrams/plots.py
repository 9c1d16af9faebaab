"""Figures of runs on the runway (matplotlib, headless)."""

import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from reachwatch.systems.files import atomic_write_bytes  # noqa: E402


def save_figure(fig, path):
    """Save ``fig`` atomically (format from the suffix) and close it."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format=str(path).rsplit(".", 1)[-1], dpi=120, bbox_inches="tight")
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue())


def plot_runs_over_time(runs, *, axes, path, title="", units=()):
    """Any plant's runs against time, one panel per state axis (``axes``: their names,
    ``units`` theirs where given) and, where a run logged them, its speed and its
    flagged ticks; a line per run in one colour per run (``runs``: ``[(Trajectory,
    label)]``), a failed run's last tick crossed."""
    units = list(units) + [""] * len(axes)
    panels = [(axis, j, units[j]) for j, axis in enumerate(axes)]       # state components
    panels += [(name, None, unit) for name, unit in (("speed", "m/s"), ("anomaly", ""))
               if any(getattr(t, name) is not None for t, _ in runs)]   # logged ones
    fig, grid = plt.subplots(len(panels), 1, figsize=(8, 1.7 * len(panels) + 0.6),
                             sharex=True, squeeze=False)
    for ax, (name, j, unit) in zip(grid[:, 0], panels):
        for i, (trajectory, label) in enumerate(runs):
            values = trajectory.state[:, j] if j is not None else getattr(trajectory, name)
            if values is None:
                continue
            values = np.asarray(values, float).reshape(len(trajectory.time), -1)[:, 0]
            ax.plot(trajectory.time, values, lw=1.8, label=label, color=f"C{i}",
                    drawstyle="default" if j is not None or name == "speed" else "steps-post")
            if trajectory.failed and j is not None:
                ax.plot(trajectory.time[-1], values[-1], "x", color="tab:red", ms=9, mew=2)
        text = "flagged" if j is None and name == "anomaly" else name
        ax.set_ylabel(f"{text} ({unit})" if unit else text)
    grid[-1, 0].set_xlabel("time (s)")
    grid[0, 0].legend(loc="upper right", fontsize=8)
    if title:
        grid[0, 0].set_title(title, fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_runway_top_view(trajectories, *, half_width: float, path, title=""):
    """Top view of ``trajectories`` (`Trajectory`, label) on the runway: downtrack
    py along x, crosstrack px up (left of the centreline), edges at +-B, the failure
    region shaded, failures marked with a cross."""
    fig, ax = plt.subplots(figsize=(9, 3.6))
    ys = np.concatenate([t.state[:, 1] for t, _ in trajectories])
    lo, hi = ys.min() - 5, ys.max() + 5
    for sign in (-1, 1):
        ax.axhline(sign * half_width, color="k", lw=1.5)
        ax.axhspan(sign * half_width, sign * (half_width + 3), color="tab:red", alpha=0.12)
    ax.axhline(0.0, color="0.6", lw=1, ls=(0, (8, 6)))
    for trajectory, label in trajectories:
        px, py = trajectory.state[:, 0], trajectory.state[:, 1]
        ax.plot(py, px, lw=2, label=label)
        if trajectory.failed:
            ax.plot(py[-1], px[-1], "x", color="tab:red", ms=10, mew=2)
    ax.set_xlim(lo, hi)
    ax.set_ylim(-(half_width + 3), half_width + 3)
    ax.set_xlabel("downtrack py (m)")
    ax.set_ylabel("crosstrack px (m, left +)")
    ax.set_title(title or f"runway top view, B = {half_width:g} m")
    ax.legend(loc="upper right", fontsize=8)
    return save_figure(fig, path)


def plot_guarded_run(nominal, guarded, *, half_width: float, path, title=""):
    """The paper's Fig. 6: the nominal run dashed, the guarded run coloured by speed
    (m/s), flagged ticks ringed, runway edges drawn."""
    fig, ax = plt.subplots(figsize=(9, 3.8))
    for sign in (-1, 1):
        ax.axhline(sign * half_width, color="k", lw=1.5)
        ax.axhspan(sign * half_width, sign * (half_width + 3), color="tab:red", alpha=0.12)
    ax.plot(nominal.state[:, 1], nominal.state[:, 0], "k--", lw=1.5,
            label="alone" + (" (fails)" if nominal.failed else ""))
    points = ax.scatter(guarded.state[:, 1], guarded.state[:, 0], c=guarded.speed, s=10,
                        cmap="viridis", vmin=0.0, vmax=max(5.0, float(np.max(guarded.speed))),
                        label="guarded" + (" (fails)" if guarded.failed else ""))
    flagged = np.asarray(guarded.anomaly) >= 0.5
    ax.plot(guarded.state[flagged, 1], guarded.state[flagged, 0], "o", mfc="none",
            mec="tab:red", ms=6, mew=0.6, label="flagged by the detector")
    fig.colorbar(points, ax=ax, label="speed (m/s)")
    ys = np.concatenate([nominal.state[:, 1], guarded.state[:, 1]])
    ax.set_xlim(ys.min() - 5, ys.max() + 5)
    ax.set_ylim(-(half_width + 3), half_width + 3)
    ax.set_xlabel("downtrack py (m)")
    ax.set_ylabel("crosstrack px (m, left +)")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="best", fontsize=7)
    return save_figure(fig, path)
