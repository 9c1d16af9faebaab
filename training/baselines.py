"""Component-level baselines, judged against the same labels as the detectors: the
controller's prediction error (`EstimateError`), and the disagreement (variance) of an
ensemble of controllers."""

import dataclasses as dc
from typing import Callable, Optional, Tuple

import numpy as np


#: `EstimateError.refusal` of a controller with no ``estimate`` output (nothing amiss).
NO_ESTIMATE = "the controller has no estimate"


@dc.dataclass(frozen=True)
class EstimateError:
    """The controller's prediction error as an anomaly score:
    ``||(estimate - truth(state)) / scale||`` per sample. ``truth`` maps states ``(n,
    d)`` to what the controller estimates, at its true value, ``(n, k)``
    (`Application.true_estimate`); ``scale`` ``(k,)`` the units its errors are measured
    in (`Application.estimate_scale`; empty: 1 each); ``controller`` names the
    controller in tables. `estimate_error_of` makes one for an application."""
    truth: Callable
    scale: Tuple[float, ...] = ()
    controller: str = "the controller"

    def refusal(self, states, estimates) -> Optional[str]:
        """Why ``estimates`` ``(n, k)`` give no prediction-error baseline for ``states``,
        in a phrase; None when they do: they are the controller's estimate of them (as
        many numbers as `truth` gives), every one finite. A controller with no
        ``estimate`` output has none (the phrase says so); one of another size, or one
        whose estimate is NaN or infinite anywhere, has none either: an error measured
        against such a number would rank, and label, nothing that it means."""
        estimates, states = np.asarray(estimates), np.asarray(states, float)
        if states.ndim != 2 or not len(states) or estimates.ndim != 2 or \
                len(estimates) != len(states):
            return (f"no states to measure it at (states {states.shape}, estimates "
                    f"{estimates.shape})")
        if estimates.shape[1] == 0:
            return NO_ESTIMATE
        size = np.asarray(self.truth(states[:1])).shape[-1]
        if estimates.shape[1] != size:
            return (f"the controller's estimate has {estimates.shape[1]} numbers, the true "
                    f"estimate {size}")
        bad = int(np.sum(~np.all(np.isfinite(estimates.astype(float)), axis=1)))
        if bad:
            return (f"the controller's estimate is NaN or infinite at {bad} of "
                    f"{len(estimates)} states")
        return None

    def applies(self, states, estimates) -> bool:
        """Whether ``estimates`` give a prediction-error baseline (`refusal` is None)."""
        return self.refusal(states, estimates) is None

    def __call__(self, states, estimates) -> np.ndarray:
        estimates = np.asarray(estimates, float)
        refusal = self.refusal(states, estimates)
        if refusal is not None:
            raise ValueError(f"no prediction-error baseline of {self.controller}: {refusal}")
        truth = np.asarray(self.truth(np.asarray(states, float)), float)
        return np.linalg.norm((estimates - truth) / scale_of(self.scale, truth.shape[1]), axis=1)

    def labels(self, data, threshold: float) -> np.ndarray:
        """Training labels of the prediction-error baseline: 1 iff the error of
        ``data`` (a `LabelledData`) > ``threshold``."""
        return (self(data.states, data.estimates) > threshold).astype(np.uint8)


def estimate_error_of(application, controller: str = "the controller") -> Optional[EstimateError]:
    """``application``'s `EstimateError` (its `true_estimate` and `estimate_scale`),
    or None when it does not say what its controller estimates."""
    if application.true_estimate is None:
        return None
    scale = application.estimate_scale
    return EstimateError(truth=application.true_estimate,
                         scale=tuple(float(s) for s in (() if scale is None else scale)),
                         controller=controller)


def scale_of(scale, k: int) -> np.ndarray:
    """``scale`` as ``(k,)`` positive numbers (empty: 1 each); a ValueError otherwise."""
    out = np.ones(k) if not len(scale) else np.asarray(scale, float)
    if out.shape != (k,) or not np.all(np.isfinite(out) & (out > 0)):
        raise ValueError(f"an estimate's scale needs {k} finite numbers > 0 (or none), got "
                         f"{list(np.atleast_1d(scale))}")
    return out


def ensemble_variance(ensemble, scale=()) -> np.ndarray:
    """Sum over outputs of the members' variance, in units of ``scale`` (`scale_of`);
    ``(N, K, k)`` in, ``K >= 2`` members."""
    ensemble = np.asarray(ensemble)
    if ensemble.ndim != 3 or ensemble.shape[1] < 2:
        raise ValueError(f"an ensemble needs >= 2 members shaped (N, K, k), got {ensemble.shape}")
    return (ensemble / scale_of(scale, ensemble.shape[2])).var(axis=1).sum(axis=1)
