"""The guard's figures from a guarded loop's table rollouts, whatever the plant: the
trade-off of failures against liveness as the detector threshold sweeps, the threshold
a flag budget sets without labels, a perfect detector's scores and the trade-off figure.

Each takes ``rollouts``, a function ``rollouts(fallbacks, *, threshold=None,
alone=None, **settings) -> {UNGUARDED | fallback: MissionOutcomes}`` (an application's
``fallback_rollouts`` with its scenario, grid, tables and horizon bound: see
`reachwatch.reach.application.Application.tradeoff_curves`)."""

import numpy as np

from .liveness import UNGUARDED, liveness_figures, threshold_for_flag_budget
from .score_noise import sigmoid


def tradeoff_row(figures: dict, threshold=None) -> dict:
    """One point of a trade-off curve from `liveness_figures`."""
    return {"threshold": threshold, "failure_set": figures["failure_set"]["rate"],
            "ended_stopped": figures["ended_stopped"]["rate"],
            "needless_stops": figures["needless_stops"]["rate"],
            "distance_ratio": figures["distance_ratio"], "flagged_ticks": figures["flagged_ticks"],
            **{name: figures[name]["rate"] for name in ("same_distance_failure_set",
                                                        "short_of_distance") if name in figures}}


def tradeoff_curves(rollouts, scores, fallbacks, points: int, *, alone=None,
                    **settings) -> dict:
    """{fallback: rows} of the failure set against liveness as the detector threshold
    sweeps the range of ``scores`` (the swept scores: ``points`` thresholds at evenly
    spaced quantiles, from flagging every node to flagging almost none), each row
    `tradeoff_row` over the rolled-out starts (with a mission limit among
    ``settings``, also the same-distance figures). ``alone``: the controller alone's
    outcomes when already computed, reused (they do not depend on the threshold).
    ``settings`` go to every ``rollouts`` call (e.g. the score noise and its seed: the
    same draw at every threshold). The quantiles are of the finite scores: a node whose
    score is NaN flags at every threshold (`flags_at`), and made every quantile NaN, the
    curve one row at threshold NaN; with none finite there is no curve."""
    scores = np.asarray(scores, float).ravel()
    finite = scores[np.isfinite(scores)]
    thresholds = (np.unique(np.quantile(finite, np.linspace(0.0, 1.0, max(points, 2))))
                  if finite.size else np.zeros(0))
    curves = {name: [] for name in fallbacks}
    for threshold in thresholds:
        runs = rollouts(fallbacks, threshold=float(threshold), alone=alone, **settings)
        alone = runs[UNGUARDED]          # the same for every threshold
        for name in fallbacks:
            curves[name].append(tradeoff_row(liveness_figures(runs[UNGUARDED], runs[name]),
                                             float(threshold)))
    return curves


#: The flag budget searches the detector's logit, not its score: over +-16 (scores from
#: 1e-7 to 1 - 1e-7), bisected to 0.005 (a score step of at most 0.00125). A detector
#: sure of itself on an environment puts the budget's threshold near 1, e.g. 0.988,
#: where a search on the score to 1e-3 would step the logit by 0.08 at a time.
FLAG_BUDGET_LOGIT_RANGE = 16.0
FLAG_BUDGET_LOGIT_TOLERANCE = 0.005


def flag_budget_threshold(rollouts, fallback: str, budget: float, *, starts, alone=None,
                          **settings) -> dict:
    """The threshold at which ``fallback``'s guarded loop, rolled out from ``starts``
    (``settings``, e.g. the detector's variation between nodes, go to every
    ``rollouts`` call), flags ``budget`` of its control ticks
    (`reach.liveness.threshold_for_flag_budget`): no labels needed, only the detector's
    scores in the environment, a probability in [0, 1], searched on its logit
    (``FLAG_BUDGET_LOGIT_RANGE``). Returns ``{threshold, flagged_ticks, budget, fallback,
    starts, steps}``; ``alone`` as in `tradeoff_curves`."""
    shares = {}

    def share(logit):
        nonlocal alone
        if logit not in shares:
            runs = rollouts([fallback], threshold=float(sigmoid(logit)), starts=starts,
                            alone=alone, **settings)
            alone = runs[UNGUARDED]      # the same at every threshold: rolled out once
            shares[logit] = liveness_figures(alone, runs[fallback])["flagged_ticks"]
        return shares[logit]

    top = share(FLAG_BUDGET_LOGIT_RANGE)
    if top is not None and top > budget:
        raise ValueError(
            f"even at threshold {float(sigmoid(FLAG_BUDGET_LOGIT_RANGE)):.7f} the {fallback} "
            f"loop flags {100 * top:.1f} % of its ticks, over the flag budget of "
            f"{100 * budget:g} %: the detector's score is 1 (or within 1e-7 of it) on that "
            f"share of the ticks")
    logit, flagged, steps = threshold_for_flag_budget(
        share, budget, low=-FLAG_BUDGET_LOGIT_RANGE, high=FLAG_BUDGET_LOGIT_RANGE,
        tolerance=FLAG_BUDGET_LOGIT_TOLERANCE)
    return {"threshold": float(sigmoid(logit)), "flagged_ticks": flagged,
            "budget": float(budget), "fallback": fallback, "starts": len(starts),
            "steps": [(float(sigmoid(z)), s) for z, s in steps]}


def perfect_detector_scores(value_function, grid) -> np.ndarray:
    """Per node of ``grid``: ``-V``, the score of a perfect detector for the BRT of
    ``value_function``: at threshold 0 it flags exactly where the (interpolated) BRT
    holds the state, the label the detector is trained on. With these scores the
    fallbacks' figures say what a perfect detector would leave to the fallback: the
    part of the gap that no better detector closes."""
    return -np.asarray(value_function.at(grid.states()), float).reshape(grid.shape)


def plot_tradeoff(curves, *, operating=None, alone=None, path, title="", noisy_curves=None,
                  noisy_operating=None):
    """Failure set against % of starts ended stopped (left) and against the distance
    travelled relative to the controller alone (right), one curve per fallback as the
    detector threshold sweeps (`tradeoff_curves`); ``operating``: {fallback: the row at
    the run's threshold}, marked with a star; ``alone``: the controller alone's failure
    set, a dashed line. Rows judged by distance too are plotted by their same-distance
    failure set (a slower vehicle on the same path only fails later), which for the
    controller alone is its failure set. ``noisy_curves``: the same curves rolled out
    with the detector's variation between nodes (``score_noise`` of `tradeoff_curves`),
    dashed in the same colour, and ``noisy_operating`` their rows at the run's
    threshold, hollow stars."""
    from reachwatch.diagrams.plots import plt, save_figure
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
