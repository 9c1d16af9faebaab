"""A monitor's operating threshold with a stated miss-rate bound on environments nobody
has seen, and the calibration of its risk. Pure functions of per-tick risks and run
outcomes; nothing here renders or knows the plant.

**Misses.** A failing run is *missed* at threshold ``tau`` when the monitor raised no
flag (risk ``>= tau``) at least ``lead`` s before the failure, ``lead`` being what the
fallback needs to act (e.g. the braking time). `warning_scores` reduces each failing
run to the largest risk among its ticks at least ``lead`` s before its failure, so a
run is missed exactly when that score is below ``tau``. A run that fails sooner than
``lead`` s after it starts has no such tick: no monitor could warn it in time with this
fallback (the oracle misses it too), so it is *unwarnable* and left out of the miss
rate by default (``warnable_only``); reports count such runs apart.

**The bound** (`conformal_threshold`). Environments, not runs, are the exchangeable
units: runs within one environment share its light and runway and are not exchangeable
with another's. Each calibration environment ``e`` gives a loss ``L_e(tau)``, the share
of its failing runs missed at ``tau`` (0 when none fail), which lies in [0, 1] and grows
with ``tau``. Conformal risk control (Angelopoulos, Bates, Fisch, Lei and Schuster, 2022)
picks the largest ``tau`` with ``n / (n + 1) * mean_e L_e(tau) + 1 / (n + 1) <= alpha``
over ``n`` calibration environments; then for a new environment exchangeable with them
(drawn from the same family, independently), ``E[L_new(tau)] <= alpha``: the expected
miss rate on an unseen environment is at most ``alpha``. The expectation is over the
draw of the calibration environments and the new one, not a promise for each
environment; `per_environment_bound` adds the distribution-free quantile statement
for one new environment. Nothing is assumed about the monitor: a poor one only buys
its bound with a low threshold (many needless flags).

**Environments where nothing fails.** Their loss is 0 at any threshold, so they count
in the expectation: when a share ``p`` of the family's environments has no failing run,
the expected miss rate *of an environment where some run fails* is bounded only by
``alpha / (1 - p)``. With ``given_failures`` the threshold is fixed on the calibration
environments with a warnable failing run alone; they are exchangeable with a new
environment that has one (selecting each environment on its own runs keeps
independent draws independent), so the bound ``alpha`` then holds for the miss rate a
user sees where failures happen, at the price of needing ``1 / alpha - 1`` such
environments and a lower threshold."""

import dataclasses as dc
import math
from typing import Sequence

import numpy as np
from scipy.optimize import minimize
from scipy.special import expit

from reachwatch.systems.history_model import logit_of, platt


def warning_scores(risks, times, failure_times, *, lead: float,
                   warnable_only: bool = True) -> np.ndarray:
    """One score per failing run: the largest risk at its ticks at least ``lead`` s
    before its failure. A run with no such tick is unwarnable: left out
    (``warnable_only``) or scored ``-inf`` (missed at any threshold). ``risks`` and
    ``times`` are per run (sequences of 1-d arrays of equal lengths); ``failure_times``
    per run (s; NaN for a run that did not fail: such runs are skipped)."""
    if not (np.isfinite(lead) and lead >= 0):
        raise ValueError(f"lead must be a finite number >= 0 s, got {lead}")
    if not len(risks) == len(times) == len(failure_times):
        raise ValueError(f"risks, times and failure_times need one entry per run, got "
                         f"{len(risks)}, {len(times)} and {len(failure_times)}")
    out = []
    for risk, time, failure in zip(risks, times, failure_times):
        if failure is None or not np.isfinite(failure):
            continue
        risk, time = np.asarray(risk, float), np.asarray(time, float)
        if risk.shape != time.shape or risk.ndim != 1:
            raise ValueError(f"a run's risks and times must be 1-d arrays of the same length, "
                             f"got {risk.shape} and {time.shape}")
        early = time <= failure - lead + 1e-9
        if np.isnan(risk[early]).any():
            raise ValueError(f"a failing run's risk is NaN at {int(np.isnan(risk[early]).sum())} "
                             f"of its ticks before its warning time: a NaN can neither warn "
                             f"nor be missed (a diverged training?)")
        if early.any():
            out.append(float(risk[early].max()))
        elif not warnable_only:
            out.append(-math.inf)
    return np.asarray(out, float)


def miss_rate(scores, threshold: float) -> float:
    """The share of failing runs (their `warning_scores`) missed at ``threshold``
    (NaN when there are none)."""
    scores = np.asarray(scores, float)
    return float(np.mean(~(scores >= threshold))) if len(scores) else float("nan")


@dc.dataclass
class ConformalThreshold:
    """A threshold chosen by `conformal_threshold`: ``threshold``, the target expected
    miss rate ``alpha`` it guarantees on a new environment of the family, the number of
    calibration environments it was fixed on (``environments``), how many of them had
    a warnable failing run (``failing_environments``) and how many such runs
    (``failing_runs``), the calibration environments' mean miss rate at it, and whether
    it was fixed on the environments with failures alone (``given_failures``)."""
    threshold: float
    alpha: float
    environments: int
    failing_runs: int
    calibration_miss_rate: float
    failing_environments: int = -1
    given_failures: bool = False

    def statement(self, lead: float) -> str:
        """The guarantee in one sentence, with its assumption and what it says about an
        environment where some run fails."""
        share = (f"{self.failing_environments} of them with a warnable failing run"
                 if self.failing_environments >= 0 else "")
        which = (f"the {self.environments} calibration environments with a warnable failing "
                 f"run" if self.given_failures else
                 f"{self.environments} calibration environments"
                 f"{' (' + share + ')' if share else ''}")
        head = (f"Threshold {self.threshold:.4g}, fixed on {which}, {self.failing_runs} "
                f"warnable failing runs: on a new environment drawn from the same family, "
                f"independently of them")
        what = (f"the expected share of its warnable failing runs (those lasting at least "
                f"{lead:.2f} s) flagged less than {lead:.2f} s before they fail is at most "
                f"{100 * self.alpha:.1f} %")
        how = ("(conformal risk control; environments exchangeable, each with as many runs "
               "drawn as in calibration)")
        if self.given_failures:
            return f"{head} and with a warnable failing run, {what} {how}."
        if self.failing_environments > 0 and self.failing_environments < self.environments:
            implied = self.alpha * self.environments / self.failing_environments
            return (f"{head}, {what}, counting an environment where no run fails as missing "
                    f"none {how}. On an environment where some run fails that is about "
                    f"{100 * min(1.0, implied):.1f} % (alpha over the calibration share of "
                    f"environments with failures).")
        if self.failing_environments == 0:
            return (f"{head}, {what} {how}. No calibration environment had a warnable "
                    f"failing run, so the bound is met by missing none where none fail: it "
                    f"says nothing of an environment where runs fail.")
        return f"{head}, {what} {how}."


def _losses(env_scores, threshold):
    return np.array([miss_rate(s, threshold) if len(s) else 0.0 for s in env_scores])


class NoConformalThreshold(ValueError):
    """No threshold reaches the target: too few calibration environments for it, or
    runs that fail before any warning can help."""


def conformal_threshold(env_scores: Sequence, alpha: float, *,
                        given_failures: bool = False) -> ConformalThreshold:
    """The largest threshold whose conformal-risk-control bound on the expected miss
    rate of a new environment is at most ``alpha`` (see the module's docstring).
    ``env_scores``: per calibration environment, the `warning_scores` of its failing
    runs (an environment without failures still counts, with loss 0; with
    ``given_failures`` it is left out, and the bound is for a new environment where
    some run fails). Raises
    ValueError when no threshold reaches ``alpha`` with so few environments, or (with
    unwarnable runs scored ``-inf``) so many runs that fail before any warning can help
    (both `NoConformalThreshold`), and for an ``alpha`` outside (0, 1)."""
    if not (0 < alpha < 1):
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    env_scores = [np.asarray(s, float) for s in env_scores]
    failing_environments = sum(len(s) > 0 for s in env_scores)
    if given_failures:
        env_scores = [s for s in env_scores if len(s)]
    n = len(env_scores)
    if n == 0 and not given_failures:
        raise ValueError("conformal_threshold needs at least one calibration environment")
    if 1.0 / (n + 1) > alpha:
        which = "calibration environments with a warnable failing run" if given_failures \
            else "calibration environments"
        raise NoConformalThreshold(
            f"{n} {which} cannot bound the miss rate at {alpha:g}: the bound is at least "
            f"1/(n+1) = {1 / (n + 1):.3f}; use at least {math.ceil(1 / alpha - 1)}")
    # 0 flags every tick; 1 flags only risks of exactly 1 (a float32 sigmoid saturates)
    candidates = np.unique(np.concatenate([s[np.isfinite(s)] for s in env_scores] + [[0.0, 1.0]]))
    best = None
    for tau in candidates:                      # the bound grows with tau: keep the largest
        bound = (float(np.sum(_losses(env_scores, tau))) + 1) / (n + 1)
        if bound <= alpha * (1 + 1e-12):        # at alpha exactly, despite float rounding
            best = tau
        else:
            break
    if best is None:
        raise NoConformalThreshold(
            f"no threshold bounds the expected miss rate at {alpha:g}: even flagging every "
            f"tick misses {np.mean(_losses(env_scores, 0.0)):.3f} of failing runs per "
            f"environment (they fail before a warning can help)")
    return ConformalThreshold(
        threshold=float(best), alpha=float(alpha), environments=n,
        failing_runs=int(sum(len(s) for s in env_scores)),
        calibration_miss_rate=float(np.mean(_losses(env_scores, best))),
        failing_environments=int(failing_environments), given_failures=bool(given_failures))


def per_environment_bound(env_miss_rates, delta: float) -> float:
    """A bound ``b`` on one new environment's miss rate at a threshold fixed without
    it: with probability at least ``1 - delta`` (over the draw of the calibration
    environments and the new one, all exchangeable) the new one's miss rate is at most
    ``b``, the ``ceil((n + 1)(1 - delta))``-th smallest of the ``n`` calibration
    environments' miss rates (1.0 when that rank exceeds ``n``: too few to say more).
    Exact only when the threshold was fixed without these environments too; at a
    threshold fitted on them (the study's) their rates are not exchangeable with a new
    one's, and the bound is optimistic."""
    rates = np.sort(np.asarray(env_miss_rates, float))
    if not (0 < delta < 1):
        raise ValueError(f"delta must be in (0, 1), got {delta}")
    rank = math.ceil((len(rates) + 1) * (1 - delta))
    return float(rates[rank - 1]) if rank <= len(rates) else 1.0


@dc.dataclass
class PlattCalibration:
    """``p = sigmoid(a * logit(q) + b)`` for a model's raw probability ``q`` (Platt
    scaling: two numbers fitted by maximum likelihood on held-out labels). The slope is
    fitted with ``a >= 0``, so calibration never reorders risks: a model whose raw
    risks rank the labels backwards gets ``a = 0``, one risk for every input (the base
    rate), not reversed risks that a threshold would read the wrong way round."""
    a: float = 1.0
    b: float = 0.0

    def __call__(self, q):
        return platt(q, self.a, self.b)

    @classmethod
    def fit(cls, q, labels) -> "PlattCalibration":
        q = np.asarray(q, float)
        y = np.asarray(labels, float)
        if q.shape != y.shape or q.ndim != 1 or len(q) == 0:
            raise ValueError(f"Platt scaling needs 1-d probabilities and labels of one "
                             f"length, got {q.shape} and {y.shape}")
        if y.min() == y.max():
            raise ValueError("Platt scaling needs labels of both classes")
        z = logit_of(q)

        def nll(p):
            s = p[0] * z + p[1]
            return float(np.sum(np.logaddexp(0, s) - y * s))

        def grad(p):
            r = expit(p[0] * z + p[1]) - y
            return np.array([np.sum(r * z), np.sum(r)])

        a, b = minimize(nll, np.array([1.0, 0.0]), jac=grad, method="L-BFGS-B",
                        bounds=[(0.0, None), (None, None)]).x
        return cls(a=float(a), b=float(b))


def reliability_curve(probabilities, labels, bins: int = 10):
    """``(mean predicted, observed frequency, count)`` per equal-width probability bin
    (empty bins left out): the points of a reliability diagram."""
    p, y = np.asarray(probabilities, float), np.asarray(labels, float)
    if p.shape != y.shape or p.ndim != 1:
        raise ValueError(f"probabilities and labels must be 1-d of one length, got "
                         f"{p.shape} and {y.shape}")
    index = np.minimum((p * bins).astype(int), bins - 1)
    counts = np.bincount(index, minlength=bins)
    kept = counts > 0
    mean_p = np.bincount(index, p, bins)[kept] / counts[kept]
    freq = np.bincount(index, y, bins)[kept] / counts[kept]
    return mean_p, freq, counts[kept]


def expected_calibration_error(probabilities, labels, bins: int = 10) -> float:
    """The count-weighted mean gap between predicted and observed frequency over
    `reliability_curve`'s bins."""
    mean_p, freq, counts = reliability_curve(probabilities, labels, bins)
    return float(np.sum(counts * np.abs(mean_p - freq)) / max(1, counts.sum()))


def brier_score(probabilities, labels) -> float:
    """Mean squared error of probabilities against 0/1 outcomes."""
    p, y = np.asarray(probabilities, float), np.asarray(labels, float)
    return float(np.mean((p - y) ** 2))
