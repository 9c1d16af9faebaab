"""How far a detector's score between grid nodes strays from the interpolation of its
node values, as a random process along the path, for table rollouts of a guarded loop.

A table rollout reads the score interpolated from a grid. The real loop renders a
new image every tick, and at night the score of that image departs from the
interpolation in patches a few metres long: it rises above the threshold and falls
back, and a fallback that brakes while flagged and resumes when clear then stops
less and fails more than the tables say. `ScoreNoise` models the departure as an
Ornstein-Uhlenbeck process in the logit of the score over the distance travelled
(standard deviation ``sigma``, correlation ``exp(-d / length)`` after a distance d):
an aircraft standing still sees the same image, so its noise stays put. Its
``mean`` is the residual's average: the interpolation's bias. Fit it with
`fit_score_noise` from real runs (the real score along each run beside the table's
interpolation at the same states), then roll the tables out with it."""

import dataclasses as dc

import numpy as np

_EPS = 1e-4


def logit(p):
    """``log(p / (1 - p))`` with ``p`` clipped into ``[1e-4, 1 - 1e-4]``."""
    p = np.clip(np.asarray(p, float), _EPS, 1 - _EPS)
    return np.log(p / (1 - p))


def sigmoid(z):
    """``1 / (1 + exp(-z))``, the inverse of `logit` (without its clipping)."""
    return 1.0 / (1.0 + np.exp(-np.asarray(z, float)))


@dc.dataclass(frozen=True)
class ScoreNoise:
    """Logit-space Ornstein-Uhlenbeck noise over distance: ``sigma`` (its stationary
    standard deviation), ``length`` (its correlation length, in the unit of the
    distance passed to `step`, metres for the taxi) and ``mean`` (a constant offset)."""
    sigma: float
    length: float
    mean: float = 0.0

    def __post_init__(self):
        for name in ("sigma", "length", "mean"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) \
                    or not np.isfinite(value) or (value <= 0 and name != "mean"):
                kind = "a finite number" + (" > 0" if name != "mean" else "")
                raise ValueError(f"ScoreNoise.{name} must be {kind}, got {value!r}")

    def step(self, noise, moved, rng: np.random.Generator) -> np.ndarray:
        """The noise after moving ``moved`` (per path); ``noise=None`` draws it from the
        stationary distribution (the first tick)."""
        moved = np.abs(np.asarray(moved, float))
        if noise is None:
            return rng.normal(0.0, self.sigma, moved.shape)
        rho = np.exp(-moved / self.length)
        return rho * noise + np.sqrt(1.0 - rho ** 2) * self.sigma * rng.normal(0.0, 1.0, moved.shape)

    def apply(self, scores, noise) -> np.ndarray:
        """``scores`` (in [0, 1]) with ``mean + noise`` added to their logits, as
        ``s e^d / (1 - s + s e^d)``: without `logit`'s clipping, so a saturated score
        stays saturated and a score above ``1 - 1e-4`` (or below ``1e-4``) keeps its
        place against a threshold there (clipped, every such score was moved to the
        clip, whatever the noise)."""
        s = np.asarray(scores, float)
        gain = np.exp(np.clip(self.mean + np.asarray(noise, float), -700.0, 700.0))
        return s * gain / (1.0 - s + s * gain)


def fit_score_noise(real_scores, table_scores, travelled, *, max_lag: int = 64,
                    min_correlation: float = 0.1) -> ScoreNoise:
    """`ScoreNoise` from runs of the real loop: per run, the real score at each tick,
    the table's interpolated score at the same states, and the distance travelled up to
    each tick (all 1-D, one entry per tick). ``mean`` and ``sigma`` are the mean and
    standard deviation of the logit residual over all ticks; ``length`` the least-squares fit of ``log(c) = -d /
    length`` to the residual's autocorrelation c at lags of 1.. ``max_lag`` ticks
    (the residual about its mean over all runs, pairs pooled over runs; d the mean distance of
    the lag), over the lags before c first falls below ``min_correlation``."""
    runs = [tuple(np.asarray(a, float).ravel() for a in r)
            for r in zip(real_scores, table_scores, travelled)]
    if not runs or any(len({len(a) for a in r}) != 1 for r in runs):
        raise ValueError("real_scores, table_scores and travelled must be lists of runs, "
                         "each three arrays of equal length")
    residuals = [logit(real) - logit(table) for real, table, _ in runs]
    pooled = np.concatenate(residuals)
    if len(pooled) < 10 or not np.all(np.isfinite(pooled)):
        raise ValueError(f"need at least 10 finite ticks of scores, got {len(pooled)}")
    sigma, centre = float(np.std(pooled)), float(np.mean(pooled))
    if sigma <= 0:
        raise ValueError("the real scores equal the table's everywhere: no noise to fit")
    lags, logs = [], []
    for lag in range(1, max_lag + 1):
        pairs = [(r[:-lag] - centre, r[lag:] - centre, d[lag:] - d[:-lag])
                 for r, (_, _, d) in zip(residuals, runs) if len(r) > lag]
        if not pairs:
            break
        a, b, gap = (np.concatenate(p) for p in zip(*pairs))
        c = float(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)))
        if not np.isfinite(c) or c < min_correlation:
            break
        lags.append(float(np.mean(gap)))
        logs.append(np.log(c))
    lags, logs = np.asarray(lags), np.asarray(logs)
    if len(lags) == 0 or np.sum(lags * lags) <= 0:
        raise ValueError("the residual is uncorrelated from one tick to the next (or the runs "
                         "do not move): no correlation length to fit")
    slope = float(np.sum(lags * logs) / np.sum(lags * lags))
    if slope >= 0:
        raise ValueError("the residual's correlation does not fall with distance")
    return ScoreNoise(sigma=sigma, length=-1.0 / slope, mean=centre)


def fit_score_noise_on_runs(grid, score_table, states, scores, ticks, travelled, *,
                            left_out=None):
    """`fit_score_noise` from recorded real runs: per run its states ``(T, d)``, its
    detector scores ``(T,)`` and its logged ``ticks`` (the rest padding); the table's
    score is ``score_table`` (values on ``grid``'s nodes) interpolated at the same
    states, and ``travelled(states) -> (ticks,)`` the distance up to each tick. A run
    counts up to its first tick outside ``grid``'s box (the table has no score there:
    interpolation would take the edge's, and fit its error as noise); runs of fewer
    than two such ticks, and those ``left_out`` marks, are not used. Returns ``(noise,
    {"runs", "ticks", "cut_at_box"})`` (``cut_at_box``: runs cut short so); a
    ValueError when no run is left to fit on."""
    import torch
    from .interpolate import GridInterpolator
    table = torch.as_tensor(np.asarray(score_table, float).reshape(grid.shape))
    skip = np.zeros(len(ticks), bool) if left_out is None else np.asarray(left_out, bool)
    real, interpolated, along, cut = [], [], [], 0
    for path, score, n, skipped in zip(states, scores, ticks, skip):
        if skipped or n < 2:
            continue
        path = np.asarray(path, float)[:n]
        outside = np.flatnonzero(~grid.contains(path))
        if len(outside):
            n, path, cut = int(outside[0]), path[:outside[0]], cut + 1
            if n < 2:
                continue
        real.append(np.asarray(score, float)[:n])
        interpolated.append(GridInterpolator(grid, torch.as_tensor(path))(table).numpy())
        along.append(travelled(path))
    if not real:
        raise ValueError(f"no real run lasted two control ticks to fit the score noise on "
                         f"({len(ticks)} runs, {int(skip.sum())} left out)")
    return (fit_score_noise(real, interpolated, along),
            {"runs": len(real), "ticks": int(sum(len(r) for r in real)), "cut_at_box": cut})
