"""Component-level baselines, judged against the same BRT labels: TaxiNet prediction
error, and the disagreement (variance) of an ensemble of TaxiNets."""

import numpy as np

#: TaxiNet's output scales (m, deg): errors and variances are measured in these units.
SCALE = np.array([10.0, 30.0])


def has_pose_estimate(data) -> bool:
    """Whether a dataset's controller estimates the pose as TaxiNet does, ``[px_hat m,
    theta_hat deg]`` (an ``estimate`` output of size 2): the prediction-error baseline
    needs that, and is skipped for a controller without it."""
    return data.estimates.ndim == 2 and data.estimates.shape[1] == 2


def prediction_error(states, estimates) -> np.ndarray:
    """Scaled estimate error ``||([px_hat, theta_hat] - [px, theta_deg]) / (10 m, 30 deg)||``."""
    truth = np.column_stack([states[:, 0], np.rad2deg(states[:, 2])])
    return np.linalg.norm((np.asarray(estimates) - truth) / SCALE, axis=1)


def ensemble_variance(ensemble) -> np.ndarray:
    """Sum over outputs of the members' variance, in scaled units; ``(N, K, 2)`` in."""
    ensemble = np.asarray(ensemble)
    if ensemble.ndim != 3 or ensemble.shape[1] < 2:
        raise ValueError(f"an ensemble needs >= 2 members shaped (N, K, 2), got {ensemble.shape}")
    return (ensemble / SCALE).var(axis=1).sum(axis=1)


def prediction_error_labels(data, threshold: float) -> np.ndarray:
    """Training labels of the prediction-error baseline: 1 iff the error > threshold."""
    return (prediction_error(data.states, data.estimates) > threshold).astype(np.uint8)
